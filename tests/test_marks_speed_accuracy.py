"""The fast paths of mark detection over busy scenes give what the slower ones gave.

* the compiled joint-scene solve (:mod:`softplot.marks.scene_tv`) at every blur radius (its
  9-tap path for radii up to 4 px, the general loop beyond) agrees with the NumPy path;
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
