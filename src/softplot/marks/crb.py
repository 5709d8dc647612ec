"""Cramér-Rao bound of a mark's centre: the best precision any unbiased estimator can reach.

For an image ``g_i = f_i(theta) + n_i`` with white Gaussian noise of standard deviation
``sigma_n``, the Fisher information is ``F = J^T J / sigma_n^2`` with ``J = df/dtheta`` over all
pixels, and ``cov(theta_hat) >= F^-1``. :func:`centre_crb` evaluates it numerically with the
same analytic model LSM fits (a blurred mark seen through square pixels, see
:mod:`softplot.marks.template`) and all its nuisance parameters (affine shape, blur, background
level and tilt, contrast), so the bound is the one for *this* estimation problem, not an
idealised one. It returns the scalar ``sqrt((var_x + var_y) / 2)`` in pixels, averaged over
sub-pixel phases of the mark.

Closed form for a cross (docs/accuracy.md). A bar edge blurred by ``sigma_b`` has the
profile ``C * Phi(t / sigma_b)``; its derivative ``C * phi(t / sigma_b) / sigma_b`` carries
``integral (C phi / sigma_b)^2 dt = C^2 / (2 sqrt(pi) sigma_b)`` of information per unit length
about a shift across it. The vertical bar of a cross (tip-to-tip length ``2L``) has two edges,
so ``I_x = 2L * 2 * C^2 / (2 sqrt(pi) sigma_b sigma_n^2)`` and::

    sigma_x >= (sigma_n / C) * sqrt(sqrt(pi) * sigma_b / (2 L))

(:func:`cross_crb_simple`). It ignores the tips, the pixel footprint and the overlap of the two
edges of a thin line (a line narrower than about ``3 sigma_b`` carries less information than two
separate edges, so the true bound is larger) and assumes the nuisance parameters known.
"""

from __future__ import annotations

import numpy as np

from softplot.marks.lsm import _parts
from softplot.marks.template import MarkShape, aperture

#: parameters of the bound: LSM's model on an unsaturated background (centre, affine, blur,
#: offset, contrast, tilt)
_NP = 11

__all__ = ["centre_crb", "cross_crb_simple", "effective_noise", "render_crb"]


def cross_crb_simple(contrast: float, noise: float, blur: float, arm_half_px: float) -> float:
    """The closed-form bound ``(sigma_n/C) sqrt(sqrt(pi) sigma_b / (2 L))`` (px)."""
    return float(noise / contrast * np.sqrt(np.sqrt(np.pi) * blur / (2.0 * arm_half_px)))


def effective_noise(noise_sigma: float, bits: int | None) -> float:
    """Noise standard deviation including quantisation (``LSB^2 / 12``), full scale 1."""
    q = 0.0 if not bits or bits >= 32 else 1.0 / (2**bits - 1)
    return float(np.sqrt(noise_sigma**2 + q * q / 12.0))


def _scene_shift_columns(shape, A, u, v, T, B, blur):
    """Image derivatives with respect to a shift of the scene across each half-arm.

    For half-arm ``k`` (part index of :func:`softplot.marks.lsm._parts`) the scene content
    in its footprint zone (``|n| <= w/2 + 2.5 s_e + 0.5``, ``n`` the across-arm mark-frame
    axis, ``s_e = sqrt(blur^2 + 1/12)``) is read at ``p - beta_k e_n`` (``e_n`` the pixel
    vector of a unit step along ``n``); the image ``B (1 - T) + m T`` then changes by
    ``-(1 - T) grad(B) . e_n`` per unit ``beta_k`` there. ``B`` is the scene window (pixel
    system, rows down), ``u``, ``v`` its mark-frame coordinates. Returns ``(cols (..., 4),
    zone half-width n0)``.
    """
    gy, gx = np.gradient(np.asarray(B, float))
    Ai = np.linalg.inv(np.asarray(A, float))
    parts = _parts(shape, u, v)
    n0 = 0.5 * shape.width + 2.5 * float(np.hypot(blur, np.sqrt(1.0 / 12.0))) + 0.5
    cols = []
    for k in range(4):
        across, e = (v, Ai[:, 1]) if k in (0, 2) else (u, Ai[:, 0])
        zone = (parts == k) & (np.abs(across) <= n0)
        cols.append(np.where(zone, -(1.0 - T) * (gx * e[0] + gy * e[1]), 0.0))
    return np.stack(cols, -1), n0


def _centre_variance(shape, A, dx, dy, blur, b, noise, mark_level=None, clip=None,
                     scene_shift=False):
    """``(var_x + var_y) / 2`` of the centre under LSM's model, from the Fisher information.

    ``dx``, ``dy``: pixel offsets from the true centre (any equal shapes); ``A`` the pixel ->
    mark-frame affine; ``b``: mark minus background, a number or per pixel. The 11 parameters
    are LSM's (centre, affine, blur, background and mark levels, background tilt). With
    ``clip`` (and ``mark_level``), pixels are weighted by their censored information
    (:func:`_censored_information`). With ``scene_shift`` (and ``mark_level``, ``b`` per
    pixel) four more nuisance parameters: the scene's shift across each half-arm
    (:func:`_scene_shift_columns`), each with the prior ``N(0, n0^2)``. NaN if the
    information matrix is singular.
    """
    dx = np.asarray(dx, float)
    dy = np.asarray(dy, float)
    u = (A[0, 0] * dx + A[0, 1] * dy).astype(np.float32)
    v = (A[1, 0] * dx + A[1, 1] * dy).astype(np.float32)
    ap = tuple(np.float32(q) for q in aperture(A))
    T, Tu, Tv, Ts = (np.asarray(t, float) for t in shape.evaluate(u, v, np.float32(blur),
                                                                  aperture=ap))
    b = np.broadcast_to(np.asarray(b, float), T.shape)
    J = np.stack([
        -b * (Tu * A[0, 0] + Tv * A[1, 0]), -b * (Tu * A[0, 1] + Tv * A[1, 1]),
        b * Tu * dx, b * Tu * dy, b * Tv * dx, b * Tv * dy, b * Ts,
        1.0 - T, T, dx * (1.0 - T), dy * (1.0 - T)], -1)
    prior = np.zeros(_NP)
    if scene_shift:
        cols, n0 = _scene_shift_columns(shape, A, u, v, T, mark_level - b, blur)
        J = np.concatenate([J, cols], -1)
        prior = np.concatenate([prior, np.full(4, 1.0 / n0**2)])
    J = J.reshape(-1, J.shape[-1])
    wt = np.ones(J.shape[0])
    if clip is not None:
        mu = ((mark_level - b) * (1.0 - T) + mark_level * T).ravel()
        wt = _censored_information(np.minimum(clip[1] - mu, mu - clip[0]) / noise)
    F = (J * wt[:, None]).T @ J / noise**2 + np.diag(prior)
    try:
        cov = np.linalg.inv(F)
    except np.linalg.LinAlgError:
        return float("nan")
    return float(0.5 * (cov[0, 0] + cov[1, 1]))


def centre_crb(shape: MarkShape, blur: float, contrast: float, noise: float,
               A=None, phases: int = 4, seed: int = 0) -> float:
    """Cramér-Rao bound (px) of the centre of ``shape`` under the full LSM model.

    Parameters
    ----------
    shape : MarkShape
        The mark (px).
    blur : float
        Gaussian blur sigma (px) of the scanner (the pixel footprint is added by the model).
    contrast : float
        Mark minus background (grey units, sign irrelevant).
    noise : float
        Noise standard deviation (same units), see :func:`effective_noise`.
    A : (2, 2), optional
        Pixel -> mark-frame affine (rotation); identity if omitted.
    phases : int
        Sub-pixel positions averaged (the bound varies slightly with the phase).
    """
    A = np.eye(2) if A is None else np.asarray(A, float)
    half = int(np.ceil(shape.extent / max(np.linalg.svd(A, compute_uv=False).min(), 1e-3)
                       + 5 * blur + 6))
    yy, xx = np.mgrid[-half : half + 1, -half : half + 1].astype(np.float64)
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(phases):
        c = rng.uniform(-0.5, 0.5, 2)
        dx = (xx - c[0]).astype(np.float32)
        dy = (yy - c[1]).astype(np.float32)
        out.append(_centre_variance(shape, A, dx, dy, blur, contrast, noise))
    return float(np.sqrt(np.mean(out)))


def _censored_information(z):
    """Fisher information about a Gaussian mean, relative to ``1/sigma^2``, when the sample
    is clipped at a level ``z`` standard deviations beyond the mean (Tobit model)::

        i(z) = Phi(z) - z phi(z) + phi(z)^2 / (1 - Phi(z))

    1 far from the clip, 0.82 with the mean at the clip, 0 far beyond it.
    """
    from scipy.special import ndtr

    z = np.asarray(z, float)
    zc = np.clip(z, -40.0, 8.0)
    phi = np.exp(-0.5 * zc * zc) / np.sqrt(2.0 * np.pi)
    tail = np.maximum(ndtr(-zc), 1e-300)
    out = ndtr(zc) - zc * phi + phi * phi / tail
    return np.where(z > 8.0, 1.0, np.clip(out, 0.0, 1.0))


def render_crb(scene: np.ndarray, centres: np.ndarray, A: np.ndarray, shape: MarkShape,
               blur: float, mark_level: float, noise: float,
               clip: tuple[float, float] | None = (0.0, 1.0),
               scene_shift: bool = False) -> np.ndarray:
    """Cramér-Rao bound (px) of each mark's centre in one render, its scene included.

    The bound of :func:`centre_crb` assumes one contrast over a flat background. A mark in a
    photograph hides a scene that varies under it; this bound uses, pixel by pixel, the
    render's own image model ``mu = B (1 - T) + m T`` (``B`` the scene the mark hides, ``m`` the
    mark's level, ``T`` the blurred mark of :mod:`softplot.marks.template`), so each pixel
    informs the centre in proportion to its own contrast ``m - B``. Pixels near the ends of the
    grey range are censored by the scanner (a saturated pixel says only "at least this
    bright"); their information is scaled by the Tobit factor of :func:`_censored_information`.
    The nuisance parameters are those LSM estimates (affine shape, blur, mark level, background
    offset and tilt); the scene ``B`` itself is taken as known, so the bound is optimistic
    (lower) wherever an estimator must also infer the scene.

    Parameters
    ----------
    scene : (H, W) float array
        The render without its marks and without noise (grey, the image's linear scale),
        pixel system.
    centres : (N, 2)
        True centres (pixel system).
    A : (N, 2, 2)
        Pixel -> mark-frame affine of each mark.
    shape : MarkShape
        The mark at the nominal scale (px).
    blur : float
        Gaussian blur sigma of the render (px; the pixel footprint is in the model).
    mark_level : float
        Grey level of the mark itself.
    noise : float
        Noise standard deviation (incl. quantisation, :func:`effective_noise`).
    clip : (lo, hi) or None
        Grey range of the image (censoring); None for no censoring.
    scene_shift : bool
        Also estimate, per half-arm, a shift of the scene across the arm inside the bar's
        footprint (prior sd: the footprint's half-width; :func:`_scene_shift_columns`): the
        bound of an estimator that knows the scene's content but not where under each
        half-arm its edges lie. On the busy renders it is within 3.3 % of the bound with
        the scene known (docs/accuracy.md).

    Returns
    -------
    (N,) float
        ``sqrt((var_x + var_y) / 2)`` of each centre (px); NaN where the window leaves the
        image.
    """
    scene = np.asarray(scene, float)
    centres = np.asarray(centres, float).reshape(-1, 2)
    A = np.broadcast_to(np.asarray(A, float), (len(centres), 2, 2))
    H, W = scene.shape
    out = np.full(len(centres), np.nan)
    for i, (c, Ai) in enumerate(zip(centres, A, strict=True)):
        grow = 1.0 / max(np.linalg.svd(Ai, compute_uv=False).min(), 1e-3)
        half = int(np.ceil(shape.extent * grow + 5 * blur + 4))
        x0, y0 = int(round(c[0])) - half, int(round(c[1])) - half
        if x0 < 0 or y0 < 0 or x0 + 2 * half + 1 > W or y0 + 2 * half + 1 > H:
            continue
        B = scene[y0 : y0 + 2 * half + 1, x0 : x0 + 2 * half + 1]
        yy, xx = np.mgrid[y0 : y0 + 2 * half + 1, x0 : x0 + 2 * half + 1].astype(float)
        dx, dy = xx - c[0], yy - c[1]
        var = _centre_variance(shape, Ai, dx, dy, blur, mark_level - B, noise, mark_level,
                               clip, scene_shift)
        if np.isfinite(var):
            out[i] = float(np.sqrt(max(var, 0.0)))
    return out
