"""The neighbours' predictions asked for again within one validation are computed once
(:func:`softplot.marks.neighbours.remembered`) and are the values a new computation gives."""

from __future__ import annotations

from contextlib import nullcontext

import numpy as np

from softplot.marks import neighbours


def _grid(seed=2):
    """Film mm of an 11 x 11 reseau of 5 mm with a tenth of the crosses missing, and
    residuals (px) of a smooth deformation plus noise."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(11.0), np.arange(11.0)), -1).reshape(-1, 2) * 5.0
    film = g[rng.random(len(g)) > 0.1]
    x, y = film.T / 50.0
    field = np.stack([0.2 * x * y - 0.1 * x**2, 0.15 * y**2 + 0.05 * x], 1)
    return film, field, field + rng.normal(0, 0.01, field.shape), rng


def _counting(monkeypatch):
    calls = []
    real = neighbours._local_prediction

    def spy(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(neighbours, "_local_prediction", spy)
    return calls


def test_a_prediction_asked_again_is_computed_once(monkeypatch):
    film, field, r, rng = _grid()
    sig = rng.uniform(0.005, 0.02, len(film))
    z = rng.standard_normal((16,) + film.shape)
    ref = [neighbours.local_prediction(film, r, sigma=sig),
           neighbours.local_prediction(film, z, sigma=sig)]
    # the leave-one-out prediction follows the smooth field (a test of what is remembered)
    assert np.sqrt(np.mean((ref[0] - field) ** 2)) < 0.01
    calls = _counting(monkeypatch)
    with neighbours.remembered():
        a = neighbours.local_prediction(film, r, sigma=sig)
        a[:] = 99.0  # the caller's copy: what is remembered is not changed
        b = neighbours.local_prediction(film, z, sigma=sig)
        c = neighbours.local_prediction(film, r.copy(), sigma=sig.copy())
        d = neighbours.local_prediction(film, z, sigma=sig)
        assert len(calls) == 2
        r2 = r.copy()
        r2[5] += 0.5  # other inputs: computed again
        e = neighbours.local_prediction(film, r2, sigma=sig)
        f = neighbours.local_prediction(film, r, sigma=None)
        assert len(calls) == 4
    assert np.array_equal(b, ref[1]) and np.array_equal(d, ref[1])
    assert np.array_equal(c, ref[0])
    assert np.array_equal(e, neighbours._local_prediction(film, r2, sigma=sig))
    assert np.array_equal(f, neighbours._local_prediction(film, r))
    # outside the context every call computes
    neighbours.local_prediction(film, r, sigma=sig)
    neighbours.local_prediction(film, r, sigma=sig)
    assert len(calls) == 8


def test_validation_remembering_its_predictions_is_the_same(monkeypatch):
    """A busy scan's validation (outlier test, rescue, lone bars, variance factor) with its
    repeated predictions computed once gives the same crosses, positions and covariances as
    computing each, with fewer computations; and the crosses are where the truth puts them."""
    from softplot.io import Scan
    from softplot.marks import detect, validation
    from softplot.synthetic import ScanSpec, render_scan

    img, truth = render_scan("rollei-6006", ScanSpec(dpi=900, rotation_deg=1.5, scene="busy"),
                             11)
    sc = Scan.from_array(img, dpi=900)
    calls = _counting(monkeypatch)
    out, n = {}, {}
    for memo in (False, True):
        monkeypatch.setattr(validation, "remembered",
                            neighbours.remembered if memo else nullcontext)
        calls.clear()
        out[memo] = detect(sc, "rollei-6006")
        n[memo] = len(calls)
    a, b = out[True], out[False]
    assert list(a.status) == list(b.status)
    ok = np.array([s == "measured" for s in a.status])
    assert ok.sum() >= 110
    # (to the float rounding of arrays placed elsewhere in memory: 1e-6 px)
    assert np.abs(a.xy[ok] - b.xy[ok]).max() < 1e-6
    assert np.abs(a.cov[ok] - b.cov[ok]).max() < 1e-6 * np.abs(b.cov[ok]).max()
    assert n[True] < n[False], n
    tm = {m["name"]: (m["x"], m["y"]) for m in truth["marks"]}
    err = np.array([a.xy[i] - tm[nm] for i, nm in enumerate(a.name) if ok[i]])
    assert np.sqrt(np.mean(err**2)) < 0.1
