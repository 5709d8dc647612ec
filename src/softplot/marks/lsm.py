"""Least-squares template matching (LSM) of analytic marks, batched over many marks.

Model of the grey values ``g`` of a mark's pixels ``p = (x, y)`` (pixel system)::

    g(p) = B(p) * (1 - T) + (a + b) * T,     B(p) = a + gx * (x - x_r) + gy * (y - y_r)

with ``T = T(A @ (p - c); s)`` the analytic blurred mark of :mod:`softplot.marks.template`
(1 on the mark, 0 off it), ``c`` its centre (px), ``A`` the 2x2 pixel -> mark-frame affine
(rotation, scale, anisotropy, shear), ``s`` the Gaussian edge blur (px; the square pixel
footprint is modelled exactly across the bars), ``B`` the background under the mark (level
``a`` and tilt ``gx``, ``gy`` about the reference ``(x_r, y_r)``, the rounded initial centre,
plus a free level ``sat`` where the background estimate is saturated) and ``a + b`` the level
of the mark itself: reseau crosses and fiducials are opaque, they
*replace* the scene rather than add to it, so a scene gradient does not leak into the mark
(the sign of ``b`` is the polarity: negative for dark marks). A mark of opacity ``o < 1``
(:attr:`MarkShape.opacity`) lets the scene show through with weight ``1 - o``: its template
is ``o T``, so the model is ``B + o (a + b - B) T``. 12 parameters per mark, solved by
Gauss-Newton for all marks at once (arrays of shape (N, P) for N marks of up to P pixels
each).

Robustness: the first iterations use a wide blur (``s`` fixed large) to widen the capture range;
then all parameters are free and pixel weights follow Tukey's biweight on the residuals scaled by
their MAD, so that dust or a scratch over one arm gets weight 0 and does not pull the centre.
The covariance of the centre is the sandwich of the final weighted normal equations with the
residuals' correlation between neighbouring pixels (:func:`_correlated_cov`; ``sigma0**2 * N^-1``
for independent pixels).

For crosses the model and Jacobian of each step come from the compiled kernel of
:mod:`softplot.marks.kernels` when numba is there (the same values to float32 rounding), else
from :func:`_geom` and :func:`_assemble` (NumPy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softplot.marks import jpegq, kernels
from softplot.marks.template import MarkShape, aperture

__all__ = ["LSMResult", "lsm", "support_mask", "patch_frame", "PARAMS"]

#: parameter order of the LSM model
PARAMS = ("cx", "cy", "a00", "a01", "a10", "a11", "s", "a", "b", "gx", "gy", "sat")
_NP = len(PARAMS)
#: a mark has converged when its centre update is below this share of its own standard
#: deviation (or below ``tol``). Gauss-Newton shrinks the update about sixfold per step here,
#: so what is left after stopping is below a tenth of the standard deviation (1 % of the
#: variance)
CONVERGED = 0.5


@dataclass
class LSMResult:
    """Batched LSM results; arrays over N marks, positions in the pixel system.

    Attributes
    ----------
    centre : (N, 2) float
        Estimated mark centres (px).
    A : (N, 2, 2) float
        Pixel -> mark-frame affine.
    s : (N,) float
        Edge blur (px).
    offset : (N,) float
        Background level correction ``a`` (grey units).
    gain : (N,) float
        Contrast: mark level minus the background under the mark (``< 0`` for dark marks),
        times the mark's opacity (:attr:`MarkShape.opacity`): the contrast as seen, as an
        opaque model's fit gives it.
    cov : (N, 2, 2) float
        Covariance of the centre (px^2), the residuals' correlation between neighbouring
        pixels allowed for (:func:`_correlated_cov`): what is reported.
    sigma0 : (N,) float
        A-posteriori standard deviation of unit weight (grey units).
    noise : (N,) float
        Robust (MAD) standard deviation of the residuals (grey units).
    score : (N,) float
        Correlation of the data with the fitted mark over the mark's pixels, the fitted
        background removed from both (near 1 when the mark looks like the model).
    support : (N, K) float
        Fraction of well-fitting pixels (weight > 0.5) in each of K parts of the mark (the 4
        arms of a cross; 1 part for dots and circles).
    converged : (N,) bool
    iterations : int
    npix : (N,) int
        Pixels used.
    level : (N,) float
        The fitted grey level of the mark itself (``a + b`` of the model; of a mark of
        opacity below 1, the level it draws where it hides the scene entirely).
    cov_white : (N, 2, 2) float
        ``s0^2 N^-1``: the covariance if the pixels were independent (what the detector's
        acceptance and outlier tests are tuned on; too small on real scans).
    part_gain : (N, K) float
        The contrast of each part alone (mark minus background, as ``gain``) at the fitted
        geometry: near ``gain`` where the part is there, near 0 where it is not (a cross's
        bar that faded away); NaN where the part has no weighted pixels.
    snr : (N,) float
        Matched-filter signal-to-noise ratio ``||M - B|| / noise``: the fitted mark's
        contrast summed over all its pixels (the fitted background removed, the norm over
        the fit's pixels, grey units over grey units). Unlike :attr:`cnr` (per pixel) it
        grows with the mark's length and width: the evidence a thin, faint mark gives.
    cov_jpeg : (N, 2, 2) float
        What the scan's JPEG quantisation adds to ``cov`` (px^2; zeros without ``quant``,
        :func:`softplot.marks.jpegq.centre_term`), kept apart: the acceptance and outlier
        tests do not see it, the reported covariance has it
        (:func:`softplot.marks.validation.validate`).
    """

    centre: np.ndarray
    A: np.ndarray
    s: np.ndarray
    offset: np.ndarray
    gain: np.ndarray
    cov: np.ndarray
    sigma0: np.ndarray
    noise: np.ndarray
    score: np.ndarray
    support: np.ndarray
    converged: np.ndarray
    iterations: int
    npix: np.ndarray
    level: np.ndarray
    cov_white: np.ndarray | None = None
    part_gain: np.ndarray | None = None
    snr: np.ndarray | None = None
    cov_jpeg: np.ndarray | None = None

    @property
    def sigma(self) -> np.ndarray:
        """Scalar precision per mark (px) for the acceptance and outlier tests:
        ``sqrt((var_x + var_y) / 2)`` of ``cov_white`` (the tests' thresholds were set on it)."""
        c = self.cov if self.cov_white is None else self.cov_white
        return np.sqrt(0.5 * (c[:, 0, 0] + c[:, 1, 1]))

    @property
    def cnr(self) -> np.ndarray:
        """Contrast-to-noise ratio ``|b| / noise`` of every mark."""
        return np.abs(self.gain) / np.maximum(self.noise, 1e-12)


def support_mask(shape: MarkShape, u, v, margin: float) -> np.ndarray:
    """Pixels that carry information about a mark: within ``margin`` px of the drawn shape.

    ``u``, ``v`` are mark-frame coordinates (px); returns a boolean array of their shape.
    """
    if shape.kind in ("cross", "bar"):
        hl = 0.5 * shape.length + margin
        hw = 0.5 * shape.width + margin
        au, av = np.abs(u), np.abs(v)
        if shape.kind == "bar":
            return (au <= hl) & (av <= hw)
        return ((au <= hl) & (av <= hw)) | ((av <= hl) & (au <= hw))
    r = np.hypot(u, v)
    return r <= shape.extent + margin


def patch_frame(origin, c, A, shape3):
    """Mark-frame coordinates ``(u, v)`` (N, h, w) float32 of every pixel of N patches.

    ``origin`` (N, 2): pixel (x, y) of each patch's element [0, 0]; ``c`` (N, 2): mark
    centres (pixel system); ``A`` (N, 2, 2): pixel -> mark-frame affines.
    """
    n, h, w = shape3
    cl = (np.asarray(c, float) - origin).astype(np.float32)
    A = np.asarray(A, np.float32).reshape(n, 2, 2)
    dx = np.arange(w, dtype=np.float32)[None, None, :] - cl[:, 0, None, None]
    dy = np.arange(h, dtype=np.float32)[None, :, None] - cl[:, 1, None, None]
    u = A[:, 0, 0, None, None] * dx + A[:, 0, 1, None, None] * dy
    v = A[:, 1, 0, None, None] * dx + A[:, 1, 1, None, None] * dy
    return u, v


def _parts(shape: MarkShape, u, v) -> np.ndarray:
    """Index of the part (0..K-1) each mark-frame point belongs to (-1: centre square)."""
    if shape.kind not in ("cross", "bar"):
        return np.zeros(np.shape(u), np.int8)
    part = np.where(np.abs(u) >= np.abs(v), np.where(u >= 0, 0, 2), np.where(v >= 0, 1, 3))
    core = np.maximum(np.abs(u), np.abs(v)) <= shape.width
    return np.where(core, -1, part).astype(np.int8)


def _gather(patches, origin, ref, c, A, shape, margin, background=None, weight=None,
            sat_bg=None, clip=None):
    """Pick each mark's relevant pixels from its patch into padded (N, P) arrays.

    Returns ``(X, Y, G, valid, S)``: pixel coordinates relative to ``ref`` (float32), grey
    values (float32, 0 where padded), the validity mask (valid pixels come first in each row)
    and the scene background estimate under the mark (zeros without ``background``), the
    prior pixel weights (``weight``; 1 without it, 0 where padded), the indicator of a
    saturated background (``sat_bg``, 0/1) and the censoring code of each grey value (+1 at
    the upper end of ``clip``, -1 at the lower end, 0 inside).
    """
    if shape.kind == "cross" and kernels.ready():  # compiled: the same arrays
        return kernels.gather_cross(patches, origin, ref, c, A, shape.length, shape.width,
                                    margin, background, weight, sat_bg, clip)
    n, h, w = patches.shape
    off = (origin - ref).astype(np.float32)
    jj = np.arange(w, dtype=np.float32)
    ii = np.arange(h, dtype=np.float32)
    X = np.broadcast_to(off[:, 0, None, None] + jj[None, None, :], (n, h, w))
    Y = np.broadcast_to(off[:, 1, None, None] + ii[None, :, None], (n, h, w))
    u, v = patch_frame(origin, c, A, (n, h, w))
    m = support_mask(shape, u, v, margin) & np.isfinite(patches)
    m = m.reshape(n, -1)
    counts = m.sum(1)
    P = max(int(counts.max()), 1)
    order = np.argsort(~m, axis=1, kind="stable")[:, :P]
    valid = np.arange(P)[None, :] < counts[:, None]
    take = lambda a: np.take_along_axis(np.ascontiguousarray(a).reshape(n, -1), order, 1)  # noqa: E731
    G = take(patches)
    G[~valid] = 0.0
    if background is None:
        S = np.zeros_like(G)
    else:
        S = take(background)
        S[~valid] = 0.0
    if weight is None:
        Wp = valid.astype(np.float32)
    else:
        Wp = np.where(valid, take(weight), 0.0).astype(np.float32)
    Q = np.zeros_like(G) if sat_bg is None else np.where(valid, take(sat_bg), 0.0).astype(
        np.float32)
    Cc = np.zeros_like(G)
    if clip is not None:
        Cc = np.where(valid & (G >= clip[1] - 1e-6), 1.0, 0.0).astype(np.float32)
        Cc[valid & (G <= clip[0] + 1e-6)] = -1.0
    return take(X), take(Y), G, valid, S, Wp, Q, Cc


def _tukey(r, scale):
    """Tukey biweight weights for residuals ``r`` (N, P) with per-row ``scale``."""
    t = r / (4.685 * scale[:, None])
    return np.where(np.abs(t) < 1.0, (1.0 - t * t) ** 2, 0.0).astype(np.float32)


def _mad(r, valid):
    """Robust standard deviation of each row's valid residuals (1.4826 * median |r|)."""
    ar = np.where(valid, np.abs(r), np.inf)
    ar.sort(axis=1)
    k = np.maximum(valid.sum(1) // 2, 0)
    med = ar[np.arange(len(k)), np.minimum(k, ar.shape[1] - 1)]
    return np.maximum(1.4826 * np.where(np.isfinite(med), med, 0.0), 1e-9)


def _contrast(p, data, T=None):
    """Mark level minus the background under it (N,): the signed contrast of each mark."""
    X, Y, valid, S = data[0], data[1], data[3], data[4]
    q = p.astype(np.float32)
    bg = S + q[:, 9:10] * X + q[:, 10:11] * Y + q[:, 11:12] * data[6]
    wt = valid.astype(np.float32) if T is None else T * valid
    return p[:, 8] - (bg * wt).sum(1) / np.maximum(wt.sum(1), 1e-6)


def _scale(r, valid, p, data):
    """Residual scale for the robust weights: the MAD, floored at 1 % of the mark's contrast
    (flat, saturated or quantised backgrounds have a MAD near 0 and would reject everything)."""
    return np.maximum(_mad(r, valid), 0.01 * np.abs(_contrast(p, data)) + 1e-4)


def _geom(p, data, shape):
    """Template and its derivatives at the current geometry: (T, Tu, Tv, Ts, u, v, dx, dy)."""
    X, Y = data[0], data[1]
    q = p.astype(np.float32)
    dx = X - q[:, 0:1]
    dy = Y - q[:, 1:2]
    a00, a01, a10, a11 = (q[:, k : k + 1] for k in range(2, 6))
    u = a00 * dx + a01 * dy
    v = a10 * dx + a11 * dy
    ap = tuple(x[:, None] for x in aperture(q[:, 2:6].reshape(-1, 2, 2)))
    T, Tu, Tv, Ts = shape.evaluate(u, v, q[:, 6:7], aperture=ap)
    return T, Tu, Tv, Ts, u, v, dx, dy


def _assemble(p, data, g, need_jac=True):
    """Model grey values (N, P) and Jacobian (N, P, 11) from the geometry ``g``."""
    X, Y = data[0], data[1]
    T, Tu, Tv, Ts, u, v, dx, dy = g
    q = p.astype(np.float32)
    # scene estimate + tilt (+ the level above the clip of a saturated scene), without ``a``
    bg = data[4] + q[:, 9:10] * X + q[:, 10:11] * Y + q[:, 11:12] * data[6]
    M = q[:, 7:8] + bg + (q[:, 8:9] - bg) * T
    if not need_jac:
        return M, T, u, v, None
    a00, a01, a10, a11 = (q[:, k : k + 1] for k in range(2, 6))
    b = q[:, 8:9] - bg  # the mark covers the background: dM/dT = mark - background
    bu, bv = b * Tu, b * Tv
    J = np.empty(X.shape + (_NP,), np.float32)
    J[..., 0] = -(bu * a00 + bv * a10)
    J[..., 1] = -(bu * a01 + bv * a11)
    J[..., 2] = bu * dx
    J[..., 3] = bu * dy
    J[..., 4] = bv * dx
    J[..., 5] = bv * dy
    J[..., 6] = b * Ts
    J[..., 7] = 1.0
    J[..., 8] = T
    J[..., 9] = X * (1.0 - T)
    J[..., 10] = Y * (1.0 - T)
    J[..., 11] = data[6] * (1.0 - T)
    return M, T, u, v, J


def _model(p, data, shape, need_jac=True):
    """Model grey values (N, P) and, if asked, the Jacobian (N, P, 11) at parameters ``p``.

    ``p[:, 0:2]`` is the centre relative to the reference point of the pixel coordinates.
    """
    return _assemble(p, data, _geom(p, data, shape), need_jac)


def _normal(J, w, r, active):
    """Weighted normal equations (float64) with inactive parameters pinned.

    ``J`` is scaled by ``sqrt(w)`` in place (it is not used afterwards): no weighted copy.
    """
    sw = np.sqrt(w)
    J *= sw[..., None]
    JT = J.transpose(0, 2, 1)
    Nm = np.matmul(JT, J).astype(float)
    g = np.matmul(JT, (sw * r)[..., None])[..., 0].astype(float)
    _pin(Nm, g, active)
    return Nm, g


def _pin(Nm, g, active):
    """Inactive parameters pinned in normal equations ``Nm``, ``g`` (in place)."""
    off = ~active
    Nm[:, off, :] = 0.0
    Nm[:, :, off] = 0.0
    g[:, off] = 0.0
    idx = np.where(off)[0]
    Nm[:, idx, idx] = 1.0
    # a parameter without any data (no saturated background around this mark) is pinned
    diag = np.arange(Nm.shape[1])
    Nm[:, diag, diag] = np.where(Nm[:, diag, diag] > 0, Nm[:, diag, diag], 1.0)


def _add_prior(Nm, g, p, prior, wrr, wsum, active):
    """A Gaussian prior ``(k, value (N,), sd)`` on parameter ``k`` added to the normal
    equations ``Nm``, ``g`` (in place) in the units of the weighted residuals: weight
    ``s0^2 / sd^2`` with ``s0^2 = wrr / (wsum - active)`` the residual variance."""
    if prior is None:
        return
    k, value, sd = prior
    lam = (np.asarray(wrr, float) / np.maximum(np.asarray(wsum, float) - active.sum(), 1.0)
           / sd**2)
    Nm[:, k, k] += lam
    g[:, k] += lam * (value - p[:, k])


def _step(p, data, shape, active, robust, init=False, prior=None):
    """One (robust) Gauss-Newton step on ``p`` in place.

    Returns the centre update (px) and an estimate of the centre's standard deviation (px).
    With ``init`` the radiometry (offset, contrast) is first set by linear regression of the
    data on the template at the current geometry. ``prior`` ``(k, value (N,), sd)``: a
    Gaussian prior on parameter ``k`` (:func:`_add_prior`).
    """
    G, valid = data[2], data[3]
    jit = shape.kind == "cross" and kernels.ready()
    if not jit:
        geo = _geom(p, data, shape)
        T = geo[0]
    elif init:
        # one compiled pass at unit contrast over a zero scene: the template and the purely
        # geometric Jacobian; the radiometry set below scales it (no second pass)
        q1 = p.copy()
        q1[:, 7:12] = (0.0, 1.0, 0.0, 0.0, 0.0)
        M, T, Tu, Tv, u, v, J = kernels.cross_model(
            q1, data[:4] + (np.zeros_like(data[4]),) + data[5:], shape)
    if init:
        # linear regression of (data - scene) on T; then the model is linear in a, b
        vf = valid.astype(np.float32)
        Gs = G - data[4]
        sw = np.maximum(vf.sum(1), 1.0)
        mT = (T * vf).sum(1) / sw
        mG = (Gs * vf).sum(1) / sw
        cov_tg = ((T - mT[:, None]) * (Gs - mG[:, None]) * vf).sum(1)
        var_t = np.maximum(((T - mT[:, None]) ** 2 * vf).sum(1), 1e-12)
        b = cov_tg / var_t
        p[:, 7] = mG - b * mT
        p[:, 8] = b + (data[4] * T * vf).sum(1) / np.maximum((T * vf).sum(1), 1e-6)
        p[:, 9:12] = 0.0
    if jit and init:  # tilt and saturated level are 0 now: background S, contrast b - S
        b = p[:, 8:9].astype(np.float32) - data[4]
        kernels.scale_columns(J, b, 7)  # J[..., :7] *= b[..., None]
        M = p[:, 7:8].astype(np.float32) + data[4] + b * T
    elif jit:  # one compiled pass (softplot.marks.kernels), else NumPy
        M, T, Tu, Tv, u, v, J = kernels.cross_model(p, data, shape)
    else:
        M, T, u, v, J = _assemble(p, data, geo)
        Tu, Tv = geo[1], geo[2]
    if jit:  # the weights, normal equations and update compiled too (the same sums)
        r, w_rob, w, Nm, g, wrr, wsum = kernels.weigh(p, data, M, J, robust)
        _add_prior(Nm, g, p, prior, wrr, wsum, active)
        Ninv, inv_ok = kernels.invert(Nm, g, active)
        if inv_ok.all():
            dc, sig, cov, s0sq = kernels.advance(Ninv, g, wsum, wrr, int(active.sum()), p)
            state = dict(M=M, T=T, u=u, v=v, r=r, w_rob=w_rob, w=w, cov=cov, s0sq=s0sq, Tu=Tu,
                         Tv=Tv, h=kernels.influence(Ninv, J))
            return dc, sig, state
        _pin(Nm, g, active)  # a vanishing pivot: the pseudo-inverse below
    else:
        r = np.where(valid, G - M, 0.0).astype(np.float32)
        # censored grey values (at the end of the range): they only say "at least this
        # bright" (or dark); consistent with a model beyond the clip they carry nothing
        Cc = data[7]
        cens = ((Cc > 0) & (M >= G)) | ((Cc < 0) & (M <= G))
        r[cens] = 0.0
        w_rob = (_tukey(r, _scale(r, valid, p, data)) if robust else valid.astype(np.float32))
        w_rob *= valid
        w = w_rob * data[5] * ~cens
        Nm, g = _normal(J, w, r, active)
        wrr = (w * r * r).sum(1, dtype=float)
        _add_prior(Nm, g, p, prior, wrr, w.sum(1, dtype=float), active)
    # a touch of Levenberg-Marquardt damping keeps ill-posed nuisance parameters in check
    diag = np.arange(_NP)
    Nm[:, diag, diag] *= 1.0 + 1e-6
    try:
        Ninv = np.linalg.inv(Nm)
        dp = np.matmul(Ninv, g[..., None])[..., 0]
    except np.linalg.LinAlgError:
        Ninv = np.linalg.pinv(Nm)
        dp = np.matmul(Ninv, g[..., None])[..., 0]
    dp[~np.isfinite(dp)] = 0.0
    red = np.maximum(w.sum(1) - active.sum(), 1.0)
    s0sq = wrr / red
    cov = Ninv[:, 0:2, 0:2] * s0sq[:, None, None]
    sig = np.sqrt(np.maximum(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]), 0.0))
    # the centre's influence on each weighted pixel, (N, 2, P): cov = Sum h h^T s0^2 for
    # white residuals; with correlated ones see _correlated_cov (J is sqrt(w) J here)
    h = (kernels.influence(Ninv, J) if jit else
         np.matmul(Ninv[:, 0:2, :].astype(np.float32), J.transpose(0, 2, 1)))
    state = dict(M=M, T=T, u=u, v=v, r=r, w_rob=w_rob, w=w, cov=cov, s0sq=s0sq, Tu=Tu, Tv=Tv,
                 h=h)
    # step limits: centre 1.5 px, shape 5 %, blur within a sane range
    dc = np.hypot(dp[:, 0], dp[:, 1])
    k = np.minimum(1.0, 1.5 / np.maximum(dc, 1e-12))
    dp[:, 0:2] *= k[:, None]
    dp[:, 2:6] = np.clip(dp[:, 2:6], -0.05, 0.05)
    p += dp
    p[:, 6] = np.clip(p[:, 6], 0.05, 25.0)
    # the shape and blur must have settled too (a centre can stall while they still move)
    settled = (np.abs(dp[:, 6]) < 0.01) & (np.abs(dp[:, 2:6]).max(1) < 2e-3)
    dc = np.where(settled, dc, np.maximum(dc, 1.0))
    return dc, sig, state


def _fine_stage(p, data, shape, full, robust, init, max_iter, tol, converged):
    """The fine stage of :func:`lsm`: up to ``max_iter`` steps (:func:`_step`) of every mark
    until it has converged (:func:`_converged`, from step 3 with ``robust``, whose weights
    start at step 2), the first with ``init``. Crosses step by the compiled loop
    (:func:`softplot.marks.kernels.fine_steps`, the same steps mark by mark) after a first
    NumPy step where ``init``. Updates ``p`` and ``converged`` in place; returns each mark's
    state at its last step (dict of arrays over the marks) and the last step taken."""
    n = len(p)
    todo = np.arange(n)
    last = None
    it0 = 1
    if shape.kind == "cross" and kernels.ready():
        if init:  # the radiometry's regression and the first step by NumPy
            last = _steps(p, data, shape, full, robust, 1, 1, tol, todo, None, converged, True)[0]
            todo = todo[~converged]
            it0 = 2
        else:
            last = _state_arrays(n, data[0].shape[1])
        if todo.size == 0 or max_iter < it0:
            return last, min(it0 - 1, max_iter)
        last_it, fail = kernels.fine_steps(p, data, shape.length, shape.width, full, robust,
                                           todo, it0, max_iter, tol, CONVERGED, last,
                                           converged, shape.opacity)
        it = int(last_it.max())
        for i in np.where(fail >= 0)[0]:  # a vanishing pivot: the pseudo-inverse's steps
            it = max(it, _steps(p, data, shape, full, robust, int(fail[i]), max_iter, tol,
                                np.array([i]), last, converged, False)[1])
        return last, it
    return _steps(p, data, shape, full, robust, 1, max_iter, tol, todo, None, converged, init)


def _state_arrays(n, npx):
    """Empty state of ``n`` marks of ``npx`` gathered pixels as :func:`_step` returns it."""
    f4 = np.float32
    last = {k: np.empty((n, npx), f4) for k in ("M", "T", "u", "v", "r", "w_rob", "w")}
    last.update(cov=np.empty((n, 2, 2)), s0sq=np.empty(n), Tu=np.empty((n, npx), f4),
                Tv=np.empty((n, npx), f4), h=np.empty((n, 2, npx), f4))
    return last


def _steps(p, data, shape, full, robust, it_from, max_iter, tol, todo, last, converged, init):
    """Steps ``it_from`` .. ``max_iter`` of :func:`_fine_stage` by NumPy (:func:`_step`) for
    the marks ``todo``; ``init`` on step 1. Returns ``(last, it)``."""
    n = len(p)
    it = it_from - 1
    for it in range(it_from, max_iter + 1):
        rob = robust and it > 1
        sub = data if todo.size == n else tuple(a[todo] for a in data)
        q = p[todo]
        dc, sig, st = _step(q, sub, shape, full, robust=rob, init=(it == 1 and init))
        p[todo] = q
        if last is None and todo.size == n:  # every mark's first state: the step's own
            last = st  # arrays (new ones each step), not copied
        else:
            if last is None:
                last = {k: np.empty((n,) + v.shape[1:], v.dtype) for k, v in st.items()}
            for k, v in st.items():
                last[k][todo] = v
        if (rob and it > 2) or not robust:
            done = _converged(dc, sig, tol)
            converged[todo[done]] = True
            todo = todo[~done]
            if todo.size == 0:
                break
    return last, it


def _converged(dc, sig, tol):
    """Marks whose centre update ``dc`` (px) is below ``tol`` or :data:`CONVERGED` times
    their centre's standard deviation ``sig`` (px)."""
    return dc < np.maximum(tol, CONVERGED * np.nan_to_num(sig, nan=0.0))


def _arm_outliers(p, data, shape, last, z_max=4.0):
    """The half-arm of each cross that disagrees with its opposite half, or -1.

    At the fitted geometry, each half-arm ``k`` (part index of :func:`_parts`) gives its own
    one-parameter estimate of the shift across its arm from the final weighted residuals,
    ``d_k = sum(w J r) / sum(w J^2)`` with ``J = b dT/dn`` (``n`` the across-arm mark-frame
    axis), and its standard deviation ``sigma0 / sqrt(sum(w J^2))``. The two halves of one arm
    measure the same coordinate: a difference beyond ``z_max`` standard deviations means a
    scene structure (an edge running along the arm, a saturated road) or damage has pulled one
    of them. The culprit is the half with the larger weighted mean square residual.

    Returns
    -------
    (N,) int
        Part index (0..3) to drop, or -1.
    """
    d, var, ms = _half_arm_shifts(p, data, shape, last)
    n = len(p)
    out = np.full(n, -1)
    worst = np.zeros(n)
    for a, c in ((0, 2), (1, 3)):
        z = np.abs(d[:, a] - d[:, c]) / np.sqrt(var[:, a] + var[:, c])
        z = np.nan_to_num(z, nan=0.0, posinf=0.0)
        flag = (z > z_max) & (z > worst)
        out[flag] = np.where(ms[flag, a] >= ms[flag, c], a, c)
        worst = np.where(flag, z, worst)
    return out


def _half_arm_shifts(p, data, shape, last):
    """Each half-arm's own estimate of the shift across its arm at the fitted geometry.

    Returns ``(d, var, ms)`` (N, 4) over the parts 0..3 of :func:`_parts`: the one-parameter
    shift ``d_k = sum(w J r) / sum(w J^2)`` (``J = b dT/dn``, ``n`` across the arm), its
    variance ``s0^2 / sum(w J^2)`` for independent pixels (inf for a half without weight)
    and the weighted mean square residual of the half.
    """
    if shape.kind == "cross" and kernels.ready():  # compiled: the same sums
        return kernels.half_arms(p, data, last, shape.width)
    X, Y, S = data[0], data[1], data[4]
    valid = data[3]
    # the geometry of each mark's last step (its update was below CONVERGED sigma)
    Tu, Tv, u, v = last["Tu"], last["Tv"], last["u"], last["v"]
    q = p.astype(np.float32)
    b = q[:, 8:9] - (S + q[:, 9:10] * X + q[:, 10:11] * Y + q[:, 11:12] * data[6])
    r, w = last["r"], last["w"] * valid
    parts = _parts(shape, u, v)
    n = len(p)
    d = np.zeros((n, 4))
    var = np.full((n, 4), np.inf)
    ms = np.zeros((n, 4))
    s0sq = np.maximum(last["s0sq"], 1e-30)
    for k in range(4):
        Jn = b * (Tv if k in (0, 2) else Tu)
        wk = np.where(parts == k, w, 0.0)
        den = (wk * Jn * Jn).sum(1, dtype=float)
        ok = den > 0
        d[ok, k] = (wk * Jn * r).sum(1, dtype=float)[ok] / den[ok]
        var[ok, k] = s0sq[ok] / den[ok]
        ms[:, k] = (wk * r * r).sum(1, dtype=float) / np.maximum(wk.sum(1, dtype=float), 1e-9)
    return d, var, ms


#: lags (px) of the residual correlation in :func:`_correlated_cov`: ``CORR_REACH`` x the
#: fitted blur plus 1, at most ``CORR_MAX_LAG`` (blurred grain decorrelates within about
#: 2.5 blur sigmas; the pixel footprint and interpolation within a pixel)
CORR_REACH = 2.5
CORR_MAX_LAG = 8
CORR_MIN_LAG = 3


def _correlated_cov(h, r, w, valid, X, Y, s0sq, blur):
    """The centre's covariance (N, 2, 2) with the residuals' correlation between neighbouring
    pixels: ``s0^2 Sum_lag rho(lag) Sum_i h_i h_{i+lag}^T``.

    Gauss-Newton's ``s0^2 N^-1`` assumes independent pixels; residuals of a scan are not
    (film grain blurred by the scanner optics, JPEG blocks, interpolation, model error over a
    few pixels): the effective number of independent pixels is smaller and the true variance
    larger. With ``h = N^-1 (sqrt(w) J)^T`` (rows: the centre's influence on each weighted
    pixel) the centre is ``Sum_i h_i sqrt(w_i) e_i``, so its covariance is the sandwich above,
    ``rho`` being the autocorrelation of the weighted residuals ``sqrt(w) r``, estimated per
    mark over its own pixels (pairs of valid pixels at each lag) within
    ``CORR_REACH * blur + 1`` px (at most :data:`CORR_MAX_LAG`). At lag 0 the sum is
    ``N^-1`` (white residuals: the usual covariance). ``X``, ``Y`` are the pixels' integer
    positions (any common origin per mark); all arrays (N, P) except ``h`` (N, 2, P).
    Where the result is not positive definite the usual covariance is kept.
    """
    from scipy import fft

    n, P = r.shape
    if n == 0:
        return np.zeros((0, 2, 2))
    big = 1e9
    ix = np.rint(X - np.where(valid, X, big).min(1, keepdims=True)).astype(np.int64)
    iy = np.rint(Y - np.where(valid, Y, big).min(1, keepdims=True)).astype(np.int64)
    ix[~valid] = 0
    iy[~valid] = 0
    gw = int(ix.max()) + 1
    gh = int(iy.max()) + 1
    K = int(min(CORR_MAX_LAG, np.ceil(CORR_REACH * max(float(np.nanmax(blur)) if np.size(blur)
                                                         else 1.0, 0.5)) + 1))
    K = max(CORR_MIN_LAG, K)
    K = max(1, min(K, gh - 1, gw - 1)) if min(gh, gw) > 1 else 0
    vf = valid.astype(np.float32)
    R = (np.sqrt(np.maximum(w, 0.0)) * r * vf).astype(np.float32)
    if kernels.ready():  # the few lags summed directly over the pixel pairs (compiled)
        return _cov_from_sums(kernels.corr_sums(ix, iy, valid, R, h, K), K, s0sq)
    shp = (fft.next_fast_len(gh + K), fft.next_fast_len(gw + K))
    # invalid pixels go to a spare cell past the grid (at the corner they would overwrite a
    # valid pixel there)
    flat = np.where(valid, iy * shp[1] + ix, shp[0] * shp[1])
    rows = np.arange(n)[:, None]

    def grid(vals):
        g = np.zeros((n, shp[0] * shp[1] + 1), np.float32)
        g[rows, flat] = np.where(valid, vals, 0.0)
        return g[:, :-1].reshape(n, *shp)

    grids = np.stack([grid(R), grid(vf), grid(h[:, 0]), grid(h[:, 1])], 1)  # (N, 4, h, w)
    # the chunks of marks run on the process's threads already: one FFT thread each
    F = fft.rfft2(grids, workers=1)
    del grids
    pairs = ((0, 0), (1, 1), (2, 2), (2, 3), (3, 3))
    prod = np.stack([np.conj(F[:, a]) * F[:, b] for a, b in pairs], 1)
    del F
    # Sum_i a_i b_{i+lag} at lags -K..K (rows, cols), (N, 5, 2K+1, 2K+1)
    cc = fft.irfft2(prod, s=shp, workers=1)
    del prod
    ks = np.r_[shp[0] - K : shp[0], 0 : K + 1]
    ls = np.r_[shp[1] - K : shp[1], 0 : K + 1]
    cc = cc[:, :, ks][:, :, :, ls].astype(float)
    return _cov_from_sums(cc, K, s0sq)


def _cov_from_sums(cc, K, s0sq):
    """:func:`_correlated_cov` from the sums ``cc`` (N, 5, 2K+1, 2K+1) over the lags."""
    n = cc.shape[0]
    rr, vv, kxx, kxy, kyy = (cc[:, j] for j in range(5))
    var0 = rr[:, K, K] / np.maximum(vv[:, K, K], 1.0)
    rho = (rr / np.maximum(vv, 1.0)) / np.maximum(var0, 1e-30)[:, None, None]
    rho = np.where(vv >= 8, rho, 0.0)  # lags with too few pairs carry nothing
    rho[:, K, K] = 1.0
    cxx = (rho * kxx).sum((1, 2))
    cyy = (rho * kyy).sum((1, 2))
    cxy = (rho * kxy).sum((1, 2))  # Sum over +-lag: symmetric (kyx(lag) = kxy(-lag))
    C = np.empty((n, 2, 2))
    C[:, 0, 0], C[:, 1, 1] = cxx, cyy
    C[:, 0, 1] = C[:, 1, 0] = cxy
    C *= np.asarray(s0sq, float)[:, None, None]
    return C


def _drop_sets(redo, part, full):
    """The marks ``redo`` refitted after the half-arm test dropped their half ``part`` (0..3),
    each set with its active parameters. With a held affine (``full`` without the affine),
    the tilt of the bar that lost a half is freed (``a10`` for the bar along ``u``, parts 0
    and 2; ``a01`` for the bar along ``v``, parts 1 and 3): the held affine let the test see
    the pulled half, but the centre of a bar measured from one half on a held tilt that is
    off by ``d`` moves by ``d L / 2`` (``L`` the half-arm; a held affine predicted by the
    neighbours misses the film's deformation at the grid's corners by 1e-3 and more, 0.05 px
    at 2900 dpi), while the remaining half measures its own tilt."""
    if full[2:6].all():
        return [(redo, full)]
    out = []
    for parts, k in (((0, 2), 4), ((1, 3), 3)):
        sel = np.isin(part, parts)
        if sel.any():
            act = full.copy()
            act[k] = True
            out.append((redo[sel], act))
    return out


def _refine(p, data, shape, active, todo, last, converged, max_iter, tol, prior=None):
    """Robust Gauss-Newton steps of the marks ``todo`` (in place on ``p``, ``last``,
    ``converged``) until each has converged; ``prior`` ``(k, value (all marks,), sd)`` as
    :func:`_add_prior`'s."""
    for _ in range(max_iter):
        sub = tuple(a[todo] for a in data)
        q = p[todo]
        pr = None if prior is None else (prior[0], prior[1][todo], prior[2])
        dc, sig, st = _step(q, sub, shape, active, robust=True, prior=pr)
        p[todo] = q
        for k_, v_ in st.items():
            last[k_][todo] = v_
        done = _converged(dc, sig, tol)
        converged[todo[done]] = True
        todo = todo[~done]
        if todo.size == 0:
            break


#: standard deviation of the prior on a bar's tilt about the held affine's when that tilt is
#: freed (:func:`_refit_dropped`): the neighbours' prediction misses the film's deformation by
#: about 1e-3 at a small reseau's corners (1.4e-3 and 1.7e-3 on the sweep's 3 x 3 grids at
#: 2900-3000 dpi). Where one half of a bar measures its tilt far better (long arms at a high
#: resolution) the data decide; where not (short arms, scene content beside the half) the
#: held tilt does
TILT_PRIOR = 1e-3


def _refit_dropped(p, data, shape, full, act, todo, last, converged, max_iter, tol):
    """Refit the marks ``todo`` after the half-arm test dropped a half (in place): with the
    parameters ``full``, then, where ``act`` frees a bar's tilt (:func:`_drop_sets`), from
    there with the tilt estimated under the prior :data:`TILT_PRIOR` about the held one."""
    _refine(p, data, shape, full, todo, last, converged, max_iter, tol)
    free = np.where(act & ~full)[0]
    if free.size == 0:
        return
    held = p[:, free[0]].copy()
    _refine(p, data, shape, act, todo, last, converged, max_iter, tol,
            prior=(int(free[0]), held, TILT_PRIOR))


def _model_patches(patches, origin, ref, X, Y, valid, M):
    """The patches (N, h, w) with the fitted model ``M`` (N, P) in place of the data at the
    fit's pixels (``X``, ``Y`` relative to ``ref``, pixel system): an estimate of the scan
    before its JPEG compression over the marks."""
    n, h, w = patches.shape
    out = np.array(patches, np.float32)
    col = np.rint(X + (ref[:, 0:1] - origin[:, 0:1])).astype(np.int64)
    row = np.rint(Y + (ref[:, 1:2] - origin[:, 1:2])).astype(np.int64)
    ok = valid & (col >= 0) & (col < w) & (row >= 0) & (row < h)
    mark = np.broadcast_to(np.arange(n)[:, None], ok.shape)
    out[mark[ok], row[ok], col[ok]] = M[ok]
    return out


def lsm(
    patches: np.ndarray,
    origin: np.ndarray,
    c0: np.ndarray,
    A0: np.ndarray,
    shape: MarkShape,
    s0: float,
    init_err: float = 2.0,
    robust: bool = True,
    max_iter: int = 10,
    tol: float = 5e-4,
    fit_shape: bool = True,
    background: np.ndarray | None = None,
    weight: np.ndarray | None = None,
    arm_check: bool = True,
    arm_z: float = 3.0,
    sat_bg: np.ndarray | None = None,
    clip: tuple[float, float] | None = None,
    fit_blur: bool = True,
    correlated: bool = True,
    quant: np.ndarray | None = None,
) -> LSMResult:
    """Fit the analytic mark model to N patches at once.

    Parameters
    ----------
    patches : (N, h, w) float array
        Grey values (any linear scale); NaN where a patch leaves the image.
    origin : (N, 2) float
        Pixel coordinates (x, y) of each patch's element [0, 0].
    c0 : (N, 2) float
        Initial centres (pixel system), within about ``init_err`` px of the truth.
    A0 : (2, 2) or (N, 2, 2) float
        Initial pixel -> mark-frame affine (from the global grid model).
    shape : MarkShape
        The mark's drawn geometry at the nominal scale (px).
    s0 : float
        Expected blur (px), the starting value of ``s``.
    init_err : float
        Expected error of ``c0`` (px); above 0.75 px a capture stage with a wide blur runs first.
    robust : bool
        Tukey pixel weights after the first fine iteration.
    max_iter : int
        Iterations of the fine stage.
    tol : float
        Convergence threshold on the centre update (px).
    fit_shape : bool
        Estimate the affine ``A`` (else keep ``A0``).
    background : (N, h, w) float array, optional
        An estimate of the scene under each mark (e.g. the patch with the thin mark removed by
        a morphological opening or closing); the model's background is then this estimate
        plus a constant and a tilt. Without it the background is a plane.
    weight : (N, h, w) float array, optional
        Prior pixel weights in [0, 1] (e.g. low where the background estimate is uncertain);
        they multiply the robust weights.

    arm_check : bool
        Crosses only: compare the two halves of each arm (see :func:`_arm_outliers`); where
        they disagree beyond ``arm_z`` standard deviations, the half that fits worse gets
        weight 0 and the mark is fitted again from the other three (without ``fit_shape``
        then with the tilt of the bar that lost a half estimated under a prior about the held
        one, :func:`_refit_dropped`).
    arm_z : float
        Threshold of that test.
    sat_bg : (N, h, w) array of 0/1, optional
        Where the background estimate is saturated: the scene there may lie beyond the grey
        range, so the model adds a free level ``sat`` (one per mark) to the background there;
        the unsaturated part of the mark's edges against it determines it.
    clip : (lo, hi), optional
        The grey range of the scan: values at its ends are censored (Tobit): they count only
        where the model is inside the range.
    fit_blur : bool
        Estimate the blur ``s`` (else hold it at ``s0`` in the fine stage).
    correlated : bool
        The centre's covariance allows for residuals correlated between neighbouring pixels
        (:func:`_correlated_cov`); False: ``s0^2 N^-1`` (independent pixels).
    quant : (8, 8) float, optional
        The variances (grey units squared) of the scan's JPEG quantisation errors of its block
        DCT coefficients (:func:`softplot.marks.jpegq.of_scan`; blocks on the pixel system's
        8 x 8 grid): what they add to the centre's covariance is ``cov_jpeg``
        (:func:`softplot.marks.jpegq.centre_term`).

    Returns
    -------
    LSMResult
    """
    patches = np.asarray(patches, np.float32)
    n = patches.shape[0]
    origin = np.asarray(origin, float).reshape(n, 2)
    c0 = np.asarray(c0, float).reshape(n, 2)
    ref = np.round(c0)
    A0 = np.broadcast_to(np.asarray(A0, float), (n, 2, 2)).copy()
    s0 = max(float(s0), 0.3)
    s_cap = float(np.hypot(s0, init_err)) if init_err > 0.75 else s0
    p = np.zeros((n, _NP))
    p[:, 0:2] = c0 - ref
    p[:, 2:6] = A0.reshape(n, 4)
    p[:, 6] = s_cap

    full = np.ones(_NP, bool)
    if not fit_shape:
        full[2:6] = False
    if not fit_blur:
        full[6] = False
    capture = np.zeros(_NP, bool)
    capture[[0, 1, 7, 8, 9, 10, 11]] = True

    def gather(margin):
        return _gather(patches, origin, ref, p[:, 0:2] + ref, p[:, 2:6].reshape(n, 2, 2),
                       shape, margin, background, weight, sat_bg, clip)

    # capture stage: wide blur, only position and radiometry, generous pixel margin
    if s_cap > s0:
        data = gather(3.0 * s_cap + init_err + 1.0)
        for i in range(3):
            _step(p, data, shape, capture, robust=False, init=i == 0)[:2]
        p[:, 6] = s0
    # fine stage: all parameters, tight margin around the mark, robust weights
    data = gather(2.5 * s0 + 1.25)
    converged = np.zeros(n, bool)
    # each mark's state at its last step (the solution to within 0.2 sigma)
    last, it = _fine_stage(p, data, shape, full, robust, s_cap <= s0, max_iter, tol, converged)
    if arm_check and shape.kind == "cross" and robust:
        bad = _arm_outliers(p, data, shape, last, z_max=arm_z)
        redo = np.where(bad >= 0)[0]
        if redo.size:
            geo = _geom(p[redo], tuple(a[redo] for a in data), shape)
            drop = _parts(shape, geo[4], geo[5]) == bad[redo, None]
            Wp = data[5]
            Wp[redo] = np.where(drop, 0.0, Wp[redo])
            for todo, act in _drop_sets(redo, bad[redo], full):
                _refit_dropped(p, data, shape, full, act, todo, last, converged, max_iter, tol)
    X, Y, G, valid, Sb = data[:5]
    vf = valid.astype(np.float32)
    sw = np.maximum(vf.sum(1), 1.0)
    npix = valid.sum(1)

    # final statistics: each mark's last step (its update was below CONVERGED sigma)
    M, T, u, v, r = last["M"], last["T"], last["u"], last["v"], last["r"]
    noise = _mad(r, valid)
    w_rob = last["w_rob"]
    sigma0 = np.sqrt(last["s0sq"])
    cov = cov_white = last["cov"]
    if correlated:
        cc = _correlated_cov(last["h"], r, last["w"], valid, X, Y, last["s0sq"], p[:, 6])
        det = cc[:, 0, 0] * cc[:, 1, 1] - cc[:, 0, 1] ** 2
        tr0 = cov[:, 0, 0] + cov[:, 1, 1]
        # a sum below the independent pixels' is not taken (fits with many nuisance
        # parameters, the joint scene, leave anti-correlated residuals)
        good = ((cc[:, 0, 0] > 0) & (det > 0) & np.all(np.isfinite(cc.reshape(n, 4)), 1)
                & (cc[:, 0, 0] + cc[:, 1, 1] >= tr0))
        cov = np.where(good[:, None, None], cc, cov)
    cov_jpeg = np.zeros((n, 2, 2))
    if quant is not None:
        g = last["h"] * np.sqrt(np.maximum(last["w"], 0.0))[:, None, :]
        add = jpegq.centre_term(g, X + ref[:, 0:1], Y + ref[:, 1:2], valid, quant,
                                _model_patches(patches, origin, ref, X, Y, valid, M), origin)
        cov_jpeg = np.where(np.isfinite(add), add, 0.0)

    # correlation of the data with the fitted mark, the fitted background removed from both
    B = (p[:, 7:8] + Sb + p[:, 9:10] * X + p[:, 10:11] * Y + p[:, 11:12] * data[6]).astype(
        np.float32)
    # the contrast as seen (a mark of opacity a darkens the scene by a (m - B)), as an
    # opaque fit of the same mark gives it
    gain = _contrast(p, data, T)
    if shape.opacity != 1.0:
        gain = gain * shape.opacity
    dG = (G - B) * vf
    dM = (M - B) * vf
    dG -= (dG.sum(1) / sw)[:, None] * vf
    dM -= (dM.sum(1) / sw)[:, None] * vf
    score = (dG * dM).sum(1) / np.sqrt(np.maximum((dG**2).sum(1) * (dM**2).sum(1), 1e-30))

    # support of each part of the mark: share of well-fitting pixels near the drawn shape
    parts = _parts(shape, u, v)
    near = support_mask(shape, u, v, 1.5 * p[:, 6:7] + 1.0) & valid
    good = (w_rob > 0.5) & near
    K = 4 if shape.kind in ("cross", "bar") else 1
    support = np.empty((n, K))
    part_gain = np.full((n, K), np.nan)
    wf = last["w"] * vf
    for k in range(K):
        sel = near & (parts == k)
        support[:, k] = (good & sel).sum(1) / np.maximum(sel.sum(1), 1)
        # the contrast of this part alone at the fitted geometry (the regression of data
        # minus fitted background on the template over the part's weighted pixels)
        wk = np.where(parts == k, wf, 0.0)
        den = (wk * T * T).sum(1, dtype=float)
        num = (wk * T * (G - B)).sum(1, dtype=float)
        part_gain[:, k] = np.where(den > 1e-6 * np.maximum(wk.sum(1), 1e-12), num /
                                   np.maximum(den, 1e-30), np.nan)
    if shape.opacity != 1.0:  # (T is the template times the opacity: as gain, as seen)
        part_gain *= shape.opacity

    return LSMResult(
        centre=p[:, 0:2] + ref,
        A=p[:, 2:6].reshape(n, 2, 2).copy(),
        s=p[:, 6].copy(),
        offset=p[:, 7].copy(),
        gain=gain,
        cov=cov,
        sigma0=sigma0,
        noise=noise,
        score=score,
        support=support,
        converged=converged,
        iterations=it,
        npix=npix,
        level=p[:, 7] + p[:, 8],
        cov_white=cov_white,
        part_gain=part_gain,
        snr=np.sqrt((dM.astype(float) ** 2).sum(1)) / noise,
        cov_jpeg=cov_jpeg,
    )
