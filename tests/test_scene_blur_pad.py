"""The joint scene solve's blur over padded rows (issue 20 point 5, busy-scene speed): the
kernel keeps ``Xb`` and ``t1`` with their rows starting at column :data:`scene_tv.O` and their
edge values repeated into the columns either side, so that the blur's horizontal pass reads
them straight from the array (:func:`softplot.marks.scene_tv._blur_p`) instead of copying
each row into a buffer first. It must give the blur of the unpadded rows bit for bit: the
detections then are those of the detector before."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.marks import kernels, scene_tv

pytestmark = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")


def _padded(a: np.ndarray, right: int) -> np.ndarray:
    """``a`` (h, w) pixel system with :data:`scene_tv.O` columns before each row and
    ``right`` after it, each holding the row's first / last value (the replicated edge)."""
    return np.pad(a, ((0, 0), (scene_tv.O, right)), mode="edge")


@pytest.mark.parametrize("s_e", [0.2, 0.45, 0.7, 1.0, 1.3, 1.7])
@pytest.mark.parametrize("w", [8, 13, 24, 31])
def test_padded_blur_is_the_blur_bit_for_bit(s_e, w):
    """Radii 1-6 px (``gauss_taps``: ceil(3 s_e); 1-4 read the padded rows, above 4 the
    general loop), widths with and without a remainder modulo 8: the same float32 values as
    :func:`softplot.marks.scene_tv._blur` of the unpadded rows, exactly."""
    rng = np.random.default_rng(int(10 * s_e) + w)
    h = 19
    k = scene_tv.gauss_taps(s_e)
    r = (len(k) - 1) // 2
    src = rng.random((h, w)).astype(np.float32)
    ref = np.zeros((h, w), np.float32)
    scene_tv._blur(src, ref, np.zeros((h, w), np.float32),
                   np.zeros(w + 2 * max(r, 4), np.float32), k, r, h, w)
    got = np.zeros((h, w), np.float32)
    scene_tv._blur_p(_padded(src, 8), got, np.zeros((h, w), np.float32),
                     np.zeros(w + 2 * max(r, 4), np.float32), k, r, h, w)
    assert np.array_equal(got, ref)
    # and it is a blur of that row: not the unblurred values (the test can tell; at
    # s_e = 0.2 the outer taps are below 1e-5)
    assert np.abs(got - src).max() > (1e-6 if s_e < 0.3 else 1e-3)


def test_padded_blur_reads_the_pad():
    """The horizontal pass takes the columns before and after a row from the array: a wrong
    value in the pad (not the row's edge value) changes the blur of the first and last
    columns, and only those within the radius (the test of the pad's role, and that the
    kernel must keep it filled)."""
    rng = np.random.default_rng(1)
    h, w = 9, 16
    k = scene_tv.gauss_taps(1.0)  # r = 3
    src = _padded(rng.random((h, w)).astype(np.float32), 8)
    bad = src.copy()
    bad[:, scene_tv.O - 1] += 1.0  # the column just before each row

    def blur(a):
        out = np.zeros((h, w), np.float32)
        scene_tv._blur_p(a, out, np.zeros((h, w), np.float32), np.zeros(w + 8, np.float32),
                         k, 3, h, w)
        return out

    diff = np.abs(blur(bad) - blur(src)).max(0)
    assert np.all(diff[:3] > 1e-3)
    assert np.all(diff[3:] == 0.0)


def test_scene_solve_pad_edges_match_numpy():
    """The whole solve, 60 iterations on patches whose first and last columns carry a scene
    edge (where a stale pad would show): the compiled kernel's scene equals the NumPy path's
    (which pads nothing) to float32 rounding, at 7 and 9 taps."""
    rng = np.random.default_rng(3)
    n, h, w = 2, 23, 29
    X = np.where(np.arange(w)[None, None, :] < 2, 0.9, 0.2) * np.ones((n, h, 1))
    X[:, :, -2:] = 0.7
    T = np.zeros((n, h, w), np.float32)
    T[:, 10:13, :] = 1.0
    for s_e in (1.0, 1.3):
        k = scene_tv.gauss_taps(s_e)
        g = scene_tv._blur_np(X.astype(np.float32), k) * (1 - T) + 0.05 * T
        g = (g + rng.normal(0, 0.01, g.shape)).astype(np.float32)
        B0 = np.full((n, h, w), 0.5, np.float32)
        a = scene_tv.deconv_tv(g, T, np.full(n, 0.05), B0, np.full(n, 0.01), s_e, 60,
                               compiled=True)
        b = scene_tv.deconv_tv(g, T, np.full(n, 0.05), B0, np.full(n, 0.01), s_e, 60,
                               compiled=False)
        for x, y in zip(a, b, strict=True):
            assert np.abs(x - y).max() < 5e-5
            assert np.abs(x[..., [0, 1, -2, -1]] - y[..., [0, 1, -2, -1]]).max() < 5e-5
