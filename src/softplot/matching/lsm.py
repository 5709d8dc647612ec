"""Least-squares matching of image patches, vectorised over many points.

For each point a square template of ``(2h+1)^2`` pixels is cut from the *left* image at an
integer pixel; the *right* image is resampled (bicubic) through a per-point affine map and a
linear radiometric map::

    left(u, v) = r0 + r1 * right(x + a0 + a1 u + a2 v, y + b0 + b1 u + b2 v)

(u, v the template offsets in pixels, x, y the right start position). Gauss-Newton on all
points at once (one ``cv2.remap`` per iteration for every patch). The matched right
position of the template centre is ``(x + a0, y + b0)``; its covariance is
``s0^2 (J'J)^-1`` restricted to ``a0, b0``, with ``s0^2 = v'v / (n - 8)`` the grey-value
residual variance of the patch. Coordinates: pixel system of each image (x right, y down,
origin at the centre of the top-left pixel).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["PatchMatch", "match_patches"]


@dataclass
class PatchMatch:
    """Result of :func:`match_patches` (N points).

    Attributes
    ----------
    xy : ndarray (N, 2)
        Matched right pixel position of each template centre.
    std : ndarray (N, 2)
        Standard deviation of ``xy``, px.
    corr : ndarray (N,)
        Correlation coefficient of the template and the resampled right patch.
    affine : ndarray (N, 2, 2)
        Local linear map left pixel offsets -> right pixel offsets.
    ok : ndarray of bool (N,)
        Converged, inside the image, well conditioned.
    """

    xy: np.ndarray
    std: np.ndarray
    corr: np.ndarray
    affine: np.ndarray
    ok: np.ndarray


def match_patches(left: np.ndarray, right: np.ndarray, left_xy, right_xy, affine=None, *,
                  half: int = 10, iterations: int = 15, max_shift: float = 3.0) -> PatchMatch:
    """Refine right positions of left integer pixels by least-squares matching.

    Parameters
    ----------
    left, right : ndarray (H, W), float32
        Grey images (pixel system).
    left_xy : array_like (N, 2)
        Left template centres, px; rounded to integer pixels (the returned match is of the
        rounded position: use ``np.rint(left_xy)`` as the left point).
    right_xy : array_like (N, 2)
        Approximate right positions of ``left_xy`` (not of the rounded ones), px.
    affine : array_like (2, 2) or (N, 2, 2), optional
        Approximate linear map left -> right offsets (identity when None).
    half : int
        Template half size (the template is ``2 half + 1`` pixels square).
    iterations : int
    max_shift : float
        Largest move of a point from its start, px (further: not ok).
    """
    left = np.ascontiguousarray(left, np.float32)
    right = np.ascontiguousarray(right, np.float32)
    pl = np.rint(np.asarray(left_xy, float).reshape(-1, 2)).astype(np.int64)
    n = len(pl)
    A = np.broadcast_to(np.eye(2) if affine is None else np.asarray(affine, float),
                        (n, 2, 2)).copy()
    d = pl - np.asarray(left_xy, float).reshape(-1, 2)
    start = np.asarray(right_xy, float).reshape(-1, 2) + np.einsum("nij,nj->ni", A, d)
    if n == 0:
        z = np.zeros((0, 2))
        return PatchMatch(z, z.copy(), np.zeros(0), np.zeros((0, 2, 2)), np.zeros(0, bool))
    g = np.arange(-half, half + 1, dtype=np.float64)
    u, v = (a.ravel() for a in np.meshgrid(g, g))
    P = u.size
    H, W = left.shape
    inside = ((pl[:, 0] >= half) & (pl[:, 0] < W - half) & (pl[:, 1] >= half)
              & (pl[:, 1] < H - half))
    pl_c = np.clip(pl, half, [W - half - 1, H - half - 1])
    rows = pl_c[:, 1, None] + v.astype(np.int64)[None, :]
    cols = pl_c[:, 0, None] + u.astype(np.int64)[None, :]
    T = left[rows, cols].astype(np.float64)  # (n, P)
    # central differences (as numpy.gradient inside the image), by OpenCV: fast on huge scans
    k = np.array([[-0.5, 0.0, 0.5]], np.float32)
    gx_img = cv2.filter2D(right, cv2.CV_32F, k, borderType=cv2.BORDER_REPLICATE)
    gy_img = cv2.filter2D(right, cv2.CV_32F, k.T, borderType=cv2.BORDER_REPLICATE)
    # parameters: a0 a1 a2 b0 b1 b2 r0 r1
    p = np.zeros((n, 8))
    p[:, 0] = start[:, 0]
    p[:, 1:3] = A[:, 0]
    p[:, 3] = start[:, 1]
    p[:, 4:6] = A[:, 1]
    p[:, 7] = 1.0
    active = inside.copy()
    Hr, Wr = right.shape
    for _ in range(iterations):
        mx = p[:, 0, None] + p[:, 1, None] * u + p[:, 2, None] * v
        my = p[:, 3, None] + p[:, 4, None] * u + p[:, 5, None] * v
        mx32, my32 = mx.astype(np.float32), my.astype(np.float32)
        G = cv2.remap(right, mx32, my32, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        Gx = cv2.remap(gx_img, mx32, my32, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        Gy = cv2.remap(gy_img, mx32, my32, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        G, Gx, Gy = (a.astype(np.float64) for a in (G, Gx, Gy))
        r1 = p[:, 7, None]
        J = np.stack([r1 * Gx, r1 * Gx * u, r1 * Gx * v, r1 * Gy, r1 * Gy * u, r1 * Gy * v,
                      np.ones_like(G), G], axis=2)  # (n, P, 8)
        res = T - (p[:, 6, None] + r1 * G)
        N = np.einsum("npi,npj->nij", J, J) + 1e-12 * np.eye(8)
        b = np.einsum("npi,np->ni", J, res)
        try:
            dp = np.linalg.solve(N, b[..., None])[..., 0]
        except np.linalg.LinAlgError:
            dp = np.stack([np.linalg.lstsq(Ni, bi, rcond=None)[0] for Ni, bi in zip(N, b,
                                                                                   strict=True)])
        dp[~active] = 0.0
        p += dp
        if np.all(np.abs(dp[active][:, [0, 3]]) < 1e-3):
            break
    # final residuals and covariance
    mx = p[:, 0, None] + p[:, 1, None] * u + p[:, 2, None] * v
    my = p[:, 3, None] + p[:, 4, None] * u + p[:, 5, None] * v
    mx32, my32 = mx.astype(np.float32), my.astype(np.float32)
    G = cv2.remap(right, mx32, my32, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    Gx = cv2.remap(gx_img, mx32, my32, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    Gy = cv2.remap(gy_img, mx32, my32, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    G, Gx, Gy = (a.astype(np.float64) for a in (G, Gx, Gy))
    r1 = p[:, 7, None]
    J = np.stack([r1 * Gx, r1 * Gx * u, r1 * Gx * v, r1 * Gy, r1 * Gy * u, r1 * Gy * v,
                  np.ones_like(G), G], axis=2)
    res = T - (p[:, 6, None] + r1 * G)
    s02 = np.sum(res * res, axis=1) / (P - 8)
    N = np.einsum("npi,npj->nij", J, J)
    with np.errstate(invalid="ignore", divide="ignore"):
        cond = np.linalg.cond(N[:, :6, :6]) if n else np.zeros(0)
        Q = np.linalg.pinv(N)
        # the grey-value residuals of neighbouring pixels are correlated (the optics' blur,
        # the resampling of the right patch): Cov = s0^2 Q (J' C J) Q with C their
        # correlation (pooled over all patches), not s0^2 Q
        # (only the shifts' variances: q' J' C J q with q the shift's row of Q)
        side = 2 * half + 1
        var = np.stack([_sandwich(np.einsum("npi,ni->np", J, Q[:, i]).reshape(n, side, side),
                                  res.reshape(n, side, side), active) for i in (0, 3)], 1)
        std = np.sqrt(np.maximum(s02[:, None] * var, 0.0))
        Tc = T - T.mean(axis=1, keepdims=True)
        Gc = G - G.mean(axis=1, keepdims=True)
        corr = np.sum(Tc * Gc, axis=1) / np.sqrt(np.sum(Tc * Tc, axis=1) * np.sum(Gc * Gc, axis=1))
    xy = np.c_[p[:, 0], p[:, 3]]
    moved = np.hypot(*(xy - start).T)
    ok = (inside & np.all(np.isfinite(xy), axis=1) & (moved <= max_shift) & np.isfinite(corr)
          & (xy[:, 0] >= half) & (xy[:, 0] <= Wr - 1 - half) & (xy[:, 1] >= half)
          & (xy[:, 1] <= Hr - 1 - half) & (cond < 1e8) & (p[:, 7] > 0)
          & np.all(np.isfinite(std), axis=1))
    aff = np.stack([p[:, 1:3], p[:, 4:6]], axis=1)
    return PatchMatch(xy, std, corr, aff, ok)


#: largest pixel lag of the residual correlation taken into account
MAX_LAG = 3


def _sandwich(t, res, use, max_lag: int = MAX_LAG) -> np.ndarray:
    """``sum_pq t_p rho(p - q) t_q`` (n,) of patches t (n, s, s) (a parameter's influence
    field ``J q``), residuals res (n, s, s); ``rho`` the residual correlation by pixel lag,
    pooled over the patches ``use`` (each patch's residuals normalised by its own
    variance). Lags beyond ``max_lag`` or where the pooled correlation is insignificant
    count as 0."""
    n, s = res.shape[:2]
    r = res - res.mean(axis=(1, 2), keepdims=True)
    var = np.mean(r * r, axis=(1, 2))
    pick = use & (var > 0)
    if not pick.any():
        pick = var > 0
    rn = r[pick] / np.sqrt(var[pick])[:, None, None]
    out = np.sum(t * t, axis=(1, 2))  # lag 0 (rho = 1)
    for dy in range(0, max_lag + 1):
        for dx in range(-max_lag, max_lag + 1):
            if dy == 0 and dx <= 0:
                continue
            ya, yb = slice(0, s - dy), slice(dy, s)
            xa, xb = (slice(0, s - dx), slice(dx, s)) if dx >= 0 else (slice(-dx, s),
                                                                     slice(0, s + dx))
            a = rn[:, ya, xa]
            rho = float(np.mean(a * rn[:, yb, xb])) if a.size else 0.0
            if not abs(rho) > 2.0 / np.sqrt(max(a.size, 1)):
                continue
            out += 2.0 * rho * np.sum(t[:, ya, xa] * t[:, yb, xb], axis=(1, 2))
    return out
