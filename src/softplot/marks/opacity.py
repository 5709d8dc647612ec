"""The opacity of a scan's reseau crosses, estimated from the scene seen through their bars.

A cross of opacity ``a`` and grey level ``m`` over the (optically blurred) scene ``B`` draws
``B + a (m - B) T`` (``T`` the blurred template, :class:`softplot.marks.template.MarkShape`):
on the bar the scene shows through with weight ``1 - a T``. Along a bar, away from the cross's
centre and tips, the grey value on the bar's centre line ``g`` and the scene beside the bar
``b`` (the mean of the two sides, beyond the bar's blur, where ``T`` is 0) follow

    g = c + (1 - a T0) b,        c = a m T0,

``T0`` the template on the bar's centre line. Within one cross ``c`` is a constant, so the
deviations of ``g`` and ``b`` from their means over the cross give ``a`` by one pooled
regression over all crosses of the scan (each its own level: a vignetted scan's ``m`` may
vary from cross to cross): ``g' - b' = -a T0 b'``. Where the scene under the crosses hardly
varies (a flat scan) the regression cannot tell ``a``: its standard error is large, and
:func:`shrink` returns 1 (an opaque mark; over a flat scene the opacity does not matter).

Samples where the two sides differ by more than a few noise sigmas (a scene edge running
along the bar: the scene under it is either side's) or lie at the ends of the grey range
(censored) are left out; the fit is robust (Tukey's biweight on the residuals). The side
mean's noise biases ``a`` towards 0 by the share of the noise in the scene's variance
beside the bars (below 2 % on the sweep's busy scenes).

Positions: crosses in the pixel system (``centre`` (N, 2) px, ``A`` (N, 2, 2) the pixel ->
mark-frame affine, mark frame in px at the nominal scale as in :mod:`softplot.marks.template`).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import map_coordinates

from softplot.marks.template import MarkShape, aperture

__all__ = ["estimate", "shrink", "MIN_Z", "MIN_DROP", "LEAST"]

#: :func:`shrink` takes an estimate that lies this many standard errors below 1
MIN_Z = 4.0
#: ... and at least this far below 1: the estimate's error is mostly the scene's (content
#: under a bar that its sides do not show, a template off on thin or blurred bars), which
#: its standard error does not see; on the robustness sweep's renders it was 0.13 (RMS) and
#: opaque crosses (opacity 0.97-1) came out as low as 0.89
MIN_DROP = 0.15
#: ... from at least this many samples
LEAST = 50
#: the lowest opacity :func:`shrink` returns
FLOOR = 0.5
#: bar pixels where the opaque template is below this carry little of the mark (thin,
#: blurred lines): left out, the template's error there is a large share of it
T_MIN = 0.5


def _bar_pixels(shape: MarkShape, u, v, s):
    """The pixels on the bars of N crosses (mark-frame ``u``, ``v`` (N, h, w) px; blurs ``s``
    (N,)), away from the centre's square and the tips' blur: ``(on, along_v)`` (N, h, w)
    bool, the pixels and those of them on the bar along ``v``."""
    s = np.asarray(s, np.float32)[:, None, None]
    lo = np.float32(0.5 * shape.width + 1.0) + np.float32(3.0) * s
    hi = np.float32(0.5 * shape.length - 1.0) - np.float32(2.5) * s
    core = np.float32(max(0.5 * shape.width, 0.5))
    au, av = np.abs(u), np.abs(v)
    on_v = (au <= core) & (av >= lo) & (av <= hi)
    on = ((av <= core) & (au >= lo) & (au <= hi)) | on_v
    return on, on_v


def _sides(stack, origin, centre, A, k, t, axis, d):
    """The scene beside the bars at the bar pixels of crosses ``k`` (M,): bilinear samples
    of the patches at mark-frame ``(t, +-d)`` (``(+-d, t)`` where ``axis``); returns the
    mean and the difference of the two sides (M,)."""
    Ai = np.linalg.inv(np.asarray(A, float))[k]
    off = (np.asarray(centre, float) - origin)[k]
    fin = np.isfinite(stack)
    img = np.where(fin, stack, 0.0)
    vals = []
    for sgn in (1.0, -1.0):
        q = np.where(axis[:, None], np.stack([sgn * d[k], t], 1), np.stack([t, sgn * d[k]], 1))
        p = np.einsum("mij,mj->mi", Ai, q) + off
        at = [k.astype(float), p[:, 1], p[:, 0]]
        val = map_coordinates(img, at, order=1, mode="constant", cval=0.0)
        if not fin.all():  # a sample that reads a pixel outside the scan is none
            val = np.where(map_coordinates(fin.astype(np.float32), at, order=1,
                                           mode="constant", cval=0.0) > 0.999, val, np.nan)
        vals.append(val)
    return 0.5 * (vals[0] + vals[1]), vals[0] - vals[1]


def _pairs(stack, origin, shape, centre, A, s):
    """Every bar pixel of N crosses (:func:`_bar_pixels`): ``(k, g, T, b, diff)`` (M,), the
    cross it belongs to, its grey value, the opaque template there and the mean and
    difference of the scene beside the bar (:func:`_sides`)."""
    from softplot.marks.lsm import patch_frame

    n = len(centre)
    u, v = patch_frame(origin, centre, A, stack.shape)
    on, along_v = _bar_pixels(shape, u, v, s)
    k, yy, xx = np.nonzero(on)
    uk, vk, axis = u[k, yy, xx], v[k, yy, xx], along_v[k, yy, xx]
    opaque = shape.with_opacity(1.0)
    ap = tuple(x[k] for x in aperture(np.asarray(A, np.float32).reshape(n, 2, 2)))
    T = opaque.evaluate(uk, vk, np.asarray(s, np.float32)[k], aperture=ap)[0]
    d = 0.5 * shape.width + 2.5 * np.asarray(s, float) + 1.5
    b, diff = _sides(stack, origin, centre, A, k, np.where(axis, vk, uk).astype(float), axis, d)
    return k, stack[k, yy, xx].astype(float), T.astype(float), b, diff


def estimate(stack, origin, shape: MarkShape, centre, A, s, noise, clip=(0.0, 1.0),
             iters: int = 4):
    """The crosses' opacity and its standard error from the scene seen through their bars
    (module docstring).

    Parameters
    ----------
    stack : (N, h, w) float
        Patches around the crosses (grey; NaN outside the scan), pixel system.
    origin : (N, 2) float
        Pixel (x, y) of each patch's [0, 0] element.
    shape : MarkShape
        The cross (its ``opacity`` is not used).
    centre, A, s : (N, 2), (N, 2, 2), (N,)
        The fitted crosses: centres (pixel system), pixel -> mark-frame affines, blurs (px).
    noise : (N,) float
        Each cross's noise (grey units, the fit's residual MAD).
    clip : (lo, hi)
        The grey range: samples at its ends are left out.

    Returns
    -------
    (a, se, count) : float, float, int
        The opacity, its standard error (from the crosses' scatter: each cross's pixels
        may share an error) and the pixels it rests on (NaN, inf, 0 without any).
    """
    n = len(centre)
    if n == 0 or shape.kind != "cross":
        return np.nan, np.inf, 0
    stack = np.asarray(stack, np.float32)
    k, g, T, b, diff = _pairs(stack, np.asarray(origin, float), shape,
                              np.asarray(centre, float), np.asarray(A, float),
                              np.asarray(s, float))
    nz = np.maximum(np.asarray(noise, float), 1e-4)[k]
    eps = 2e-3
    use = (np.isfinite(g) & np.isfinite(b) & (np.abs(np.nan_to_num(diff)) <= 3.0 * nz)
           & (g > clip[0] + eps) & (g < clip[1] - eps) & (b > clip[0] + eps)
           & (b < clip[1] - eps) & (T >= T_MIN))
    g, b = np.nan_to_num(g), np.nan_to_num(b)
    # g - b = a m_k T - a T b: the cross's own level ``a m_k`` by its template column
    y0, x0 = g - b, T * b
    w = use.astype(float)
    a, se = np.nan, np.inf
    for _ in range(iters):
        stt = np.bincount(k, w * T * T, n)
        good = stt > 1e-9
        cy = np.bincount(k, w * T * y0, n) / np.where(good, stt, 1.0)
        cx = np.bincount(k, w * T * x0, n) / np.where(good, stt, 1.0)
        y = y0 - T * cy[k]
        x = x0 - T * cx[k]
        den = (w * x * x).sum()
        if den <= 0 or (w > 0).sum() < 3:
            return np.nan, np.inf, 0
        a = -float((w * x * y).sum() / den)
        r = y + a * x
        # each cross's share of the estimate's error: its pixels' errors may be one
        per = np.bincount(k, w * x * r, n)
        se = float(np.sqrt((per * per).sum()) / den)
        live = w > 0
        scale = max(1.4826 * float(np.median(np.abs(r[live]))), 1e-6)
        tt = r / (4.685 * scale)
        w = np.where(use & (np.abs(tt) < 1.0), (1.0 - tt * tt) ** 2, 0.0)
    return a, se, int((w > 0).sum())


def shrink(a: float, se: float, count: int) -> float:
    """The opacity the fits take from an estimate ``a`` with standard error ``se`` from
    ``count`` samples: ``a`` (at least :data:`FLOOR`) where it lies :data:`MIN_Z` standard
    errors and :data:`MIN_DROP` below 1 from :data:`LEAST` samples or more; else 1 (opaque:
    the scene under the crosses does not tell, or they are opaque)."""
    if not (np.isfinite(a) and np.isfinite(se)) or count < LEAST:
        return 1.0
    if 1.0 - a < max(MIN_Z * se, MIN_DROP):
        return 1.0
    return float(max(a, FLOOR))
