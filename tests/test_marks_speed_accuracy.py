"""The fast paths of mark detection over busy scenes give what the slower ones gave.

* the compiled joint-scene solve (:mod:`softplot.marks.scene_tv`) at every blur radius (its
  7- and 9-tap paths for radii up to 3 and 4 px, the general loop beyond) agrees with the
  NumPy path;
* ``scene="auto"`` on busy scenes, which refits with the joint scene only the crosses with a
  scene edge in their footprint, is as accurate as the joint estimate on every cross
  (``scene="joint"``, what ``auto`` did before) while solving the scene under far fewer
  patches. (The whole accuracy sweep's busy renders, compared the same way, are in
  docs/benchmarks.md, "Busy scenes".)
"""

from __future__ import annotations

import numpy as np
import pytest

from softplot.marks import kernels, scene_tv


def _patches(n=3, h=47, w=43, seed=5):
    rng = np.random.default_rng(seed)
    T = np.zeros((n, h, w), np.float32)
    T[:, 22:25, 4:39] = 1.0
    T[:, 4:43, 20:23] = 1.0
    g = rng.random((n, h, w)).astype(np.float32)
    B0 = rng.random((n, h, w)).astype(np.float32)
    return g, T, B0, rng.random(n).astype(np.float32), np.full(n, 0.05, np.float32)


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
@pytest.mark.parametrize("s_e", [0.2, 0.45, 0.7, 1.0, 1.3, 2.1])
def test_scene_solve_blur_matches_numpy_at_every_radius(s_e):
    """Radii 1..7 px (``gauss_taps``: ceil(3 s_e)): the compiled solve, whole patch and band,
    equals the NumPy path to float32 rounding, and the blurred scene it returns is the NumPy
    blur of its scene."""
    g, T, B0, level, mu = _patches()
    for band in (np.inf, 4.0):
        a = scene_tv.deconv_tv(g, T, level, B0, mu, s_e, 15, compiled=True, band_px=band)
        b = scene_tv.deconv_tv(g, T, level, B0, mu, s_e, 15, compiled=False, band_px=band)
        for x, y in zip(a, b, strict=True):
            assert np.abs(x - y).max() < 2e-5
        B, X = a
        assert np.abs(B - scene_tv._blur_np(X, scene_tv.gauss_taps(s_e))).max() < 2e-6


def _errors(det, truth):
    tm = {m["name"]: m for m in truth["marks"]}
    return {nm: det.xy[i] - (tm[nm]["x"], tm[nm]["y"]) for i, nm in enumerate(det.name)
            if det.status[i] == "measured" and tm[nm]["visible"]}


def _rms(errs):
    e = np.concatenate([np.array(list(d.values())) for d in errs])
    return float(np.sqrt(np.mean(e**2)))


def test_busy_scene_auto_is_as_accurate_as_the_joint_estimate_on_every_cross(monkeypatch):
    """Busy scenes: ``scene="auto"`` refits with the joint scene only the crosses with a scene
    edge in their footprint (``scene_tv.EDGE_MIN``), ``scene="joint"`` every cross (the
    estimate of before). Pooled over three renders the fast path's RMS error against the
    truth is within 3 % of the joint estimate's, the same crosses are measured (at most one
    more or fewer per render), no cross differs by more than 0.05 px, and the fast path solves
    the scene under at most 70 % of the patches; the opening alone is clearly worse (so the
    renders do test the scene model)."""
    from softplot.io import Scan
    from softplot.marks import detect
    from softplot.synthetic import ScanSpec, render_scan

    solved = {"n": 0}
    real = scene_tv.deconv_tv

    def spy(g, *a, **k):
        solved["n"] += len(g)
        return real(g, *a, **k)

    monkeypatch.setattr(scene_tv, "deconv_tv", spy)
    errs = {"joint": [], "auto": [], "opening": []}
    patches = {"joint": 0, "auto": 0}
    for seed in (11, 12, 13):
        img, truth = render_scan("rollei-6006", ScanSpec(dpi=1000, rotation_deg=1.5,
                                                         scene="busy"), seed)
        sc = Scan.from_array(img, dpi=1000)
        for mode in errs:
            solved["n"] = 0
            det = detect(sc, "rollei-6006", scene=mode)
            if mode in patches:
                patches[mode] += solved["n"]
                assert det.scene == "joint"
            errs[mode].append(_errors(det, truth))
        j, a = errs["joint"][-1], errs["auto"][-1]
        assert len(set(j) ^ set(a)) <= 1
        both = sorted(set(j) & set(a))
        assert max(np.hypot(*(j[k] - a[k])) for k in both) < 0.05
    r = {k: _rms(v) for k, v in errs.items()}
    assert r["auto"] <= 1.03 * r["joint"], r
    assert r["opening"] > 1.15 * r["joint"], r
    assert patches["auto"] <= 0.7 * patches["joint"], patches
