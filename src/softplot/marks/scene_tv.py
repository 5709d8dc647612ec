"""The scene under a fitted cross, estimated jointly with it: TV-regularised deconvolution.

The grey opening of :func:`softplot.marks.measure.scene_background` removes the bars with a disc
and fills the footprint from the scene around it. Where a scene edge runs under or along a bar,
or crosses it obliquely, the disc puts the edge at the wrong place inside the footprint, and the
error, antisymmetric across the bar, shifts the centre (docs/accuracy.md, "Open gap: busy
scenes"). Here the fitted cross tells which pixels see the scene and how much of it: LSM's
image model is ``g = B (1 - T) + m T`` with ``B = G * X`` the optically blurred scene ``X``
(``G`` the scanner's Gaussian of the edge spread ``s_e``). With the cross held (``T`` and the
mark level ``m`` from a first fit), the scene is the minimiser of::

    1/2 sum_p ((1 - T) (G * X) + m T - g)^2 + mu TV(X)

over the whole patch: the data term is exactly LSM's residual; the total variation of the
unblurred scene is the prior of a scene of sharp-edged areas (buildings, fields, roads). Where
the bar hides the scene (``T`` near 1) the prior continues the edges seen around it by the
shortest way, straight across the bar; in the bar's blur tails the data put the edges where they
are; TV's threshold keeps a small misfit of the cross from being explained as scene (a weak
edge costs more total variation than it saves in residual). ``mu`` is a multiple of the patch's
noise. The problem is solved by the primal-dual method of Chambolle and Pock (2011) from the
opening's estimate, a fixed number of iterations.

The passes after the first start from the last pass's scene (:data:`ITERATIONS_WARM`
iterations, :func:`iterations`). The solve can be restricted to the band around the mark
(``band_px``, :func:`band_rows`): the scene beyond it, which the mark does not reach, is held
at the starting estimate (an option: not the default, see :data:`BAND_PX`).

All arrays are patches ``(N, h, w)`` in the pixel system of the scan (row = y, column = x), grey
units of :mod:`softplot.marks.lsm`. The compiled kernel (numba, :data:`kernels.AVAILABLE`) and the
NumPy path give the same values to float32 rounding
(``tests/test_marks_units.py::test_scene_tv_kernel_matches_numpy``).
"""

from __future__ import annotations

import math
import warnings

import cv2
import numpy as np
from scipy.ndimage import correlate1d

from softplot import runtime
from softplot.marks import kernels

__all__ = ["gauss_taps", "deconv_tv", "iterations", "ITERATIONS", "MU"]

#: iterations of the primal-dual solver of the first joint-scene pass (from the opening's
#: estimate): a pixel without data moves by at most ``4 tau mu`` per iteration, and with 20
#: the busy renders' crosses with a scene edge along a bar stopped short of the joint optimum
ITERATIONS = 60
#: iterations of the passes after the first, which start from the last pass's scene
#: (:func:`iterations`; fewer lost accuracy on the noisiest busy render of the accuracy
#: sweep, docs/benchmarks.md "Busy scenes")
ITERATIONS_WARM = 60


def iterations(p: int) -> int:
    """Solver iterations of joint-scene pass ``p`` (0: from the opening's estimate)."""
    return ITERATIONS if p == 0 else ITERATIONS_WARM


#: ``scene="auto"`` on a busy scene refits with the joint scene only the crosses whose
#: footprint holds a scene edge steeper than this x their contrast per px (the scene-edge
#: figure of :func:`softplot.marks.measure._footprint_gradient`); under the others the
#: opening's estimate is as good (docs/benchmarks.md, "Busy scenes")
EDGE_MIN = 0.02
#: TV weight in units of the patch's noise
MU = 1.0
#: with ``band_px`` (:func:`deconv_tv`) the scene is free only in the band around each
#: fitted mark (pixels within this many px of where its blurred template ``T`` exceeds
#: :data:`BAND_T`); outside it the scene is held at the starting estimate. Default: the whole
#: patch (``inf``): with 8 px and 40/30 iterations the busy renders' RMS was that of the
#: whole patch on most renders but not on the noisiest (docs/benchmarks.md, "Busy scenes"),
#: and since the whole-patch kernel runs over padded rows the band solve is the slower one
BAND_PX = math.inf
BAND_T = 0.01
#: steps of the primal-dual solver: tau * sigma * ||K||^2 <= 1 with ||K||^2 <= 8 + 1
TAU = SIGMA = 1.0 / 3.0


def gauss_taps(s_e: float) -> np.ndarray:
    """Normalised taps of a sampled Gaussian of sigma ``s_e`` px, to 3 sigma (float32)."""
    r = max(1, int(np.ceil(3.0 * float(s_e))))
    return cv2.getGaussianKernel(2 * r + 1, float(s_e), cv2.CV_32F).ravel()


# -- compiled kernel ---------------------------------------------------------------------------

njit = kernels.njit


@njit(fastmath=True, cache=True, nogil=True)
def _vertical7(tmp, dst, k1, k2, k3, k4, k5, k6, k7, h, w):  # pragma: no cover - compiled
    # the vertical pass of the 7-tap blurs (``_blur7``, ``_blur_p`` for r <= 3): rows of ``tmp`` to
    # ``dst``, edges replicated
    for i in range(h):
        r1 = tmp[max(i - 3, 0)]
        r2 = tmp[max(i - 2, 0)]
        r3 = tmp[max(i - 1, 0)]
        r4 = tmp[i]
        r5 = tmp[min(i + 1, h - 1)]
        r6 = tmp[min(i + 2, h - 1)]
        r7 = tmp[min(i + 3, h - 1)]
        d = dst[i]
        for j in range(w):
            d[j] = (k1 * r1[j] + k2 * r2[j] + k3 * r3[j] + k4 * r4[j] + k5 * r5[j]
                    + k6 * r6[j] + k7 * r7[j])


@njit(fastmath=True, cache=True, nogil=True)
def _vertical9(tmp, dst, k0, k1, k2, k3, k4, k5, k6, k7, k8, h, w):  # pragma: no cover - compiled
    # the vertical pass of the 9-tap blurs (``_blur``, ``_blur9_p``): rows of ``tmp`` to ``dst``,
    # edges replicated
    for i in range(h):
        r0 = tmp[max(i - 4, 0)]
        r1 = tmp[max(i - 3, 0)]
        r2 = tmp[max(i - 2, 0)]
        r3 = tmp[max(i - 1, 0)]
        r4 = tmp[i]
        r5 = tmp[min(i + 1, h - 1)]
        r6 = tmp[min(i + 2, h - 1)]
        r7 = tmp[min(i + 3, h - 1)]
        r8 = tmp[min(i + 4, h - 1)]
        d = dst[i]
        for j in range(w):
            d[j] = (k0 * r0[j] + k1 * r1[j] + k2 * r2[j] + k3 * r3[j] + k4 * r4[j]
                    + k5 * r5[j] + k6 * r6[j] + k7 * r7[j] + k8 * r8[j])


@njit(fastmath=True, cache=True, nogil=True)
def _blur(src, dst, tmp, row, k, r, h, w):  # pragma: no cover - compiled
    # separable Gaussian, edges replicated (``row``: a buffer of w + 2 max(r, 4))
    if r > 4:
        _blur_any(src, dst, tmp, row, k, r, h, w)
        return
    if r <= 3:  # the common case (edge spread up to 1 px): 7 taps
        _blur7(src, dst, tmp, row, k, r, h, w)
        return
    # up to 9 taps (r <= 4, the blurs of real scans): the taps as scalars, zero-padded to 9,
    # each output one expression over the pixels: it vectorises (about twice as fast as the
    # loop over the taps, the same sums)
    z = np.float32(0.0)
    k0 = k[r - 4] if r >= 4 else z
    k1 = k[r - 3] if r >= 3 else z
    k2 = k[r - 2] if r >= 2 else z
    k3 = k[r - 1]
    k4 = k[r]
    k5 = k[r + 1]
    k6 = k[r + 2] if r >= 2 else z
    k7 = k[r + 3] if r >= 3 else z
    k8 = k[r + 4] if r >= 4 else z
    for i in range(h):
        s = src[i]
        for j in range(4):
            row[j] = s[0]
            row[w + 4 + j] = s[w - 1]
        for j in range(w):
            row[4 + j] = s[j]
        d = tmp[i]
        for j in range(w):
            d[j] = (k0 * row[j] + k1 * row[j + 1] + k2 * row[j + 2] + k3 * row[j + 3]
                    + k4 * row[j + 4] + k5 * row[j + 5] + k6 * row[j + 6] + k7 * row[j + 7]
                    + k8 * row[j + 8])
    _vertical9(tmp, dst, k0, k1, k2, k3, k4, k5, k6, k7, k8, h, w)


@njit(fastmath=True, cache=True, nogil=True)
def _blur7(src, dst, tmp, row, k, r, h, w):  # pragma: no cover - compiled
    # ``_blur`` for r <= 3: the taps zero-padded to 7
    z = np.float32(0.0)
    k1 = k[r - 3] if r >= 3 else z
    k2 = k[r - 2] if r >= 2 else z
    k3 = k[r - 1]
    k4 = k[r]
    k5 = k[r + 1]
    k6 = k[r + 2] if r >= 2 else z
    k7 = k[r + 3] if r >= 3 else z
    for i in range(h):
        s = src[i]
        for j in range(3):
            row[j] = s[0]
            row[w + 3 + j] = s[w - 1]
        for j in range(w):
            row[3 + j] = s[j]
        d = tmp[i]
        for j in range(w):
            d[j] = (k1 * row[j] + k2 * row[j + 1] + k3 * row[j + 2] + k4 * row[j + 3]
                    + k5 * row[j + 4] + k6 * row[j + 5] + k7 * row[j + 6])
    _vertical7(tmp, dst, k1, k2, k3, k4, k5, k6, k7, h, w)


@njit(fastmath=True, cache=True, nogil=True)
def _blur_any(src, dst, tmp, row, k, r, h, w):  # pragma: no cover - compiled
    # ``_blur`` for any radius (``row``: a buffer of w + 2 r)
    for i in range(h):
        for j in range(r):
            row[j] = src[i, 0]
            row[w + r + j] = src[i, w - 1]
        for j in range(w):
            row[r + j] = src[i, j]
        # taps outside, pixels inside: the inner loop vectorises (twice as fast as a sum
        # over the taps per pixel)
        for j in range(w):
            tmp[i, j] = 0.0
        for t in range(2 * r + 1):
            kt = k[t]
            for j in range(w):
                tmp[i, j] += kt * row[j + t]
    for i in range(h):
        for j in range(w):
            dst[i, j] = 0.0
        for t in range(-r, r + 1):
            ii = min(max(i + t, 0), h - 1)
            kt = k[t + r]
            for j in range(w):
                dst[i, j] += kt * tmp[ii, j]


@njit(fastmath=True, cache=True, nogil=True)
def _project(a, b, il):  # pragma: no cover - compiled
    nn = max(np.float32(1.0), np.sqrt(a * a + b * b) * il)
    return a / nn, b / nn


#: the scene kernel's ``Xb`` and ``t1`` rows start at this column: the blur's horizontal pass
#: reads the columns before a row's first (its replicated edge) straight from the array
O = 8


@njit(fastmath=True, cache=True, nogil=True)
def _blur9_p(src, dst, tmp, k, h, w):  # pragma: no cover - compiled
    # ``_blur_p`` for r = 4: the sums of ``_blur``'s 9 taps
    k0, k1, k2, k3, k4, k5, k6, k7, k8 = k[0], k[1], k[2], k[3], k[4], k[5], k[6], k[7], k[8]
    for i in range(h):
        s = src[i, O - 4:]
        d = tmp[i]
        for j in range(w):
            d[j] = (k0 * s[j] + k1 * s[j + 1] + k2 * s[j + 2] + k3 * s[j + 3]
                    + k4 * s[j + 4] + k5 * s[j + 5] + k6 * s[j + 6] + k7 * s[j + 7]
                    + k8 * s[j + 8])
    _vertical9(tmp, dst, k0, k1, k2, k3, k4, k5, k6, k7, k8, h, w)


@njit(fastmath=True, cache=True, nogil=True)
def _blur_p(src, dst, tmp, row, k, r, h, w):  # pragma: no cover - compiled
    # ``_blur`` of rows that start at column ``O`` of ``src``, the 4 columns either side of
    # each row holding its edge values: for r <= 4 the horizontal pass reads the row itself
    # (no copy into a buffer; every index non-negative, so it vectorises), the same sums as
    # ``_blur7`` (r <= 3) and ``_blur``'s 9 taps (r = 4)
    if r > 4:
        _blur(src[:, O:], dst, tmp, row, k, r, h, w)
        return
    if r == 4:
        _blur9_p(src, dst, tmp, k, h, w)
        return
    z = np.float32(0.0)
    k1 = k[r - 3] if r >= 3 else z
    k2 = k[r - 2] if r >= 2 else z
    k3 = k[r - 1]
    k4 = k[r]
    k5 = k[r + 1]
    k6 = k[r + 2] if r >= 2 else z
    k7 = k[r + 3] if r >= 3 else z
    for i in range(h):
        s = src[i, O - 3:]
        d = tmp[i]
        for j in range(w):
            d[j] = (k1 * s[j] + k2 * s[j + 1] + k3 * s[j + 2] + k4 * s[j + 3]
                    + k5 * s[j + 4] + k6 * s[j + 5] + k7 * s[j + 6])
    _vertical7(tmp, dst, k1, k2, k3, k4, k5, k6, k7, h, w)


@njit(fastmath=True, cache=True, nogil=True)
def _kernel(g, T, m, B0, mu, k, iters, tau, sig, out, xout):  # pragma: no cover - compiled
    # the patch's rows padded to a multiple of 8 columns (``wp``, plus a margin): the loops
    # over whole rows then have no scalar remainder (they vectorise 8 or 16 wide); the pad
    # columns repeat the last column of ``Xb`` and ``t1`` (what the blur's replicated edge and
    # the zero forward difference across the far edge see), so the patch's own columns get
    # the values of the unpadded loops. ``Xb`` and ``t1``, the blurred arrays, also have ``O``
    # columns before each row that repeat its first column: the blur's horizontal pass
    # (``_blur_p``) reads a row's replicated edges from the array itself, without copying
    # the row into a buffer (the same sums; the whole solve about 20 % faster)
    n, h, w = g.shape
    r = (k.shape[0] - 1) // 2
    wp = (w + 7) // 8 * 8
    w1 = wp + 8
    one = np.float32(1.0)
    isg = one / (one + sig)
    X = np.empty((h, w1), np.float32)
    Xb = np.empty((h, O + w1), np.float32)
    px = np.empty((h, w1), np.float32)
    py = np.empty((h, w1), np.float32)
    y2 = np.empty((h, w1), np.float32)
    t1 = np.empty((h, O + w1), np.float32)
    t2 = np.zeros((h, w1), np.float32)
    tmp = np.zeros((h, w1), np.float32)
    W = np.empty((h, w1), np.float32)
    f = np.empty((h, w1), np.float32)
    row = np.empty(w1 + 2 * max(r, 4), np.float32)
    for q in range(n):
        il = one / mu[q]
        for i in range(h):
            for j in range(w):
                X[i, j] = B0[q, i, j]
                Xb[i, O + j] = B0[q, i, j]
                W[i, j] = one - T[q, i, j]
                f[i, j] = sig * (g[q, i, j] - m[q] * T[q, i, j])
            for j in range(w, w1):  # the pad: no data, the scene's last column repeated
                X[i, j] = B0[q, i, w - 1]
                Xb[i, O + j] = B0[q, i, w - 1]
                W[i, j] = 0.0
                f[i, j] = 0.0
            for j in range(w1):
                px[i, j] = 0.0
                py[i, j] = 0.0
                y2[i, j] = 0.0
            for j in range(O + w1):
                t1[i, j] = 0.0
            for j in range(O):  # the left pad: the first column repeated
                Xb[i, j] = B0[q, i, 0]
        for _ in range(iters):
            # dual step of the TV term: ascent on grad X (forward differences, 0 across the
            # far edges: the pad repeats the last column), projection onto |p| <= mu
            for i in range(h - 1):
                for j in range(wp):
                    px[i, j], py[i, j] = _project(
                        px[i, j] + sig * (Xb[i, O + j + 1] - Xb[i, O + j]),
                        py[i, j] + sig * (Xb[i + 1, O + j] - Xb[i, O + j]), il)
            for j in range(wp):
                px[h - 1, j], py[h - 1, j] = _project(
                    px[h - 1, j] + sig * (Xb[h - 1, O + j + 1] - Xb[h - 1, O + j]), py[h - 1, j],
                    il)
            # dual step of the data term (prox of the conjugate of 1/2 |z - f|^2)
            _blur_p(Xb, t2, tmp, row, k, r, h, wp)
            for i in range(h):
                for j in range(wp):
                    y2[i, j] = (y2[i, j] + sig * W[i, j] * t2[i, j] - f[i, j]) * isg
                    t1[i, O + j] = W[i, j] * y2[i, j]
                e = t1[i, O + w - 1]
                for j in range(w, wp + 4):
                    t1[i, O + j] = e
                e = t1[i, O]
                for j in range(O):
                    t1[i, j] = e
            _blur_p(t1, t2, tmp, row, k, r, h, wp)
            # primal step: X - tau K^T y = X + tau (div p - G (W y2)), then extrapolation
            # (px on the last column and py on the last row stay 0: added without a branch,
            # the inner loop vectorises)
            for i in range(h):
                d = -t2[i, 0] + px[i, 0] + py[i, 0]
                if i > 0:
                    d -= py[i - 1, 0]
                xn = X[i, 0] + tau * d
                Xb[i, O] = np.float32(2.0) * xn - X[i, 0]
                X[i, 0] = xn
                if i > 0:
                    for j in range(1, w):
                        d = -t2[i, j] + px[i, j] - px[i, j - 1] + py[i, j] - py[i - 1, j]
                        xn = X[i, j] + tau * d
                        Xb[i, O + j] = np.float32(2.0) * xn - X[i, j]
                        X[i, j] = xn
                else:
                    for j in range(1, w):
                        d = -t2[i, j] + px[i, j] - px[i, j - 1] + py[i, j]
                        xn = X[i, j] + tau * d
                        Xb[i, O + j] = np.float32(2.0) * xn - X[i, j]
                        X[i, j] = xn
                e = Xb[i, O + w - 1]
                for j in range(w, wp + 4):
                    Xb[i, O + j] = e
                e = Xb[i, O]
                for j in range(O):
                    Xb[i, j] = e
        _blur(X, t2, tmp, row, k, r, h, w)
        for i in range(h):
            for j in range(w):
                out[q, i, j] = t2[i, j]
                xout[q, i, j] = X[i, j]


@njit(fastmath=True, cache=True, nogil=True)
def _blur_rows(src, dst, tmp, row, k, r, h, w, lo, hi, nlo, nhi):  # pragma: no cover - compiled
    # the separable blur of ``_blur`` at the band's pixels only: row i's columns [lo, hi);
    # the horizontal pass where the vertical one reads it ([nlo, nhi): rows i - r .. i + r)
    for i in range(h):
        a, b = nlo[i], nhi[i]
        if a >= b:
            continue
        for j in range(b - a + 2 * r):  # the row's segment, edges replicated
            row[j] = src[i, min(max(a - r + j, 0), w - 1)]
        for j in range(b - a):
            acc = np.float32(0.0)
            for t in range(2 * r + 1):
                acc += k[t] * row[j + t]
            tmp[i, a + j] = acc
    # the vertical pass over whole rows (it vectorises; the columns outside the band are
    # not used, and ``tmp`` there holds finite values of earlier passes)
    for i in range(h):
        if lo[i] >= hi[i]:
            continue
        for j in range(w):
            dst[i, j] = 0.0
        for t in range(-r, r + 1):
            ii = min(max(i + t, 0), h - 1)
            kt = k[t + r]
            for j in range(w):
                dst[i, j] += kt * tmp[ii, j]


@njit(fastmath=True, cache=True, nogil=True)
def _kernel_band(g, T, m, B0, mu, k, iters, tau, sig, lo, hi, out,
                 xout):  # pragma: no cover - compiled
    # ``_kernel`` with the scene free only in the band of each patch (row i: columns
    # [lo[q, i], hi[q, i])), the rest held at B0: the data term and the total variation of
    # the edges leaving a band pixel (right, down)
    n, h, w = g.shape
    r = (k.shape[0] - 1) // 2
    one = np.float32(1.0)
    isg = one / (one + sig)
    X = np.empty((h, w), np.float32)
    Xb = np.empty((h, w), np.float32)
    px = np.zeros((h, w), np.float32)
    py = np.zeros((h, w), np.float32)
    y2 = np.zeros((h, w), np.float32)
    t1 = np.zeros((h, w), np.float32)
    t2 = np.zeros((h, w), np.float32)
    tmp = np.zeros((h, w), np.float32)
    W = np.empty((h, w), np.float32)
    f = np.empty((h, w), np.float32)
    row = np.empty(w + 2 * max(r, 4), np.float32)
    nlo = np.empty(h, np.int64)
    nhi = np.empty(h, np.int64)
    for q in range(n):
        il = one / mu[q]
        lq = lo[q]
        hq = hi[q]
        for i in range(h):
            a = w
            b = 0
            for t in range(-r, r + 1):
                ii = min(max(i + t, 0), h - 1)
                if hq[ii] > lq[ii]:
                    a = min(a, lq[ii])
                    b = max(b, hq[ii])
            nlo[i] = a
            nhi[i] = max(a, b)
        for i in range(h):
            for j in range(w):
                X[i, j] = B0[q, i, j]
                Xb[i, j] = B0[q, i, j]
                px[i, j] = 0.0
                py[i, j] = 0.0
                y2[i, j] = 0.0
                t1[i, j] = 0.0
                W[i, j] = one - T[q, i, j]
                f[i, j] = sig * (g[q, i, j] - m[q] * T[q, i, j])
        for _ in range(iters):
            # dual step of the TV term (loops split so that the inner ones have no branch)
            for i in range(h):
                a, b = lq[i], hq[i]
                if a >= b:
                    continue
                bi = min(b, w - 1)
                if i < h - 1:
                    for j in range(a, bi):
                        px[i, j], py[i, j] = _project(px[i, j] + sig * (Xb[i, j + 1] - Xb[i, j]),
                                                      py[i, j] + sig * (Xb[i + 1, j] - Xb[i, j]),
                                                      il)
                    if b == w:
                        px[i, w - 1], py[i, w - 1] = _project(
                            px[i, w - 1], py[i, w - 1] + sig * (Xb[i + 1, w - 1] - Xb[i, w - 1]),
                            il)
                else:
                    for j in range(a, bi):
                        px[i, j], py[i, j] = _project(px[i, j] + sig * (Xb[i, j + 1] - Xb[i, j]),
                                                      py[i, j], il)
                    if b == w:
                        px[i, w - 1], py[i, w - 1] = _project(px[i, w - 1], py[i, w - 1], il)
            # dual step of the data term
            _blur_rows(Xb, t2, tmp, row, k, r, h, w, lq, hq, nlo, nhi)
            for i in range(h):
                for j in range(lq[i], hq[i]):
                    y2[i, j] = (y2[i, j] + sig * W[i, j] * t2[i, j] - f[i, j]) * isg
                    t1[i, j] = W[i, j] * y2[i, j]
            _blur_rows(t1, t2, tmp, row, k, r, h, w, lq, hq, nlo, nhi)
            # primal step and extrapolation (p is 0 outside the band and on the far edges)
            for i in range(h):
                a, b = lq[i], hq[i]
                if a >= b:
                    continue
                if a == 0:
                    d = -t2[i, 0] + px[i, 0] + py[i, 0]
                    if i > 0:
                        d -= py[i - 1, 0]
                    xn = X[i, 0] + tau * d
                    Xb[i, 0] = np.float32(2.0) * xn - X[i, 0]
                    X[i, 0] = xn
                    a = 1
                if i > 0:
                    for j in range(a, b):
                        d = -t2[i, j] + px[i, j] - px[i, j - 1] + py[i, j] - py[i - 1, j]
                        xn = X[i, j] + tau * d
                        Xb[i, j] = np.float32(2.0) * xn - X[i, j]
                        X[i, j] = xn
                else:
                    for j in range(a, b):
                        d = -t2[i, j] + px[i, j] - px[i, j - 1] + py[i, j]
                        xn = X[i, j] + tau * d
                        Xb[i, j] = np.float32(2.0) * xn - X[i, j]
                        X[i, j] = xn
        _blur(X, t2, tmp, row, k, r, h, w)
        for i in range(h):
            for j in range(w):
                out[q, i, j] = t2[i, j]
                xout[q, i, j] = X[i, j]


# -- NumPy path ----------------------------------------------------------------------------------


def _blur_np(a: np.ndarray, k: np.ndarray) -> np.ndarray:
    """The kernel's separable blur of a stack (N, h, w), edges replicated."""
    t = correlate1d(a, k, axis=2, mode="nearest")
    return correlate1d(t, k, axis=1, mode="nearest").astype(np.float32)


def _grad(X):
    gx = np.zeros_like(X)
    gy = np.zeros_like(X)
    gx[:, :, :-1] = X[:, :, 1:] - X[:, :, :-1]
    gy[:, :-1, :] = X[:, 1:, :] - X[:, :-1, :]
    return gx, gy


def _div(px, py):
    d = np.zeros_like(px)
    d[:, :, :-1] += px[:, :, :-1]
    d[:, :, 1:] -= px[:, :, :-1]
    d[:, :-1, :] += py[:, :-1, :]
    d[:, 1:, :] -= py[:, :-1, :]
    return d


def _numpy(g, T, m, B0, mu, k, iters, band=None):
    """The NumPy path of both kernels (``band``: (lo, hi) of :func:`band_rows`, or None)."""
    tau, sig = np.float32(TAU), np.float32(SIGMA)
    W = 1.0 - T
    f = sig * (g - m[:, None, None] * T)
    X = B0.copy()
    Xb = X.copy()
    px = np.zeros_like(X)
    py = np.zeros_like(X)
    y2 = np.zeros_like(X)
    il = (1.0 / mu)[:, None, None].astype(np.float32)
    M = None
    if band is not None:
        cols = np.arange(g.shape[2])[None, None, :]
        M = (cols >= band[0][:, :, None]) & (cols < band[1][:, :, None])
    for _ in range(iters):
        gx, gy = _grad(Xb)
        px += sig * gx
        py += sig * gy
        nn = np.maximum(1.0, np.sqrt(px * px + py * py) * il)
        px /= nn
        py /= nn
        y2 = (y2 + sig * W * _blur_np(Xb, k) - f) / (1.0 + sig)
        if M is not None:
            px *= M
            py *= M
            y2 *= M
        Xn = X + tau * (_div(px, py) - _blur_np(W * y2, k))
        if M is not None:
            Xn = np.where(M, Xn, X)
        Xb = 2.0 * Xn - X
        X = Xn
    return _blur_np(X, k), X.astype(np.float32)


def band_rows(T: np.ndarray, band_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Per patch and row, the columns ``[lo, hi)`` of the band around each mark: the pixels
    within ``band_px`` (square neighbourhood) of ``T > BAND_T``, as one interval per row
    (the hull of the row's band pixels). ``T`` (N, h, w) pixel system; returns two (N, h)
    int64 arrays (``lo == hi`` where a row has none; a patch without any mark pixel is
    whole)."""
    n, h, w = T.shape
    r = max(0, int(np.ceil(band_px)))
    ker = np.ones((2 * r + 1, 2 * r + 1), np.uint8)
    lo = np.zeros((n, h), np.int64)
    hi = np.zeros((n, h), np.int64)
    for q in range(n):
        M = cv2.dilate((T[q] > BAND_T).astype(np.uint8), ker) > 0
        anyr = M.any(axis=1)
        first = np.argmax(M, axis=1)
        last = w - np.argmax(M[:, ::-1], axis=1)
        if anyr.any():
            lo[q] = np.where(anyr, first, 0)
            hi[q] = np.where(anyr, last, 0)
        else:  # no mark in the patch: the whole patch
            hi[q] = w
    return lo, hi


#: :func:`deconv_tv` shares its patches with an idle thread from this many on
#: (:func:`_whole_patches`)
SHARE_MIN = 2


def _whole_patches(g, T, m, B0, mu, k, iters, out, xout) -> None:
    """The compiled solve (:func:`_kernel`) of the N patches (pixel system, float32,
    C-contiguous), into ``out`` and ``xout``: in two halves where a thread of the process is
    idle (:func:`softplot.runtime.share`; e.g. the last chunk of crosses refitted while the
    other chunks are done). Each patch is solved on its own, from its own arrays (the kernel's
    work rows are set afresh for every patch), so the halves give the whole's values to the
    last bit."""
    n = len(g)
    tau, sig = np.float32(TAU), np.float32(SIGMA)

    def solve(s):
        _kernel(g[s], T[s], m[s], B0[s], mu[s], k, iters, tau, sig, out[s], xout[s])

    if n < SHARE_MIN or not runtime.idle_threads():
        solve(slice(None))
        return
    runtime.share(solve, [slice(0, n // 2), slice(n // 2, n)])


def deconv_tv(g: np.ndarray, T: np.ndarray, level: np.ndarray, B0: np.ndarray,
              mu: np.ndarray, s_e: float, iters: int | None = None,
              compiled: bool | None = None, band_px: float | None = None) -> np.ndarray:
    """The blurred scene ``B = G * X`` under N fitted marks (see the module docstring).

    Parameters
    ----------
    g : (N, h, w) float
        Grey values of the patches (pixel system; finite everywhere).
    T : (N, h, w) float
        The fitted blurred mark of each patch (1 on the mark, 0 off it).
    level : (N,) float
        Each mark's fitted grey level.
    B0 : (N, h, w) float
        Starting estimate of the scene ``X`` (the opening's, or the ``X`` of a previous call).
    mu : (N,) float
        TV weight of each patch (grey units; a multiple of its noise).
    s_e : float
        Edge spread of the scanner (px): Gaussian blur and pixel box.
    iters : int, optional
        Iterations of the solver (default :data:`ITERATIONS`).
    compiled : bool, optional
        Use the numba kernel (default: when it is available).
    band_px : float, optional
        Solve for the scene only in the band around each mark (:func:`band_rows`; the rest
        held at ``B0``); default :data:`BAND_PX`; ``math.inf`` solves over the whole patch.

    Returns
    -------
    B, X : (N, h, w) float32
        The blurred scene (what LSM's model uses) and the scene before the blur.
    """
    g = np.ascontiguousarray(g, np.float32)
    T = np.ascontiguousarray(T, np.float32)
    B0 = np.ascontiguousarray(B0, np.float32)
    m = np.ascontiguousarray(level, np.float32).reshape(-1)
    mu = np.ascontiguousarray(np.maximum(mu, 1e-6), np.float32).reshape(-1)
    k = gauss_taps(s_e)
    iters = ITERATIONS if iters is None else iters
    if compiled is None:
        compiled = kernels.AVAILABLE and kernels.ready()
    band_px = BAND_PX if band_px is None else float(band_px)
    band = None if not np.isfinite(band_px) else band_rows(T, band_px)
    if not compiled:
        return _numpy(g, T, m, B0, mu, k, int(iters), band)
    out = np.empty_like(g)
    xout = np.empty_like(g)
    try:
        if band is None:
            _whole_patches(g, T, m, B0, mu, k, int(iters), out, xout)
        else:
            _kernel_band(g, T, m, B0, mu, k, int(iters), np.float32(TAU), np.float32(SIGMA),
                         band[0], band[1], out, xout)
    except Exception as exc:  # noqa: BLE001 - numba cannot compile it here: the NumPy path
        warnings.warn(f"softplot: compiled scene kernel unavailable ({type(exc).__name__}: "
                      f"{exc}); using NumPy", RuntimeWarning, stacklevel=2)
        return _numpy(g, T, m, B0, mu, k, int(iters), band)
    return out, xout
