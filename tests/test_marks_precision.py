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


def test_projective_prediction_takes_up_a_model_change_and_leaves_noise_its_redundancy():
    """The small grid's departures: a residual field that is a change of the projective model
    is taken up whole; independent errors keep on average 2M - 8 of their 2M squared units."""
    from softplot.marks.grid import apply_h
    from softplot.marks.precision import projective_prediction

    g = np.array([-23.0, 0.0, 23.0])
    film = np.stack(np.meshgrid(g, 0.75 * g), -1).reshape(-1, 2)  # a 3 x 3 grid, mm
    H = np.array([[30.0, 0.4, 1500.0], [-0.4, 30.1, 1100.0], [2e-5, -1e-5, 1.0]])
    dH = np.array([[1e-3, -2e-4, 0.3], [3e-4, 2e-3, -0.2], [1e-6, 2e-6, 0.0]])
    r = apply_h(H + dH, film) - apply_h(H, film)  # a model change: px
    pred = projective_prediction(H)
    np.testing.assert_allclose(pred(film, r), r, atol=1e-3 * np.abs(r).max())
    e = np.random.default_rng(3).normal(0.0, 0.1, (4000, len(film), 2))
    left = np.mean(np.sum((e - pred(film, e)) ** 2, (1, 2))) / 0.1 ** 2
    assert left == pytest.approx(2 * len(film) - 8, rel=0.03)


def _pentax_jpeg_normalised(monkeypatch=None):
    """Pooled normalised-error RMS of the sweep's Pentax 645 (3 x 3) JPEG and web-size copies
    among its first 130 seeds (``softplot.synthetic.sweep``)."""
    from softplot.synthetic.sweep import make_case, run_case

    z2, n = 0.0, 0
    for seed in range(130):
        case = make_case(seed)
        if case.camera != "pentax-645" or not {"jpeg", "web-copy"} & set(case.conditions):
            continue
        sc, det = run_case(case)
        assert det is not None, case.describe()
        z2, n = z2 + float(np.sum(sc.z2)), n + len(sc.z2)
    assert n >= 80
    return float(np.sqrt(z2 / n))


def test_small_grids_variance_factor_from_the_global_model(monkeypatch):
    """A 3 x 3 grid has too few crosses for the neighbours' local fits: its variance factor
    comes from the departures from the global projective model. On the sweep's Pentax JPEG
    copies the normalised errors then have an RMS within 0.67-1.5, with the JPEG
    quantisation's share of the covariances (softplot.marks.jpegq) and without it; without
    either (the factor 1 below 12 crosses) above 1.5."""
    z = _pentax_jpeg_normalised()
    assert 0.67 <= z <= 1.5, z
    J = importlib.import_module("softplot.marks.jpegq")
    monkeypatch.setattr(J, "of_scan", lambda scan: None)
    z = _pentax_jpeg_normalised()
    assert 0.67 <= z <= 1.5, z
    V = importlib.import_module("softplot.marks.validation")
    P = importlib.import_module("softplot.marks.precision")
    monkeypatch.setattr(V, "variance_factor",
                        lambda *a, H=None, **k: P.variance_factor(*a, **k))
    assert _pentax_jpeg_normalised() > 1.5
