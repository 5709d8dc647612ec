"""Space intersection: object points from two or more rays of oriented photos.

Vectorised over points: every object point is its own small Gauss-Markov problem (3 unknowns,
``2k`` photo observations for ``k`` rays); all points are solved together with batched 3x3
normal equations - no per-point Python loop.

Start: the point nearest to all rays in the least-squares sense,
``sum_k (I - d_k d_k') X = sum_k (I - d_k d_k') X0_k`` (``d_k`` unit ray directions, object
frame). Then Gauss-Newton on the collinearity equations (photo residuals, weights from the
photo standard errors) until the steps vanish.

Precision (``docs/orientation.md``): per point ``Qxx = N^-1``, redundancy ``2k - 3`` and its own
``sigma0``; the reported covariance is ``s0^2 Qxx`` with the *pooled* ``s0 = sqrt(sum v'Pv / sum
r)`` of all points (photos and measuring conditions are shared; a two-ray point alone has one
degree of freedom). ``covariance="point"`` uses each point's own sigma0, ``"prior"`` the a
priori sigma.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softplot.adjust import Snooping, UndeterminedError, data_snooping, snooping_json
from softplot.errors import SoftplotError
from softplot.geometry.collinearity import camera_coordinates, image_rays
from softplot.geometry.rotation import rotation_matrix

__all__ = ["Intersection", "intersect", "intersect_pair"]


@dataclass
class Intersection:
    """Result of :func:`intersect` (P object points from K photo observations).

    Attributes
    ----------
    XYZ : ndarray, shape (P, 3)
        Object coordinates.
    cofactor : ndarray, shape (P, 3, 3)
        ``N^-1`` per point (unit: object^2 / (photo mm)^2 times sigma0_prior^2).
    covariance : ndarray, shape (P, 3, 3)
        Covariance per point (see the module docstring for the sigma0 used).
    sigma0 : ndarray, shape (P,)
        Per-point a posteriori sigma0, photo mm (nan with redundancy 0).
    sigma0_pooled : float
        Pooled sigma0 of all points.
    redundancy : ndarray of int, shape (P,)
        ``2k - 3``.
    n_rays : ndarray of int, shape (P,)
    rms : ndarray, shape (P,)
        RMS of the photo residuals of each point, mm.
    residuals : ndarray, shape (K, 2)
        Photo residuals of every observation (projected minus observed), mm.
    standardized : ndarray, shape (K, 2)
        Baarda's w of every photo coordinate (using the a priori sigma).
    flagged : ndarray of bool, shape (P,)
        Points with an observation beyond the critical value.
    iterations : int
    """

    XYZ: np.ndarray
    cofactor: np.ndarray
    covariance: np.ndarray
    sigma0: np.ndarray
    sigma0_pooled: float
    redundancy: np.ndarray
    n_rays: np.ndarray
    rms: np.ndarray
    residuals: np.ndarray
    standardized: np.ndarray
    flagged: np.ndarray
    iterations: int
    #: data snooping over every photo coordinate (w-test or tau test, pooled redundancy)
    snooping: Snooping | None = None
    #: the point name of every photo coordinate (K*2), for ``blunders``
    obs_labels: tuple = ()

    def snooping_json(self) -> dict:
        """``{"blunders": [point names, most likely first], "snooping_test": {...}}``."""
        return snooping_json(self.snooping, list(self.obs_labels) or None)

    @property
    def std(self) -> np.ndarray:
        """Standard deviations of X, Y, Z per point, shape (P, 3)."""
        return np.sqrt(np.clip(np.einsum("pii->pi", self.covariance), 0.0, None))


def _inv3(N):
    """Inverses (P, 3, 3) of symmetric 3x3 matrices by cofactors, and their determinants."""
    a, b, c = N[:, 0, 0], N[:, 0, 1], N[:, 0, 2]
    d, e, f = N[:, 1, 1], N[:, 1, 2], N[:, 2, 2]
    A = d * f - e * e
    B = c * e - b * f
    C = b * e - c * d
    det = a * A + b * B + c * C
    inv = np.empty_like(N)
    inv[:, 0, 0] = A
    inv[:, 0, 1] = inv[:, 1, 0] = B
    inv[:, 0, 2] = inv[:, 2, 0] = C
    inv[:, 1, 1] = a * f - c * c
    inv[:, 1, 2] = inv[:, 2, 1] = b * c - a * e
    inv[:, 2, 2] = a * d - b * b
    with np.errstate(divide="ignore", invalid="ignore"):
        inv /= det[:, None, None]
    return inv, det


def _scaled_det(N):
    """Determinant of the unit-diagonal scaled matrices: ~0 when (near-)singular."""
    dg = np.einsum("pii->pi", N)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = 1.0 / np.sqrt(dg)
        Ns = N * s[:, :, None] * s[:, None, :]
    _, det = _inv3(np.nan_to_num(Ns))
    return np.where(np.all(dg > 0, axis=1), det, 0.0)


def _batched_solve(N, b):
    inv, _ = _inv3(N)
    return np.einsum("pij,pj->pi", inv, b)


_SYM = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def _normal_matrices(point, Jx, Jw, P):
    """Per-point ``sum J' P J`` (P, 3, 3) from the six unique products, by bincount."""
    N = np.empty((P, 3, 3))
    for i, j in _SYM:
        v = Jx[:, 0, i] * Jw[:, 0, j] + Jx[:, 1, i] * Jw[:, 1, j]
        N[:, i, j] = N[:, j, i] = np.bincount(point, weights=v, minlength=P)
    return N


def _accumulate(point, values, P):
    """Sum ``values`` (K, ...) per point -> (P, ...) with bincount (np.add.at is slow)."""
    flat = values.reshape(len(values), -1)
    out = np.empty((P, flat.shape[1]))
    for j in range(flat.shape[1]):
        out[:, j] = np.bincount(point, weights=flat[:, j], minlength=P)
    return out.reshape((P,) + values.shape[1:])


def _project_dX(XYZ, C, R, c, x0, y0):
    """Photo coordinates (K, 2) and their derivative w.r.t. the object point (K, 2, 3).

    ``R`` is the tuple of the three rows of every observation's rotation, each (K, 3).
    """
    d = XYZ - C
    u0 = np.einsum("ki,ki->k", R[0], d)
    u1 = np.einsum("ki,ki->k", R[1], d)
    w = np.einsum("ki,ki->k", R[2], d)
    qx = u0 / w
    qy = u1 / w
    f = np.empty((len(w), 2))
    f[:, 0] = x0 - c * qx
    f[:, 1] = y0 - c * qy
    # d xy / d u = [[-c/w, 0, c qx/w], [0, -c/w, c qy/w]];  d u / d X = M
    a = (-c / w)[:, None]
    J = np.empty((len(w), 2, 3))
    J[:, 0, :] = a * (R[0] - qx[:, None] * R[2])
    J[:, 1, :] = a * (R[1] - qy[:, None] * R[2])
    return f, J


def intersect(
    xy,
    point,
    photo,
    X0,
    angles,
    c,
    x0=0.0,
    y0=0.0,
    *,
    sigma=1.0,
    n_points: int | None = None,
    point_names=None,
    covariance: str = "pooled",
    alpha0: float = 0.001,
    max_iter: int = 20,
    tol: float = 1e-12,
    precision_known: bool = True,
) -> Intersection:
    """Intersect rays of oriented photos (least squares, vectorised over points).

    Parameters
    ----------
    xy : array_like, shape (K, 2)
        Photo coordinates of every observation, mm.
    point : array_like of int, shape (K,)
        Object point index (0..P-1) of every observation.
    photo : array_like of int, shape (K,)
        Photo index (0..F-1) of every observation.
    X0 : array_like, shape (F, 3)
        Projection centres, object frame.
    angles : array_like, shape (F, 3)
        ``omega, phi, kappa`` of every photo, radians.
    c, x0, y0 : float or array_like (F,)
        Interior orientation of every photo, mm.
    sigma : float or array_like (K,) or (K, 2)
        Standard error of the photo coordinates, mm (the median is the a priori sigma0).
    n_points : int, optional
        Number of object points P (default ``max(point) + 1``).
    point_names : sequence of str, optional
        Names for error messages.
    covariance : {"pooled", "point", "prior"}
        Which sigma0 scales the reported covariance.
    alpha0 : float
        Significance level of data snooping.
    precision_known : bool
        Whether ``sigma`` states the photo coordinates' precision: Baarda's w-test against it;
        else Pope's tau test against the pooled a posteriori sigma0 (redundancy summed over the
        points).
    max_iter : int
    tol : float
        Convergence when every coordinate step is below ``tol`` times the coordinate magnitude
        (plus 1).

    Returns
    -------
    Intersection

    Raises
    ------
    UndeterminedError
        A point with fewer than two rays or (nearly) parallel rays; the message names the
        point's X, Y, Z.
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    K = len(xy)
    point = np.asarray(point, dtype=int).ravel()
    photo = np.asarray(photo, dtype=int).ravel()
    X0 = np.asarray(X0, dtype=float).reshape(-1, 3)
    angles = np.asarray(angles, dtype=float).reshape(-1, 3)
    F = len(X0)
    if point.size != K or photo.size != K:
        raise SoftplotError("intersection: point and photo indices must match the observations")
    if angles.shape[0] != F:
        raise SoftplotError("intersection: X0 and angles must describe the same photos")
    if K == 0:
        raise SoftplotError("intersection: no observations")
    if photo.min() < 0 or photo.max() >= F:
        raise SoftplotError("intersection: photo index out of range")
    if point.min() < 0:
        raise SoftplotError("intersection: negative point index")
    if not np.all(np.isfinite(xy)):
        raise SoftplotError("intersection: photo coordinates must be finite")
    if covariance not in ("pooled", "point", "prior"):
        raise SoftplotError(f"intersection: unknown covariance mode {covariance!r}")
    P = int(point.max()) + 1 if n_points is None else int(n_points)
    names = list(point_names) if point_names is not None else [str(i) for i in range(P)]
    cF = np.broadcast_to(np.asarray(c, dtype=float), (F,))
    x0F = np.broadcast_to(np.asarray(x0, dtype=float), (F,))
    y0F = np.broadcast_to(np.asarray(y0, dtype=float), (F,))
    sig = np.asarray(sigma, dtype=float)
    if sig.ndim == 0:
        sig = np.full((K, 2), float(sig))
    elif sig.ndim == 1:
        sig = np.repeat(sig[:, None], 2, axis=1)
    if sig.shape != (K, 2) or np.any(~(sig > 0)):
        raise SoftplotError("intersection: sigma must be positive, a number or (K,) or (K,2)")
    s_prior = float(np.median(sig))
    p = (s_prior / sig) ** 2
    Ms = rotation_matrix(angles[:, 0], angles[:, 1], angles[:, 2])
    Mk = Ms[photo]
    Ck = X0[photo]
    nr = np.bincount(point, minlength=P)

    def undetermined(bad):
        shown = ", ".join(names[i] for i in bad[:5]) + (" ..." if len(bad) > 5 else "")
        raise UndeterminedError(
            f"intersection: X, Y, Z of point(s) {shown} not determined "
            "(fewer than 2 rays or parallel rays)",
            [f"{a}_{names[i]}" for i in bad for a in "XYZ"],
        )

    if np.any(nr < 2):
        undetermined(list(np.nonzero(nr < 2)[0]))
    # linear start: nearest point to the rays
    d = image_rays(xy, Mk, cF[photo], x0F[photo], y0F[photo])
    A = np.eye(3)[None] - d[:, :, None] * d[:, None, :]
    NA = _accumulate(point, A, P)
    bA = _accumulate(point, np.einsum("kij,kj->ki", A, Ck), P)
    bad = np.nonzero(_scaled_det(NA) <= 1e-10)[0]
    if bad.size:
        undetermined(list(bad))
    XYZ = _batched_solve(NA, bA)
    ck, x0k, y0k = cF[photo], x0F[photo], y0F[photo]
    Rk = tuple(np.ascontiguousarray(Ms[photo, i, :]) for i in range(3))

    def normals(XYZ):
        f, Jx = _project_dX(XYZ[point], Ck, Rk, ck, x0k, y0k)
        Jw = Jx * p[:, :, None]
        N = _normal_matrices(point, Jx, Jw, P)
        return f, Jx, Jw, N

    it = 0
    for it in range(1, max_iter + 1):  # noqa: B007
        f, Jx, Jw, N = normals(XYZ)
        b = _accumulate(point, np.einsum("kai,ka->ki", Jw, xy - f), P)
        dX = _batched_solve(N, b)
        XYZ = XYZ + dX
        if np.all(np.abs(dX) <= tol * (1.0 + np.abs(XYZ))):
            break
    f, Jx, Jw, N = normals(XYZ)
    bad = np.nonzero(_scaled_det(N) <= 1e-12)[0]
    if bad.size:
        undetermined(list(bad))
    Q, _ = _inv3(N)
    u = camera_coordinates(XYZ[point], Ck, Mk)
    if np.any(u[:, 2] >= 0):
        behind = sorted(set(point[u[:, 2] >= 0].tolist()))
        raise SoftplotError(
            "intersection: point(s) "
            + ", ".join(names[i] for i in behind[:5])
            + " intersect behind a camera"
        )
    v = f - xy
    vpv = np.bincount(point, weights=np.sum(p * v**2, axis=1), minlength=P)
    r = 2 * nr - 3
    with np.errstate(invalid="ignore", divide="ignore"):
        s0 = np.where(r > 0, np.sqrt(vpv / np.where(r > 0, r, 1)), np.nan)
    pooled = float(np.sqrt(vpv.sum() / r.sum())) if r.sum() > 0 else float("nan")
    if covariance == "pooled":
        scale = np.full(P, pooled if np.isfinite(pooled) else s_prior)
    elif covariance == "point":
        scale = np.where(np.isfinite(s0), s0, s_prior)
    else:
        scale = np.full(P, s_prior)
    cov = Q * (scale**2)[:, None, None]
    # residual cofactors: qvv = 1/p - J Q J'
    h = np.einsum("kai,kai->ka", np.matmul(Jx, Q[point]), Jx)
    qvv = np.clip(1.0 / p - h, 0.0, None)
    ri = p * qvv
    sn = data_snooping(v.ravel(), qvv.ravel(), p.ravel(), int(r.sum()),
                       sigma0_prior=s_prior if precision_known else None, alpha0=alpha0)
    w = np.where(ri > 1e-8, sn.statistic.reshape(-1, 2), np.nan)
    fl_obs = sn.flagged.reshape(-1, 2)
    flagged = np.bincount(point, weights=fl_obs.any(axis=1).astype(float), minlength=P) > 0
    rms = np.sqrt(np.bincount(point, weights=np.sum(v**2, axis=1), minlength=P) / (2 * nr))
    return Intersection(
        XYZ=XYZ,
        cofactor=Q,
        covariance=cov,
        sigma0=s0,
        sigma0_pooled=pooled,
        redundancy=r,
        n_rays=nr,
        rms=rms,
        residuals=v,
        standardized=w,
        flagged=flagged,
        iterations=it,
        snooping=sn,
        obs_labels=tuple(np.repeat(np.asarray(names, dtype=object)[point], 2)),
    )


def intersect_pair(xy1, xy2, X01, angles1, X02, angles2, c1, c2=None, *, sigma=1.0, **kwargs):
    """Intersect the rays of N homologous points of two photos (convenience wrapper).

    Parameters
    ----------
    xy1, xy2 : array_like, shape (N, 2)
        Photo coordinates in photos 1 and 2, mm.
    X01, X02 : array_like, shape (3,)
        Projection centres.
    angles1, angles2 : array_like, shape (3,)
        ``omega, phi, kappa`` of the photos, radians.
    c1, c2 : float
        Principal distances (``c2 = c1`` by default).
    sigma : float
        Photo standard error, mm.
    **kwargs
        Passed to :func:`intersect`.
    """
    xy1 = np.asarray(xy1, dtype=float).reshape(-1, 2)
    xy2 = np.asarray(xy2, dtype=float).reshape(-1, 2)
    n = len(xy1)
    if xy2.shape != xy1.shape:
        raise SoftplotError("intersection: the two photos need the same number of points")
    idx = np.arange(n)
    return intersect(
        np.r_[xy1, xy2],
        np.r_[idx, idx],
        np.r_[np.zeros(n, int), np.ones(n, int)],
        np.vstack([X01, X02]),
        np.vstack([angles1, angles2]),
        np.array([c1, c1 if c2 is None else c2], dtype=float),
        sigma=sigma,
        n_points=n,
        **kwargs,
    )
