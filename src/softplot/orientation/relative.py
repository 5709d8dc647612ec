"""Relative orientation of a stereo pair: dependent and independent, coplanarity condition.

Model frame (``docs/orientation.md``): right-handed, the base ``b = (bx, by, bz)``; the left
projection centre at the origin.

* dependent pairs (``mode="dependent"``): left photo unrotated (model frame = left photo
  frame), unknowns ``by, bz, omega2, phi2, kappa2`` with ``bx`` fixed;
* independent pairs (``mode="independent"``): base along the model x axis ``b = (bx, 0, 0)``,
  ``omega1 = 0``, unknowns ``phi1, kappa1, omega2, phi2, kappa2``.

Coplanarity condition of every point, with ``r_k = M_k' (x_k - x0, y_k - y0, -c)``::

    F = b . (r1 x r2) = 0

adjusted in the Gauss-Helmert model (:func:`softplot.adjust.gauss_helmert`): the photo
coordinates of both photos are the observations, so the converged solution minimises the
weighted sum of squared photo residuals subject to exact ray intersection (the maximum
likelihood estimate), redundancy ``n - 5``, sigma0 in photo mm.

Start: the essential matrix (OpenCV ``findEssentialMat`` on normalised coordinates, LMedS,
then ``recoverPose`` for the cheirality), converted from OpenCV axes (x right, y down, z
forward) with ``C = diag(1, -1, -1)``: ``M2 = C R C``, ``b = -C R' t`` scaled to ``bx``.

y-parallax: both rays are turned into the *base frame* (x along ``b``, y perpendicular to ``b``
in the plane of ``b`` and the model y axis) and projected with ``c``: the difference
``py = y'_left - y'_right`` (photo mm) is zero exactly when the rays intersect. Model points
come from the least-squares intersection of the observed rays
(:func:`softplot.orientation.intersection.intersect_pair`).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.sparse

from softplot.adjust import Adjustment, UndeterminedError, gauss_helmert, snooping_json
from softplot.errors import SoftplotError
from softplot.geometry.rotation import angles_from_matrix, rotation_derivatives, rotation_matrix
from softplot.orientation._adjusted import AdjustedResult
from softplot.orientation.intersection import Intersection, intersect_pair

__all__ = ["RelativeOrientation", "relative_orientation", "essential_start", "y_parallax"]

PARAMS = ("bx", "by", "bz", "omega1", "phi1", "kappa1", "omega2", "phi2", "kappa2")
FREE = {
    "dependent": ("by", "bz", "omega2", "phi2", "kappa2"),
    "independent": ("phi1", "kappa1", "omega2", "phi2", "kappa2"),
}
_C = np.diag([1.0, -1.0, -1.0])


def _cross(a, b):
    """Row-wise cross product of (n, 3) arrays (faster than np.cross for small n)."""
    return np.c_[
        a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1],
        a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2],
        a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0],
    ]


def _photo_vectors(xy, c, x0, y0):
    return np.c_[xy[:, 0] - x0, xy[:, 1] - y0, np.full(len(xy), -float(c))]


def _eight_point(p1, p2):
    """Linear 8-point essential matrix of normalised OpenCV coordinates (n >= 8)."""
    h1 = np.c_[p1, np.ones(len(p1))]
    h2 = np.c_[p2, np.ones(len(p2))]
    A = np.einsum("ni,nj->nij", h2, h1).reshape(len(p1), 9)
    E = np.linalg.svd(A)[2][-1].reshape(3, 3)
    U, d, Vt = np.linalg.svd(E)
    m = 0.5 * (d[0] + d[1])
    return U @ np.diag([m, m, 0.0]) @ Vt


def _sampson_each(E, p1, p2):
    h1 = np.c_[p1, np.ones(len(p1))]
    h2 = np.c_[p2, np.ones(len(p2))]
    Ex1 = h1 @ E.T
    Etx2 = h2 @ E
    num = np.einsum("ni,ni->n", h2, Ex1) ** 2
    den = Ex1[:, 0] ** 2 + Ex1[:, 1] ** 2 + Etx2[:, 0] ** 2 + Etx2[:, 1] ** 2
    return num / np.maximum(den, 1e-300)


def essential_candidates(xy1, xy2, c, x0=0.0, y0=0.0, bx: float = 1.0, max_candidates: int = 4):
    """Dependent relative orientations from the essential matrix, best first.

    Candidates: every solution of OpenCV's ``findEssentialMat`` (five-point, LMedS) and, with
    8 or more points, the linear eight-point solution of all points; each is turned into a
    pose by ``recoverPose`` (cheirality) and ranked by the number of points in front, then by
    the Sampson error over all points.

    Parameters
    ----------
    xy1, xy2 : ndarray, shape (n, 2)
        Photo coordinates in the left and right photo, mm (n >= 5).
    c, x0, y0 : float
        Interior orientation, mm (both photos).
    bx : float
        Base component to scale to.
    max_candidates : int

    Returns
    -------
    list of (b (3,), angles2 (3,))
        Base in the left photo frame with ``b[0] = bx`` and ``omega2, phi2, kappa2`` (radians)
        of the right photo relative to the left one.
    """
    p1 = np.c_[(xy1[:, 0] - x0) / c, -(xy1[:, 1] - y0) / c].astype(np.float64)
    p2 = np.c_[(xy2[:, 0] - x0) / c, -(xy2[:, 1] - y0) / c].astype(np.float64)
    K = np.eye(3)
    n = len(p1)
    Es = []
    if n >= 8:
        Es.append(_eight_point(p1, p2))
    # every root of the five-point problem (Nister, OpenCV) on 5-point subsets: a spread
    # deterministic first subset, then random ones
    rng = np.random.default_rng(0)
    subsets = [np.arange(5)] if n == 5 else [rng.choice(n, 5, replace=False) for _ in range(24)]
    for idx in subsets:
        try:
            E, _ = cv2.findEssentialMat(
                p1[idx], p2[idx], K, method=cv2.RANSAC, threshold=1.0, maxIters=1
            )
        except cv2.error:
            continue
        if E is not None:
            Es += [E[3 * i : 3 * i + 3] for i in range(E.shape[0] // 3)]
    # rank by the Sampson error over all points (its median when there are enough points,
    # robust to blunders); the pose (cheirality) only for the best ones
    robust = n >= 12

    def score(e):
        d = _sampson_each(e, p1, p2)
        return float(np.median(d)) if robust else float(np.sum(d))

    Es.sort(key=score)
    Es = Es[: 4 * max_candidates]
    scored = []
    for Ei in Es:
        try:
            ngood, R, t, _ = cv2.recoverPose(Ei, p1, p2, K)
        except cv2.error:
            continue
        tx = np.array([[0, -t[2, 0], t[1, 0]], [t[2, 0], 0, -t[0, 0]], [-t[1, 0], t[0, 0], 0]])
        M2 = _C @ R @ _C
        b = -_C @ R.T @ t.ravel()
        if abs(b[0]) < 1e-6 * np.linalg.norm(b):
            continue
        b = b * (bx / b[0])
        ang = np.array(angles_from_matrix(M2))
        if any(
            np.allclose(b, o[2], atol=1e-6 * abs(bx)) and np.allclose(ang, o[3], atol=1e-6)
            for o in scored
        ):
            continue
        scored.append((-int(ngood), score(tx @ R), b, ang))
    if not scored:
        raise SoftplotError(
            "relative orientation: no essential matrix (degenerate points, or the base has no "
            "x component)"
        )
    scored.sort(key=lambda o: (o[0], o[1]))
    return [(o[2], o[3]) for o in scored[:max_candidates]]


def essential_start(xy1, xy2, c, x0=0.0, y0=0.0, bx: float = 1.0):
    """The best candidate of :func:`essential_candidates`: ``(b (3,), angles2 (3,))``."""
    return essential_candidates(xy1, xy2, c, x0, y0, bx)[0]


def y_parallax(xy1, xy2, b, angles1, angles2, c, x0=0.0, y0=0.0):
    """y-parallax of every point in the base-normalised images, photo mm.

    Parameters
    ----------
    xy1, xy2 : ndarray, shape (n, 2)
        Photo coordinates, mm.
    b : array_like, shape (3,)
        Base, model frame.
    angles1, angles2 : array_like, shape (3,)
        Rotations of the photos, radians.
    c, x0, y0 : float

    Returns
    -------
    ndarray, shape (n,)
        ``py = y'_left - y'_right``.
    """
    b = np.asarray(b, dtype=float)
    e1 = b / np.linalg.norm(b)
    Y = np.array([0.0, 1.0, 0.0])
    e2 = Y - (Y @ e1) * e1
    e2 /= np.linalg.norm(e2)
    Rb = np.vstack([e1, e2, np.cross(e1, e2)])
    q1 = _photo_vectors(xy1, c, x0, y0) @ rotation_matrix(*angles1) @ Rb.T
    q2 = _photo_vectors(xy2, c, x0, y0) @ rotation_matrix(*angles2) @ Rb.T
    return -c * q1[:, 1] / q1[:, 2] + c * q2[:, 1] / q2[:, 2]


@dataclass
class RelativeOrientation(AdjustedResult):
    """Result of :func:`relative_orientation`.

    Attributes
    ----------
    mode : str
        "dependent" or "independent".
    params : ndarray, shape (9,)
        :data:`PARAMS`: ``bx, by, bz`` (model units) and the rotations of both photos
        (radians).
    adjustment : Adjustment
        Gauss-Helmert adjustment over :data:`PARAMS` (the four fixed ones have zero
        covariance); residuals are the photo corrections ``[x1, y1, x2, y2]`` per point.
    points : Intersection
        Model points by intersection.
    py : ndarray, shape (n,)
        y-parallax of every point, photo mm.
    flagged : ndarray of bool, shape (n,)
        Points whose condition fails Baarda's test.
    names : tuple of str
    c, x0, y0 : float
    """

    mode: str
    params: np.ndarray
    adjustment: Adjustment
    points: Intersection
    py: np.ndarray
    flagged: np.ndarray
    names: tuple
    c: float
    x0: float
    y0: float

    def snooping_json(self) -> dict:
        """``{"blunders": [point names, most likely first], "snooping_test": {...}}``."""
        labels = np.repeat(np.asarray(self.names, dtype=object), 4)
        return snooping_json(self.adjustment.snooping, list(labels))

    def value(self, name: str) -> float:
        return float(self.params[PARAMS.index(name)])

    @property
    def base(self) -> np.ndarray:
        return self.params[0:3].copy()

    @property
    def angles1(self) -> np.ndarray:
        return self.params[3:6].copy()

    @property
    def angles2(self) -> np.ndarray:
        return self.params[6:9].copy()

    @property
    def free(self) -> tuple:
        """Names of the five unknowns."""
        return FREE[self.mode]

    @property
    def covariance(self) -> np.ndarray:
        """5x5 covariance of :attr:`free`."""
        return self.adjustment.sub_covariance(self.free)

    @property
    def std(self) -> dict:
        """Standard deviation of every one of the nine parameters (0 for fixed ones)."""
        return dict(zip(PARAMS, self.adjustment.std, strict=True))

    @property
    def residuals(self) -> np.ndarray:
        """Photo corrections ``vx1, vy1, vx2, vy2`` per point, shape (n, 4), mm."""
        return self.adjustment.residuals.reshape(-1, 4)


def _dependent_to_independent(b, angles2):
    """Dependent (left frame) -> independent parameters (phi1, kappa1, omega2, phi2, kappa2)."""
    nb = np.linalg.norm(b)
    kappa1 = np.arctan2(-b[1], b[0])
    phi1 = np.arcsin(np.clip(b[2] / nb, -1, 1))
    M1 = rotation_matrix(0.0, phi1, kappa1)
    M2 = rotation_matrix(*angles2) @ M1
    return np.array([phi1, kappa1]), np.array(angles_from_matrix(M2))


def relative_orientation(
    xy1,
    xy2,
    c: float,
    x0: float = 0.0,
    y0: float = 0.0,
    *,
    bx: float = 1.0,
    mode: str = "dependent",
    sigma=0.005,
    names=None,
    start=None,
    alpha0: float = 0.001,
    precision_known: bool = True,
) -> RelativeOrientation:
    """Relative orientation of two photos by the coplanarity condition (Gauss-Helmert).

    Parameters
    ----------
    xy1, xy2 : array_like, shape (n, 2)
        Photo coordinates of homologous points in the left and right photo, mm, n >= 5
        (reduced to the principal point when x0 = y0 = 0).
    c, x0, y0 : float
        Interior orientation (both photos), mm.
    bx : float
        Fixed base component (the model scale), model units; its sign says on which side
        the right photo is.
    mode : {"dependent", "independent"}
    sigma : float or array_like (n, 4)
        Standard error of the photo coordinates, mm (the median is the a priori sigma0).
    names : sequence of str, optional
    start : array_like (9,), optional
        Initial :data:`PARAMS` (skips the essential-matrix start).
    alpha0 : float
        Significance level of data snooping.
    precision_known : bool
        Whether ``sigma`` states the photo coordinates' precision (Baarda's w-test) or only
        weights them (Pope's tau test against the a posteriori sigma0).

    Returns
    -------
    RelativeOrientation

    Raises
    ------
    UndeterminedError
        Fewer than 5 points or a degenerate configuration; the message names the unknowns.
    """
    xy1 = np.asarray(xy1, dtype=float)
    xy2 = np.asarray(xy2, dtype=float)
    if xy1.ndim != 2 or xy1.shape[1] != 2 or xy2.shape != xy1.shape:
        raise SoftplotError(
            f"relative orientation: left and right points must both be (n,2), got "
            f"{xy1.shape} and {xy2.shape}"
        )
    if not (np.all(np.isfinite(xy1)) and np.all(np.isfinite(xy2))):
        raise SoftplotError("relative orientation: photo coordinates must be finite")
    if mode not in FREE:
        raise SoftplotError(f"relative orientation: unknown mode {mode!r} (dependent|independent)")
    if not c > 0:
        raise SoftplotError(f"relative orientation: principal distance must be > 0, got {c}")
    if bx == 0 or not np.isfinite(bx):
        raise SoftplotError("relative orientation: bx must be finite and non-zero")
    n = len(xy1)
    free = FREE[mode]
    if n < 5:
        raise UndeterminedError(
            f"relative orientation needs >= 5 points, got {n}: not determined: " + ", ".join(free),
            free,
        )
    names = tuple(names) if names is not None else tuple(str(i) for i in range(n))
    starts = []
    if start is None:
        for b, ang2 in essential_candidates(xy1, xy2, c, x0, y0, bx, max_candidates=3):
            x_start = np.zeros(9)
            if mode == "dependent":
                x_start[0:3] = b
                x_start[6:9] = ang2
            else:
                a1, a2 = _dependent_to_independent(b, ang2)
                x_start[0] = bx
                x_start[4:6] = a1
                x_start[6:9] = a2
            starts.append(x_start)
    else:
        x_start = np.asarray(start, dtype=float).ravel().copy()
        if x_start.size != 9:
            raise SoftplotError("relative orientation: start must have the 9 PARAMS")
        x_start[0] = bx
        starts.append(x_start)
    fixed = np.array([p not in free for p in PARAMS])
    obs = np.c_[xy1, xy2].ravel()
    cols = np.arange(4 * n)
    indptr = np.arange(0, 4 * n + 1, 4)

    def fun(x, lh):
        L = lh.reshape(n, 4)
        p1 = _photo_vectors(L[:, :2], c, x0, y0)
        p2 = _photo_vectors(L[:, 2:], c, x0, y0)
        b = x[0:3]
        M1 = rotation_matrix(*x[3:6])
        M2 = rotation_matrix(*x[6:9])
        dM1 = rotation_derivatives(*x[3:6])
        dM2 = rotation_derivatives(*x[6:9])
        r1 = p1 @ M1
        r2 = p2 @ M2
        cr = _cross(r1, r2)
        F = cr @ b
        A = np.zeros((n, 9))
        A[:, 0:3] = cr
        for i in range(3):
            A[:, 3 + i] = _cross(p1 @ dM1[i], r2) @ b
            A[:, 6 + i] = _cross(r1, p2 @ dM2[i]) @ b
        g1 = _cross(r2, np.broadcast_to(b, r2.shape)) @ M1.T  # dF/dp1 = M1 (r2 x b)
        g2 = _cross(np.broadcast_to(b, r1.shape), r1) @ M2.T  # dF/dp2 = M2 (b x r1)
        vals = np.c_[g1[:, :2], g2[:, :2]].ravel()
        B = scipy.sparse.csr_matrix((vals, cols, indptr), shape=(n, 4 * n))
        return F, A, B

    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (n, 4)).ravel()
    s_prior = float(np.median(sig))
    best = None
    first_error = None
    for x_start in starts:
        # candidates come best first (points in front, Sampson error - the first-order
        # approximation of v'Pv); the three best are adjusted and the converged one with every
        # point in front of both photos and the smallest v'Pv is taken (the five-point
        # problem has several roots, close ones with few points)
        try:
            adj = gauss_helmert(
                fun,
                x_start,
                obs,
                sig,
                names=PARAMS,
                sigma0_prior=s_prior,
                fixed=fixed,
                alpha0=alpha0,
                what=f"relative orientation ({mode})",
                precision_known=precision_known,
            )
            x = adj.x
            pts = intersect_pair(
                xy1, xy2, np.zeros(3), x[3:6], x[0:3], x[6:9], c, sigma=s_prior, point_names=names
            )
        except SoftplotError as exc:
            first_error = first_error or exc
            continue
        if best is None or adj.vtpv < best[0].vtpv:
            best = (adj, pts)
    if best is None:
        raise first_error
    adj, pts = best
    x = adj.x
    py = y_parallax(xy1, xy2, x[0:3], x[3:6], x[6:9], c, x0, y0)
    flagged = adj.flagged.reshape(n, 4).any(axis=1)
    return RelativeOrientation(
        mode=mode,
        params=x.copy(),
        adjustment=adj,
        points=pts,
        py=py,
        flagged=flagged,
        names=names,
        c=float(c),
        x0=float(x0),
        y0=float(y0),
    )
