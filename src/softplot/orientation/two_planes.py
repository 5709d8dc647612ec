"""Projection centres by two planes, resection on fiducials, the differential procedure.

After G. Birardi, "Computing and checking the projection centers in analogical plotters", ISP
Congress Hamburg 1980 (``docs/orientation.md`` reconstructs the OCR-garbled formulas).
Instrument frame: X, Y horizontal carriage coordinates, Z height, all in mm.

Two planes (Birardi 2.1)
    A point A of the plate (a grid cross of known photo coordinates ``x, y``) is read at two
    heights: ``(X1, Y1)`` in the plane ``Z = Z1`` and ``(X2, Y2)`` in ``Z = Z2``. The ray
    through both readings passes through the projection centre ``(X0, Y0, Z0)``::

        (X1 - X2) / (Z1 - Z2) = (X1 - X0) / (Z1 - Z0)       (and Y alike)

    With ``a = -(X1 - X2)``, ``b = -(Y1 - Y2)``, ``c = Z1 - Z2`` and approximate values
    ``x0, y0, z0`` of the centre this is Birardi's linear system (3)::

        c dx + a dz + kx = vx,   kx = c (x0 - X1) + a (z0 - Z1)
        c dy + b dz + ky = vy,   ky = c (y0 - Y1) + b (z0 - Z1)

    ``method="birardi"`` solves it by least squares, each equation divided by
    ``sqrt((Z2 - Z0)^2 + (Z0 - Z1)^2)`` - the standard error of a condition in units of a
    reading error - so that sigma0 estimates the reading error. ``method="rigorous"`` (the
    default) starts from it and adjusts the readings themselves: unknowns ``X0, Y0, Z0`` and
    the two slopes ``tx, ty`` of every ray, observations ``X_k = X0 + tx (Z_k - Z0)``,
    ``Y_k = Y0 + ty (Z_k - Z0)`` (k = 1, 2), redundancy ``4n - 3 - 2n = 2n - 3``.

    Principal distance (Birardi 4-6): every point gives
    ``f_i = -c sqrt(x_i^2 + y_i^2) / sqrt(a_i^2 + b_i^2)`` (``Z1 < Z2`` so ``-c > 0``; the
    absolute value is used) and the weighted mean ``f = [p f] / [p]`` with Birardi's
    ``p_i = (a_i^2 + b_i^2)^2``; ``f_weights="rigorous"`` uses ``p_i = a_i^2 + b_i^2`` (the
    standard error of ``f_i`` is ``f sqrt(2) s / sqrt(a_i^2 + b_i^2)`` for a reading error s).

Resection on fiducials (Birardi 2.2)
    The fiducial marks of the photo carrier (photo coordinates ``x_i, y_i`` known) are read
    in ONE plane ``Z = h`` at any attitude: ``X_i = X0 + (h - Z0) d_x / d_z``,
    ``Y_i = Y0 + (h - Z0) d_y / d_z`` with ``d = M' (x_i, y_i, -F)``. Unknowns ``X0, Y0, Z0,
    omega, phi, kappa``, observations the readings, rigorous partial derivatives (Birardi's
    (9) are their vertical-photo simplification); start from a space resection.

Differential procedure (Birardi 2.3)
    ``PC_model = PC_two_planes + (PC_fiducials_model - PC_fiducials_reference)``: the shift of
    the fiducial resection between the reference epoch and the model is applied to the
    two-plane centre; independent of the calibration of the fiducials and of the interior
    orientation. Covariance: the sum of the three (independent) covariances.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softplot.adjust import Adjustment, least_squares, linear_least_squares
from softplot.errors import SoftplotError
from softplot.geometry.rotation import rotation_derivatives, rotation_matrix
from softplot.orientation._adjusted import AdjustedResult
from softplot.orientation.resection import EO_NAMES, resect

__all__ = [
    "TwoPlanes",
    "two_planes",
    "principal_distance",
    "FiducialResection",
    "fiducial_resection",
    "Differential",
    "differential",
    "plane_readings",
]


@dataclass
class TwoPlanes(AdjustedResult):
    """Result of :func:`two_planes` (instrument mm).

    Attributes
    ----------
    X0 : ndarray, shape (3,)
        Projection centre.
    covariance : ndarray, shape (3, 3)
    adjustment : Adjustment
        The adjustment (Birardi's linear one, or the rigorous one whose first three unknowns
        are X0, Y0, Z0).
    residuals : ndarray, shape (n, 4)
        ``vX1, vY1, vX2, vY2`` (rigorous) or ``vx, vy, nan, nan`` (birardi, in reading units).
    f : float or None
        Weighted mean principal distance (None without photo coordinates).
    f_std : float or None
        Its standard error (propagated from the reading error sigma0).
    f_i : ndarray or None, shape (n,)
        Per-point principal distances (nan for a point at the principal point).
    p_i : ndarray or None, shape (n,)
        Their weights.
    method : str
    """

    X0: np.ndarray
    covariance: np.ndarray
    adjustment: Adjustment
    residuals: np.ndarray
    f: float | None
    f_std: float | None
    f_i: np.ndarray | None
    p_i: np.ndarray | None
    method: str

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))


def _xy(a, n=None, what="readings"):
    a = np.asarray(a, dtype=float)
    if a.ndim != 2 or a.shape[1] != 2 or (n is not None and len(a) != n):
        raise SoftplotError(f"two planes: {what} must be (n,2), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise SoftplotError(f"two planes: {what} must be finite")
    return a


def principal_distance(XY1, Z1, XY2, Z2, xy, weights: str = "birardi", sigma: float = 0.0):
    """Birardi's per-point principal distance and its weighted mean (equations 4-6).

    Parameters
    ----------
    XY1, XY2 : array_like, shape (n, 2)
        Readings of the points in the planes ``Z1`` and ``Z2``, instrument mm.
    Z1, Z2 : float or array_like (n,)
        Plane heights, instrument mm.
    xy : array_like, shape (n, 2)
        Photo coordinates of the points (reduced to the principal point), mm.
    weights : {"birardi", "rigorous"}
        ``p_i = (a_i^2 + b_i^2)^2`` (Birardi) or ``a_i^2 + b_i^2`` (inverse variance).
    sigma : float
        Reading standard error, for the standard error of the mean.

    Returns
    -------
    f : float
    f_std : float
        Standard error of ``f`` from ``sigma`` (0 if sigma is 0).
    f_i : ndarray, shape (n,)
    p_i : ndarray, shape (n,)
        Weights (0 for a point at the principal point, whose ``f_i`` is nan).
    """
    XY1 = _xy(XY1)
    XY2 = _xy(XY2, len(XY1))
    xy = _xy(xy, len(XY1), "photo coordinates")
    a = -(XY1[:, 0] - XY2[:, 0])
    b = -(XY1[:, 1] - XY2[:, 1])
    c = np.broadcast_to(np.asarray(Z1, float) - np.asarray(Z2, float), (len(a),))
    rho = np.hypot(a, b)
    r = np.hypot(xy[:, 0], xy[:, 1])
    ok = (rho > 1e-12 * (np.abs(c) + 1)) & (r > 1e-9)
    if not ok.any():
        raise SoftplotError("two planes: every point is at the principal point; f is undefined")
    with np.errstate(invalid="ignore", divide="ignore"):
        f_i = np.where(ok, np.abs(c) * r / rho, np.nan)
    if weights == "birardi":
        p = np.where(ok, rho**4, 0.0)
    elif weights == "rigorous":
        p = np.where(ok, rho**2, 0.0)
    else:
        raise SoftplotError(f"two planes: unknown f weights {weights!r} (birardi|rigorous)")
    f = float(np.sum(p[ok] * f_i[ok]) / np.sum(p[ok]))
    s_i = f * np.sqrt(2.0) * sigma / np.where(ok, rho, np.inf)
    f_std = float(np.sqrt(np.sum((p[ok] * s_i[ok]) ** 2)) / np.sum(p[ok]))
    return f, f_std, f_i, p


def two_planes(
    XY1,
    Z1,
    XY2,
    Z2,
    xy=None,
    *,
    sigma: float = 0.001,
    method: str = "rigorous",
    f_weights: str = "birardi",
    alpha0: float = 0.001,
) -> TwoPlanes:
    """Projection centre from points read in two planes (Birardi 1980, 2.1).

    Parameters
    ----------
    XY1 : array_like, shape (n, 2)
        Readings ``X1, Y1`` of the points in the plane ``Z = Z1``, instrument mm (n >= 2).
    Z1 : float or array_like (n,)
    XY2 : array_like, shape (n, 2)
        Readings in the plane ``Z = Z2``.
    Z2 : float or array_like (n,)
    xy : array_like, shape (n, 2), optional
        Photo coordinates of the points (for the principal distance), mm.
    sigma : float
        Standard error of one reading, mm (a priori sigma0).
    method : {"rigorous", "birardi"}
        Adjust the readings (default) or Birardi's linear condition system (3).
    f_weights : {"birardi", "rigorous"}
        Weights of the principal-distance mean.
    alpha0 : float
        Significance level of data snooping.

    Returns
    -------
    TwoPlanes

    Raises
    ------
    UndeterminedError
        The planes coincide (Z0 not determined) or the rays are all parallel.
    """
    XY1 = _xy(XY1)
    n = len(XY1)
    XY2 = _xy(XY2, n)
    if n < 2:
        raise SoftplotError(f"two planes: need >= 2 points, got {n}")
    Z1a = np.broadcast_to(np.asarray(Z1, dtype=float), (n,))
    Z2a = np.broadcast_to(np.asarray(Z2, dtype=float), (n,))
    if method not in ("rigorous", "birardi"):
        raise SoftplotError(f"two planes: unknown method {method!r} (rigorous|birardi)")
    a = -(XY1[:, 0] - XY2[:, 0])
    b = -(XY1[:, 1] - XY2[:, 1])
    c = Z1a - Z2a
    # Birardi's linear system, reduced to approximate values (centroid of the lower readings)
    x0a, y0a = XY1.mean(axis=0)
    z0a = float(np.mean(Z1a))
    names = ("X0", "Y0", "Z0")
    zz = np.zeros(n)
    A = np.vstack([np.c_[c, zz, a], np.c_[zz, c, b]])
    k = np.r_[c * (x0a - XY1[:, 0]) + a * (z0a - Z1a), c * (y0a - XY1[:, 1]) + b * (z0a - Z1a)]
    # scale each condition to reading units: d(cond)/d(readings) = (Z2 - Z0, Z0 - Z1)
    s = np.ones(2 * n)
    lin = None
    for _ in range(3):
        lin = linear_least_squares(
            A / s[:, None],
            -k / s,
            sigma,
            names=names,
            sigma0_prior=sigma,
            alpha0=alpha0,
            what="two planes",
        )
        Z0 = z0a + lin.x[2]
        s = np.tile(np.sqrt((Z2a - Z0) ** 2 + (Z0 - Z1a) ** 2), 2)
    X0_lin = np.array([x0a, y0a, z0a]) + lin.x
    if method == "birardi":
        adj = lin
        adj.x = X0_lin
        res = np.c_[lin.residuals[:n], lin.residuals[n:], np.full((n, 2), np.nan)]
        X0 = X0_lin
        cov = lin.covariance
    else:
        Zs = np.c_[Z1a, Z2a]
        if np.any(np.abs(Z1a - Z2a) <= 0):
            tx = ty = np.zeros(n)
        else:
            tx = (XY1[:, 0] - XY2[:, 0]) / (Z1a - Z2a)
            ty = (XY1[:, 1] - XY2[:, 1]) / (Z1a - Z2a)
        x_start = np.r_[X0_lin, tx, ty]
        obs = np.c_[XY1[:, 0], XY1[:, 1], XY2[:, 0], XY2[:, 1]].ravel()
        u = 3 + 2 * n
        rows = np.arange(n)

        def fun(x):
            X0_, Y0_, Z0_ = x[:3]
            txx, tyy = x[3 : 3 + n], x[3 + n :]
            dz = Zs - Z0_  # (n, 2)
            f = np.empty((n, 4))
            f[:, 0] = X0_ + txx * dz[:, 0]
            f[:, 1] = Y0_ + tyy * dz[:, 0]
            f[:, 2] = X0_ + txx * dz[:, 1]
            f[:, 3] = Y0_ + tyy * dz[:, 1]
            J = np.zeros((n, 4, u))
            J[:, [0, 2], 0] = 1.0
            J[:, [1, 3], 1] = 1.0
            J[:, 0, 2] = J[:, 2, 2] = -txx
            J[:, 1, 2] = J[:, 3, 2] = -tyy
            J[rows, 0, 3 + rows] = dz[:, 0]
            J[rows, 2, 3 + rows] = dz[:, 1]
            J[rows, 1, 3 + n + rows] = dz[:, 0]
            J[rows, 3, 3 + n + rows] = dz[:, 1]
            return f.ravel(), J.reshape(4 * n, u)

        unames = list(names) + [f"tx{i}" for i in range(n)] + [f"ty{i}" for i in range(n)]
        adj = least_squares(
            fun,
            x_start,
            obs,
            sigma,
            names=unames,
            sigma0_prior=sigma,
            alpha0=alpha0,
            what="two planes",
        )
        X0 = adj.x[:3].copy()
        cov = adj.covariance[:3, :3]
        res = adj.residuals.reshape(n, 4)
    f = f_std = f_i = p_i = None
    if xy is not None:
        f, _, f_i, p_i = principal_distance(XY1, Z1a, XY2, Z2a, xy, f_weights)
        s_read = adj.sigma0 if adj.redundancy > 0 else sigma
        _, f_std, _, _ = principal_distance(XY1, Z1a, XY2, Z2a, xy, f_weights, s_read)
    return TwoPlanes(
        X0=X0,
        covariance=cov,
        adjustment=adj,
        residuals=res,
        f=f,
        f_std=f_std,
        f_i=f_i,
        p_i=p_i,
        method=method,
    )


def plane_readings(xy, Z, X0, angles, F):
    """Readings ``(X, Y)`` where the rays of photo points meet the plane(s) ``Z``.

    Parameters
    ----------
    xy : array_like, shape (n, 2)
        Photo coordinates (reduced to the principal point), mm.
    Z : float or array_like (n,)
        Height of the reading plane, instrument mm.
    X0 : array_like, shape (3,)
        Projection centre.
    angles : array_like, shape (3,)
        ``omega, phi, kappa``, radians.
    F : float
        Principal distance, mm.

    Returns
    -------
    ndarray, shape (n, 2)
        Instrument X, Y, mm.
    """
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    n = len(xy)
    q = np.c_[xy, np.full(n, -float(F))]
    d = q @ rotation_matrix(*angles)  # rows: (M' q)'
    t = (np.broadcast_to(np.asarray(Z, float), (n,)) - X0[2]) / d[:, 2]
    return np.c_[X0[0] + t * d[:, 0], X0[1] + t * d[:, 1]]


@dataclass
class FiducialResection(AdjustedResult):
    """Result of :func:`fiducial_resection` (instrument mm, radians).

    Attributes
    ----------
    X0 : ndarray, shape (3,)
    angles : ndarray, shape (3,)
    adjustment : Adjustment
        Unknowns :data:`softplot.orientation.resection.EO_NAMES`.
    residuals : ndarray, shape (n, 2)
        Reading residuals ``vX, vY``, mm.
    """

    X0: np.ndarray
    angles: np.ndarray
    adjustment: Adjustment
    residuals: np.ndarray

    @property
    def covariance(self) -> np.ndarray:
        return self.adjustment.covariance

    @property
    def std(self) -> np.ndarray:
        return self.adjustment.std


def fiducial_resection(
    xy,
    XY,
    Z,
    F: float,
    *,
    sigma: float = 0.001,
    start=None,
    alpha0: float = 0.001,
) -> FiducialResection:
    """Space resection on marks read in one plane (Birardi 1980, 2.2), rigorous.

    Parameters
    ----------
    xy : array_like, shape (n, 2)
        Photo coordinates of the marks (fiducials of the photo carrier), mm, n >= 3.
    XY : array_like, shape (n, 2)
        Instrument readings of the marks in the plane ``Z``, mm.
    Z : float or array_like (n,)
        Height of the reading plane.
    F : float
        Principal distance, mm (e.g. ``TwoPlanes.f``).
    sigma : float
        Reading standard error, mm (a priori sigma0).
    start : (X0, angles), optional
        Initial values (default: a space resection treating the readings as control).
    alpha0 : float

    Returns
    -------
    FiducialResection
    """
    xy = _xy(xy, what="photo coordinates")
    n = len(xy)
    XY = _xy(XY, n)
    if n < 3:
        raise SoftplotError(f"fiducial resection: need >= 3 marks, got {n}")
    Zs = np.broadcast_to(np.asarray(Z, dtype=float), (n,))
    if start is None:
        r0 = resect(xy, np.c_[XY, Zs], F)
        start = (r0.X0, r0.angles)
    x_start = np.r_[np.asarray(start[0], float), np.asarray(start[1], float)]
    q = np.c_[xy, np.full(n, -float(F))]
    obs = XY.ravel()

    def fun(x):
        M = rotation_matrix(*x[3:6])
        dMs = rotation_derivatives(*x[3:6])
        d = q @ M  # (n,3) = M' q
        h = Zs - x[2]
        qx, qy = d[:, 0] / d[:, 2], d[:, 1] / d[:, 2]
        f = np.c_[x[0] + h * qx, x[1] + h * qy]
        J = np.zeros((n, 2, 6))
        J[:, 0, 0] = 1.0
        J[:, 1, 1] = 1.0
        J[:, 0, 2] = -qx
        J[:, 1, 2] = -qy
        for i, dM in enumerate(dMs):
            dd = q @ dM
            J[:, 0, 3 + i] = h * (dd[:, 0] * d[:, 2] - d[:, 0] * dd[:, 2]) / d[:, 2] ** 2
            J[:, 1, 3 + i] = h * (dd[:, 1] * d[:, 2] - d[:, 1] * dd[:, 2]) / d[:, 2] ** 2
        return f.ravel(), J.reshape(2 * n, 6)

    adj = least_squares(
        fun,
        x_start,
        obs,
        sigma,
        names=EO_NAMES,
        sigma0_prior=sigma,
        alpha0=alpha0,
        what="fiducial resection",
    )
    return FiducialResection(
        X0=adj.x[:3].copy(),
        angles=adj.x[3:6].copy(),
        adjustment=adj,
        residuals=adj.residuals.reshape(n, 2),
    )


@dataclass
class Differential:
    """Result of :func:`differential` (instrument mm).

    Attributes
    ----------
    X0 : ndarray, shape (3,)
        Corrected projection centre of the model.
    covariance : ndarray, shape (3, 3)
    delta : ndarray, shape (3,)
        ``dX0, dY0, dZ0``: model fiducial resection minus reference fiducial resection.
    delta_covariance : ndarray, shape (3, 3)
    """

    X0: np.ndarray
    covariance: np.ndarray
    delta: np.ndarray
    delta_covariance: np.ndarray

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance))


def _pc(obj):
    X0 = np.asarray(getattr(obj, "X0", obj), dtype=float)[:3]
    cov = getattr(obj, "covariance", None)
    cov = np.zeros((3, 3)) if cov is None else np.asarray(cov, dtype=float)[:3, :3]
    return X0, cov


def differential(two_planes_pc, reference, model) -> Differential:
    """Birardi's differential procedure (2.3 a-d).

    Parameters
    ----------
    two_planes_pc : TwoPlanes or array_like (3,)
        Projection centre by two planes at the reference epoch (a).
    reference : FiducialResection or array_like (3,)
        Fiducial resection at the same epoch, lower plane, with the two-plane f (b).
    model : FiducialResection or array_like (3,)
        Fiducial resection in the oriented model (c).

    Returns
    -------
    Differential
        ``X0 = PC_a + (PC_c - PC_b)`` (d); covariance the sum of the three covariances (zero
        for plain arrays).
    """
    a, Ca = _pc(two_planes_pc)
    b, Cb = _pc(reference)
    c, Cc = _pc(model)
    delta = c - b
    return Differential(
        X0=a + delta, covariance=Ca + Cb + Cc, delta=delta, delta_covariance=Cb + Cc
    )
