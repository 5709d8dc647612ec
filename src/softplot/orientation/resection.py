"""Space resection: exterior orientation of one photo from >= 3 control points.

No initial values are needed. The start comes from

* ``n = 3``: P3P (Grunert's distance equations solved by a bracketed 1-D root search, then the
  rigid fit of the three camera-frame points, :func:`p3p`) - up to four solutions;
* ``n >= 4``: OpenCV ``solvePnP`` (SQPnP) and P3P on a well-spread triple, the candidate with
  the smallest reprojection error over all points winning;

then the collinearity equations are adjusted by Gauss-Newton
(:func:`softplot.adjust.least_squares`).

Camera conventions (``docs/orientation.md``). OpenCV's camera frame has x right, y down, z
forward; the photogrammetric photo frame has x right, y up, z backward with principal distance
``c > 0``. With ``C = diag(1, -1, -1)`` and OpenCV's ``x_cam = R X + t``::

    M = C R,    X0 = -R' t,    OpenCV image point (x - x0, -(y - y0)) with K = diag(c, c, 1)

Control points may carry standard errors ``sX, sY, sZ``: they then become unknowns observed
with those standard errors (weighted control); without them they are fixed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import scipy.optimize

from softplot.adjust import Adjustment, least_squares, snooping_json
from softplot.errors import SoftplotError
from softplot.geometry.collinearity import camera_coordinates, project, project_jacobian
from softplot.geometry.rotation import angles_from_matrix, rotation_matrix
from softplot.orientation._adjusted import AdjustedResult
from softplot.orientation.absolute import kabsch

__all__ = [
    "Resection",
    "resect",
    "p3p",
    "pnp_start",
    "opencv_to_photogrammetric",
    "photogrammetric_to_opencv",
    "EO_NAMES",
]

#: names of the exterior orientation unknowns, in order
EO_NAMES = ("X0", "Y0", "Z0", "omega", "phi", "kappa")

_C = np.diag([1.0, -1.0, -1.0])


def opencv_to_photogrammetric(R, t):
    """OpenCV pose ``x_cam = R X + t`` -> ``(M, X0)``: ``M = C R``, ``X0 = -R' t``."""
    R = np.asarray(R, dtype=float)
    t = np.asarray(t, dtype=float).ravel()
    return _C @ R, -R.T @ t


def photogrammetric_to_opencv(M, X0):
    """``(M, X0)`` -> OpenCV ``(R, t)`` with ``x_cam = R X + t``."""
    R = _C @ np.asarray(M, dtype=float)
    return R, -R @ np.asarray(X0, dtype=float)


def _bearings(xy, c, x0, y0):
    v = np.c_[xy[:, 0] - x0, xy[:, 1] - y0, -np.full(len(xy), float(c))]
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def p3p(xy, XYZ, c, x0=0.0, y0=0.0):
    """All P3P solutions for three points.

    Grunert's equations ``s_i^2 + s_j^2 - 2 s_i s_j cos(g_ij) = d_ij^2`` (``s`` distances from
    the projection centre, ``g`` angles between the bearing vectors, ``d`` object distances)
    are reduced to one unknown ``s_1`` on the four sign branches of ``s_2(s_1), s_3(s_1)``; the
    roots of the third equation are bracketed on a fine grid and refined by Brent's method.

    Parameters
    ----------
    xy : array_like, shape (3, 2)
        Photo coordinates, mm.
    XYZ : array_like, shape (3, 3)
        Object coordinates.
    c, x0, y0 : float
        Principal distance and principal point, mm.

    Returns
    -------
    list of (M (3, 3), X0 (3,))
        Every pose that places the three points in front of the camera.
    """
    xy = np.asarray(xy, dtype=float)
    P = np.asarray(XYZ, dtype=float)
    j = _bearings(xy, c, x0, y0)
    d12 = np.linalg.norm(P[0] - P[1])
    d13 = np.linalg.norm(P[0] - P[2])
    d23 = np.linalg.norm(P[1] - P[2])
    c12, c13, c23 = j[0] @ j[1], j[0] @ j[2], j[1] @ j[2]
    if min(d12, d13, d23) <= 0:
        return []
    smax = min(d12 / np.sqrt(max(1 - c12**2, 1e-300)), d13 / np.sqrt(max(1 - c13**2, 1e-300)))

    def branch(s1, e2, e3):
        r2 = d12**2 - s1**2 * (1 - c12**2)
        r3 = d13**2 - s1**2 * (1 - c13**2)
        s2 = s1 * c12 + e2 * np.sqrt(np.clip(r2, 0, None))
        s3 = s1 * c13 + e3 * np.sqrt(np.clip(r3, 0, None))
        return s2, s3, s2**2 + s3**2 - 2 * s2 * s3 * c23 - d23**2

    # fine grid, denser towards smax where the branches meet
    g = smax * (1 - (1 - np.linspace(0, 1, 4001)) ** 2)
    g[0] = 1e-12 * smax
    sols = []
    for e2 in (1.0, -1.0):
        for e3 in (1.0, -1.0):
            _, _, h = branch(g, e2, e3)
            sgn = np.sign(h)
            idx = np.nonzero(sgn[:-1] * sgn[1:] < 0)[0]
            for i in idx:
                s1 = scipy.optimize.brentq(
                    lambda s, a=e2, b=e3: branch(s, a, b)[2], g[i], g[i + 1], xtol=1e-15 * smax
                )
                s2, s3, _ = branch(s1, e2, e3)
                if s1 > 0 and s2 > 0 and s3 > 0:
                    sols.append((s1, s2, s3))
    out = []
    for s in sols:
        Q = j * np.asarray(s)[:, None]  # photo-axis frame points
        _, M, t = kabsch(P, Q)
        X0 = -M.T @ t
        if any(np.allclose(X0, o[1], atol=1e-9 * (1 + np.abs(X0).max())) for o in out):
            continue
        out.append((M, X0))
    return out


def _reproj_rms(xy, XYZ, M, X0, c, x0, y0):
    u = camera_coordinates(XYZ, X0, M)
    if np.any(u[:, 2] >= 0):
        return np.inf
    return float(np.sqrt(np.mean((project(XYZ, X0, M, c, x0, y0) - xy) ** 2)))


def _spread_triple(XYZ):
    i0 = int(np.argmax(np.linalg.norm(XYZ - XYZ.mean(0), axis=1)))
    i1 = int(np.argmax(np.linalg.norm(XYZ - XYZ[i0], axis=1)))
    area = np.linalg.norm(np.cross(XYZ[i1] - XYZ[i0], XYZ - XYZ[i0]), axis=1)
    return [i0, i1, int(np.argmax(area))]


def pnp_start(xy, XYZ, c, x0=0.0, y0=0.0):
    """Candidate starts ``[(M, X0, rms)]`` sorted by reprojection rms (photo mm).

    Parameters
    ----------
    xy : ndarray, shape (N, 2)
        Photo coordinates, mm.
    XYZ : ndarray, shape (N, 3)
        Object coordinates (best reduced to their centroid).
    c, x0, y0 : float
        Interior orientation, mm.
    """
    cands = []
    n = len(xy)
    if n >= 4:
        K = np.array([[c, 0, 0], [0, c, 0], [0, 0, 1.0]])
        ip = np.c_[xy[:, 0] - x0, -(xy[:, 1] - y0)]
        try:
            _, rvecs, tvecs, _ = cv2.solvePnPGeneric(
                XYZ.astype(np.float64), ip.astype(np.float64), K, None, flags=cv2.SOLVEPNP_SQPNP
            )
            for rv, tv in zip(rvecs, tvecs, strict=True):
                M, X0 = opencv_to_photogrammetric(cv2.Rodrigues(rv)[0], tv)
                cands.append((M, X0))
        except cv2.error:
            pass
    tri = list(range(3)) if n == 3 else _spread_triple(XYZ)
    if len(set(tri)) == 3:
        cands += p3p(xy[tri], XYZ[tri], c, x0, y0)
    out = [(M, X0, _reproj_rms(xy, XYZ, M, X0, c, x0, y0)) for M, X0 in cands]
    out = [o for o in out if np.isfinite(o[2])]
    out.sort(key=lambda o: o[2])
    return out


@dataclass
class Resection(AdjustedResult):
    """Result of :func:`resect`.

    Attributes
    ----------
    X0 : ndarray, shape (3,)
        Projection centre, object frame.
    angles : ndarray, shape (3,)
        ``omega, phi, kappa`` in radians.
    c, x0, y0 : float
        Interior orientation used, mm.
    adjustment : Adjustment
        The Gauss-Markov adjustment; its first six unknowns are :data:`EO_NAMES` (then
        ``X_<name>, Y_<name>, Z_<name>`` of weighted control points).
    residuals : ndarray, shape (N, 2)
        Photo residuals ``vx, vy`` (mm; adjusted minus observed).
    standardized : ndarray, shape (N, 2)
        Baarda's w of the photo coordinates.
    flagged : ndarray of bool, shape (N,)
        Points with a coordinate (photo or control) beyond the critical value.
    control : ndarray, shape (N, 3)
        Adjusted control coordinates (equal to the given ones when fixed).
    names : tuple of str
    ambiguous : bool
        More than one start fitted the points exactly (three points: P3P ambiguity).
    alternatives : list of (X0, angles)
        The other exact starts when ambiguous.
    """

    X0: np.ndarray
    angles: np.ndarray
    c: float
    x0: float
    y0: float
    adjustment: Adjustment
    residuals: np.ndarray
    standardized: np.ndarray
    flagged: np.ndarray
    control: np.ndarray
    names: tuple
    ambiguous: bool = False
    alternatives: list = field(default_factory=list)
    #: the point name of every observation of the adjustment (for ``blunders``)
    obs_labels: tuple = ()

    def snooping_json(self) -> dict:
        """``{"blunders": [point names, most likely first], "snooping_test": {...}}``."""
        return snooping_json(self.adjustment.snooping, list(self.obs_labels) or None)

    @property
    def M(self) -> np.ndarray:
        """Rotation object -> photo axes."""
        return rotation_matrix(*self.angles)

    @property
    def params(self) -> np.ndarray:
        """``X0, Y0, Z0, omega, phi, kappa``."""
        return np.r_[self.X0, self.angles]

    @property
    def covariance(self) -> np.ndarray:
        """6x6 covariance of :data:`EO_NAMES`."""
        return self.adjustment.covariance[:6, :6]

    @property
    def std(self) -> np.ndarray:
        return self.adjustment.std[:6]


def _as_xy(xy, what="photo coordinates"):
    a = np.asarray(xy, dtype=float)
    if a.ndim != 2 or a.shape[1] != 2:
        raise SoftplotError(f"{what} must be (N,2), got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise SoftplotError(f"{what} must be finite")
    return a


def resect(
    xy,
    XYZ,
    c: float,
    x0: float = 0.0,
    y0: float = 0.0,
    *,
    sigma_xy=0.005,
    sigma_XYZ=None,
    names=None,
    start=None,
    alpha0: float = 0.001,
    precision_known: bool = True,
) -> Resection:
    """Space resection of one photo (closed-form / PnP start, then least squares).

    Parameters
    ----------
    xy : array_like, shape (N, 2)
        Photo coordinates of the control points, mm (reduced to the principal point when
        ``x0 = y0 = 0``), N >= 3.
    XYZ : array_like, shape (N, 3)
        Object coordinates of the control points.
    c, x0, y0 : float
        Principal distance and principal point, mm.
    sigma_xy : float or array_like (N,) or (N, 2)
        Standard error of the photo coordinates, mm; it is also the a priori standard error of
        unit weight, so ``sigma0`` comes out in photo mm.
    sigma_XYZ : array_like (N, 3), optional
        Standard errors of the control coordinates (object units). A point with any finite
        positive entry becomes weighted control; other entries (nan, inf, <= 0) are fixed.
    names : sequence of str, optional
        Point names.
    start : (X0 (3,), angles (3,)), optional
        Initial exterior orientation (skips the closed-form start).
    alpha0 : float
        Significance level of data snooping.
    precision_known : bool
        Whether ``sigma_xy`` states the photo coordinates' precision (Baarda's w-test) or only
        weights them (Pope's tau test against the a posteriori sigma0).

    Returns
    -------
    Resection

    Raises
    ------
    UndeterminedError
        Degenerate control (e.g. collinear points): the message names the unknowns.
    """
    xy = _as_xy(xy)
    XYZ = np.asarray(XYZ, dtype=float)
    n = len(xy)
    if XYZ.shape != (n, 3):
        raise SoftplotError(f"resection: control must be (N,3) for N={n} photo points")
    if not np.all(np.isfinite(XYZ)):
        raise SoftplotError("resection: control coordinates must be finite")
    if n < 3:
        raise SoftplotError(f"resection needs >= 3 control points, got {n}")
    if not c > 0:
        raise SoftplotError(f"resection: principal distance must be > 0, got {c}")
    names = tuple(names) if names is not None else tuple(str(i) for i in range(n))
    origin = XYZ.mean(axis=0)
    Xr = XYZ - origin
    ambiguous, alternatives = False, []
    if start is not None:
        X0s = np.asarray(start[0], dtype=float) - origin
        ang = np.asarray(start[1], dtype=float)
    else:
        cands = pnp_start(xy, Xr, c, x0, y0)
        scale = np.sqrt(np.mean(np.sum((xy - xy.mean(0)) ** 2, axis=1))) + 1e-3
        exact = []
        for o in cands:
            tol = 1e-6 * (1 + np.abs(o[1]).max())
            if o[2] <= 1e-6 * scale + 1e-9 and not any(
                np.allclose(o[1], e[1], atol=tol) for e in exact
            ):
                exact.append(o)
        if len(exact) > 1:
            # several exact fits (3 points): prefer the camera nearest to a vertical photo
            # looking down (smallest tilt arccos(m33)); pass `start` to choose otherwise
            exact.sort(key=lambda o: np.arccos(np.clip(o[0][2, 2], -1, 1)))
            ambiguous = True
            alternatives = [(o[1] + origin, np.array(angles_from_matrix(o[0]))) for o in exact[1:]]
            cands = exact
        if cands:
            M0, X0s, _ = cands[0]
            ang = np.array(angles_from_matrix(M0))
        else:
            # no start (degenerate control): a vertical photo above the points; the adjustment
            # then names what is not determined
            ext = np.sqrt(np.mean(np.sum(Xr**2, axis=1))) + 1.0
            img = np.sqrt(np.mean(np.sum((xy - [x0, y0]) ** 2, axis=1))) + 1e-6
            X0s = np.array([0.0, 0.0, ext * c / img])
            ang = np.zeros(3)
    sx = np.asarray(sigma_xy, dtype=float)
    if sx.ndim == 0:
        sx = np.full((n, 2), float(sx))
    elif sx.ndim == 1 and sx.size == n:
        sx = np.repeat(sx[:, None], 2, axis=1)
    if sx.shape != (n, 2) or not np.all(np.isfinite(sx) & (sx > 0)):
        raise SoftplotError(
            f"resection: sigma_xy must be positive: a number, (N,) or (N,2), got shape {sx.shape}"
        )
    s_prior = float(np.median(sx))
    if sigma_XYZ is None:
        sX = np.full((n, 3), np.nan)
    else:
        sX = np.broadcast_to(np.asarray(sigma_XYZ, dtype=float), (n, 3)).copy()
    okX = np.isfinite(sX) & (sX > 0)
    wpts = np.nonzero(okX.any(axis=1))[0]
    m = len(wpts)
    u = 6 + 3 * m
    unames = list(EO_NAMES)
    for i in wpts:
        unames += [f"X_{names[i]}", f"Y_{names[i]}", f"Z_{names[i]}"]
    fixed = np.zeros(u, dtype=bool)
    fixed[6:] = ~okX[wpts].ravel()
    obs_ctrl = Xr[wpts].ravel()
    ctrl_idx = np.nonzero(~fixed[6:])[0]
    l = np.r_[xy.ravel(), obs_ctrl[ctrl_idx]]
    sig = np.r_[sx.ravel(), sX[wpts].ravel()[ctrl_idx]]
    x_start = np.r_[X0s, ang, obs_ctrl]

    def fun(x):
        pts = Xr.copy()
        if m:
            pts[wpts] = x[6:].reshape(m, 3)
        f, Jp = project_jacobian(pts, x[:3], x[3:6], c, x0, y0)
        J = np.zeros((2 * n + len(ctrl_idx), u))
        J[: 2 * n, :6] = Jp[:, :, :6].reshape(2 * n, 6)
        for k, i in enumerate(wpts):
            J[2 * i : 2 * i + 2, 6 + 3 * k : 9 + 3 * k] = Jp[i, :, 6:9]
        J[2 * n + np.arange(len(ctrl_idx)), 6 + ctrl_idx] = 1.0
        return np.r_[f.ravel(), x[6:][ctrl_idx]], J

    adj = least_squares(
        fun,
        x_start,
        l,
        sig,
        names=unames,
        sigma0_prior=s_prior,
        fixed=fixed,
        alpha0=alpha0,
        what="resection",
        precision_known=precision_known,
    )
    xs = adj.x.copy()
    xs[:3] += origin
    if m:
        xs[6:] += np.tile(origin, m)
    adj.x = xs
    ctrl = XYZ.copy()
    if m:
        ctrl[wpts] = xs[6:].reshape(m, 3)
    ang = xs[3:6]
    if np.any(camera_coordinates(ctrl, xs[:3], rotation_matrix(*ang))[:, 2] >= 0):
        raise SoftplotError("resection: the solution puts control points behind the camera")
    w = adj.standardized
    flagged = adj.flagged[: 2 * n].reshape(n, 2).any(axis=1)
    if m:
        fl_c = np.zeros((m, 3), dtype=bool)
        fl_c.ravel()[ctrl_idx] = adj.flagged[2 * n :]
        flagged[wpts] |= fl_c.any(axis=1)
    return Resection(
        X0=xs[:3].copy(),
        angles=np.array(ang),
        c=float(c),
        x0=float(x0),
        y0=float(y0),
        adjustment=adj,
        residuals=adj.residuals[: 2 * n].reshape(n, 2),
        standardized=w[: 2 * n].reshape(n, 2),
        flagged=flagged,
        control=ctrl,
        names=names,
        ambiguous=ambiguous,
        alternatives=alternatives,
        obs_labels=tuple(np.repeat(np.asarray(names, dtype=object), 2))
        + tuple(np.repeat(np.asarray(names, dtype=object)[wpts], 3)[ctrl_idx] if m else ()),
    )
