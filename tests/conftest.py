"""Shared test helpers.

Accuracy sweeps are parametrised over many renders. The default run samples a deterministic
subset of every sweep (so `make test` stays within minutes on 2 cores); ``SOFTPLOT_FULL=1``
runs every case. Sampled cases are the same on every run.

The detection sweep's pooled rate (issue 3 point 6) is a figure of all its cases together;
the hooks at the end collect each case's counts (with xdist, from the workers' reports) and
fail the run when it is below 99.5 %.
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


#: ``record_property`` key of a detection-sweep case: (visible crosses, measured correctly)
POOLED_RATE_KEY = "pooled_detection"
#: issue 3 point 6: at least this share of the visible crosses of the sweep measured
POOLED_RATE = 0.995
_pooled: list[tuple[str, int, int]] = []


def pytest_runtest_logreport(report):
    """Collect the detection counts of every sweep case (in the controller with xdist too:
    a worker's report carries its ``user_properties``)."""
    if report.when != "call":
        return
    for key, val in report.user_properties:
        if key == POOLED_RATE_KEY:
            _pooled.append((report.nodeid, int(val[0]), int(val[1])))


def _pooled_rate():
    vis = sum(v for _, v, _ in _pooled)
    got = sum(m for _, _, m in _pooled)
    return vis, got


def pytest_terminal_summary(terminalreporter):
    vis, got = _pooled_rate()
    if vis:
        terminalreporter.write_line(
            f"detection sweep, pooled: {got} of {vis} visible crosses measured "
            f"({100.0 * got / vis:.2f} %, at least {100 * POOLED_RATE:.1f} % required) over "
            f"{len(_pooled)} renders")


def pytest_sessionfinish(session, exitstatus):
    """Fail the run when the pooled detection rate of the sweep's cases that ran is below
    :data:`POOLED_RATE` (each case checks its own rate too, :mod:`test_marks_accuracy`):
    the rate is a share of all the visible crosses, so it is checked over all of them."""
    if hasattr(session.config, "workerinput"):  # an xdist worker: the controller decides
        return
    vis, got = _pooled_rate()
    if vis and got < POOLED_RATE * vis:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
        tr = session.config.pluginmanager.get_plugin("terminalreporter")
        tr.ensure_newline()
        tr.write_line(
            f"FAILED: detection sweep, pooled rate {100.0 * got / vis:.2f} % < "
            f"{100 * POOLED_RATE:.1f} % ({vis - got} of {vis} visible crosses not measured)")


def across_over_bound(m: dict, truth: dict) -> float:
    """The error of a measured one-armed cross ``m`` (detection JSON entry, scan pixels)
    across its bar over the bar's one-dimensional bound: the per-axis Cramér-Rao bound of the
    cross as drawn (its true arm length and line width, the render's blur and noise, the
    truth's local contrast). Across the bar is the normal, in the pixel system, of the bar's
    film axis as the truth mapping takes it there."""
    import numpy as np

    from softplot.marks.crb import centre_crb, effective_noise
    from softplot.marks.template import MarkShape
    from softplot.synthetic.mapping import TruthMapping

    t = next(q for q in truth["marks"] if q["name"] == m["name"])
    r, ppm = truth["render"], truth["dpi"] / 25.4
    noise = effective_noise(r["noise_sigma"], truth["bit_depth"])
    along = TruthMapping.from_truth(truth).jacobian(np.array([[t["film_x"], t["film_y"]]]))[0][
        :, 0 if t["arm_axis"] == "x" else 1]
    nv = np.array([-along[1], along[0]]) / np.hypot(*along)
    shape = MarkShape("cross", length=t["arm_length_mm"] * ppm, width=t["line_width_mm"] * ppm)
    crb = centre_crb(shape, r["blur_sigma_px"], abs(t["contrast"]), noise, phases=2)
    return float(np.array([m["x"] - t["x"], m["y"] - t["y"]]) @ nv) / crb


@pytest.fixture(scope="module")
def renders(tmp_path_factory):
    """A folder the robustness sweep's renders are kept in, one per test module (each seed
    rendered once for a test's counterfactual and real runs)."""
    return tmp_path_factory.mktemp("renders")


def run_sweep_case(seed: int, renders):
    """The robustness sweep's render ``seed`` detected and scored (renders kept in the folder
    ``renders``): its :class:`~softplot.synthetic.sweep.Score` and the detection's JSON,
    after checking it gave a result with no wrong row/col and no claim."""
    from softplot.synthetic.sweep import make_case, run_case

    sc, det = run_case(make_case(seed), cache=renders)
    assert sc.result and not sc.wrong and not sc.claimed, (sc.error, sc.wrong, sc.claimed)
    return sc, det.to_json()
