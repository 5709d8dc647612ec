"""Shared test helpers.

Accuracy sweeps are parametrised over many renders. The default run samples a deterministic
subset of every sweep (so `make test` stays within minutes on 2 cores); ``SOFTPLOT_FULL=1``
runs every case. Sampled cases are the same on every run.
"""

from __future__ import annotations

import os
import random

import pytest

FULL = os.environ.get("SOFTPLOT_FULL", "") not in ("", "0")


def sweep(cases: list, k: int, seed: int = 0) -> list:
    """All ``cases`` when SOFTPLOT_FULL=1, else a fixed sample of ``k`` of them.

    Cases not sampled are still collected, marked ``slow`` and skipped with a reason, so the
    report shows what the full sweep would add.
    """
    cases = list(cases)
    if FULL or len(cases) <= k:
        return cases
    keep = set(random.Random(seed).sample(range(len(cases)), k))
    out = []
    for i, c in enumerate(cases):
        if i in keep:
            out.append(c)
        else:
            out.append(
                pytest.param(
                    *(c if isinstance(c, tuple) else (c,)),
                    marks=[
                        pytest.mark.slow,
                        pytest.mark.skip(reason="sampled out; SOFTPLOT_FULL=1"),
                    ],
                )
            )
    return out
