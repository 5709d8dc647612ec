"""Shared plumbing of the bundle, calibrate and triangulate commands (no numerics)."""

from __future__ import annotations

import json
from pathlib import Path

import click
import numpy as np

from softplot.errors import SoftplotError


def lm_progress(desc: str):
    """An LMOptions.progress callback drawing a tqdm bar on stderr; returns (callback, close)."""
    from tqdm import tqdm

    bar = tqdm(desc=desc, unit="it", leave=False, disable=None)

    def cb(rec):
        bar.update(1)
        bar.set_postfix(cost=f"{rec['cost']:.6g}")

    return cb, bar.close


def guard_output(out, inputs) -> Path | None:
    """Refuse to write over an input file."""
    if out is None:
        return None
    p = Path(out).resolve()
    for i in inputs:
        if i is not None and Path(i).exists() and Path(i).resolve() == p:
            raise SoftplotError(f"refusing to overwrite the input file {out}")
    return p


def project_inputs(folder) -> list:
    root = Path(folder)
    return [root / f for f in ("cameras.toml", "photos.csv", "observations.csv", "control.csv")]


def _clean(o):
    if isinstance(o, dict):
        return {k: _clean(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_clean(v) for v in o]
    if isinstance(o, np.ndarray):
        return _clean(o.tolist())
    if isinstance(o, (np.floating, float)):
        return None if not np.isfinite(o) else float(o)
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.bool_):
        return bool(o)
    return o


def write_json(obj, path) -> None:
    Path(path).write_text(json.dumps(_clean(obj), indent=1) + "\n", encoding="utf-8")
    click.echo(f"wrote {path}", err=True)


def parse_free(text: str | None):
    if text is None:
        return None
    from softplot.orientation.bundle import INTRINSICS

    names = tuple(t.strip() for t in text.split(",") if t.strip())
    bad = [n for n in names if n not in INTRINSICS]
    if bad:
        raise SoftplotError(f"--free: unknown parameter(s) {bad}; use {', '.join(INTRINSICS)}")
    return names
