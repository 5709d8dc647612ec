"""Honest precision: each measured cross's reported 2 x 2 covariance matches its real error.

The normalised error ``e^T C^-1 e / 2`` of a cross has mean 1 when ``C`` is its true
covariance; over the 121 crosses of a render its RMS must lie within 0.7-1.4. Film grain
blurred by the scanner makes neighbouring pixels' noise correlated (fewer independent pixels
than pixels): a covariance that counts every pixel as independent is then 2-3x too small
(checked below, so that the test can fail)."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from softplot.io import Scan
from softplot.marks import detect
from softplot.marks import lsm as lsm_mod
from softplot.marks import measure as measure_mod
from softplot.synthetic import ScanSpec, render_scan

CASES = {
    "white noise": ScanSpec(dpi=600),
    "grain, blur 1.5 px": ScanSpec(dpi=600, grain_sigma=0.04, blur_sigma_px=1.5,
                                   noise_sigma=0.003),
    "grain, blur 2.5 px": ScanSpec(dpi=600, grain_sigma=0.05, blur_sigma_px=2.5,
                                   noise_sigma=0.003),
    "busy scene": ScanSpec(dpi=600, scene="busy"),
}


def _normalised(spec, seed, monkeypatch=None):
    img, truth = render_scan("rollei-6006", spec, seed)
    det = detect(Scan.from_array(img, dpi=spec.dpi), "rollei-6006")
    tm = {m["name"]: m for m in truth["marks"]}
    z2 = []
    for i, name in enumerate(det.name):
        t = tm[name]
        if (det.status[i] != "measured" or det.kind[i] != "reseau" or t["state"] != "visible"
                or t["damaged"] or t["arms"] != 2):
            continue
        e = det.xy[i] - (t["x"], t["y"])
        C = det.cov[i]
        assert np.all(np.linalg.eigvalsh(C) > 0)
        z2.append(float(e @ np.linalg.solve(C, e)) / 2)
    assert len(z2) >= 100
    return float(np.sqrt(np.mean(z2)))


@pytest.mark.parametrize("name", list(CASES))
def test_normalised_errors_have_rms_near_one(name):
    z = _normalised(CASES[name], 5)
    assert 0.7 <= z <= 1.4, f"{name}: normalised-error RMS {z:.2f}"


def test_independent_pixels_would_understate_grain(monkeypatch):
    """Without the residuals' correlation the same render's covariances are far too small
    (the scan's variance factor, :mod:`softplot.marks.precision`, held at 1: it would find
    the shortfall from the grid)."""
    f = lsm_mod.lsm
    monkeypatch.setattr(measure_mod, "lsm", lambda *a, **k: f(*a, **{**k, "correlated": False}))
    monkeypatch.setattr(importlib.import_module("softplot.marks.validation"), "variance_factor",
                        lambda *a, **k: 1.0)
    z = _normalised(CASES["grain, blur 1.5 px"], 5)
    assert z > 2.0


def test_grid_redundancy_finds_what_independent_pixels_understate(monkeypatch):
    """With covariances that count every pixel as independent (2-3x too small under grain),
    the scan's variance factor from the crosses' departures restores honest ones."""
    f = lsm_mod.lsm
    monkeypatch.setattr(measure_mod, "lsm", lambda *a, **k: f(*a, **{**k, "correlated": False}))
    z = _normalised(CASES["grain, blur 1.5 px"], 5)
    assert 0.7 <= z <= 1.4, z
