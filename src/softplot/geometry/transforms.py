"""Plane transforms: similarity, affine, projective, bilinear and polynomials of degree 2 and 3.

Every transform maps a *source* plane to a *destination* plane (for film correction: pixel ->
film mm, or film mm -> pixel; the arrays carry the units of their plane). A transform is fitted
by (weighted) least squares with :func:`fit_transform` from at least its minimum number of
point pairs and carries its precision: residuals, sigma0, redundancy and the covariance of its
parameters - an adjustment without its precision is not a result.

Models and parameter order (natural parameters, in the units of the caller's planes)::

    similarity  X = a x - b y + c            Y = b x + a y + d              (a, b, c, d)
    affine      X = a x + b y + c            Y = d x + e y + f              (a .. f)
    projective  X = (a x + b y + c) / w      Y = (d x + e y + f) / w,
                w = g x + h y + 1                                           (a .. h)
    bilinear    X = a0 + a1 x + a2 y + a3 xy, Y = b0 + b1 x + b2 y + b3 xy  (a0..a3, b0..b3)
    poly2       X = sum a_ij x^i y^j (i+j <= 2), monomials 1 x y x2 xy y2; then Y: 12 params
    poly3       likewise up to degree 3: 1 x y x2 xy y2 x3 x2y xy2 y3; 20 params

Conditioning. Source and destination coordinates are centred on their centroid and scaled
isotropically (mean distance sqrt(2), Hartley) before the fit; every model class above is
invariant under such a change, and the least-squares objective only changes by a constant
factor, so the conditioned solution *is* the natural least-squares solution. The natural
parameters and their covariance are obtained from the conditioned ones exactly (polynomial
expansion for the linear models, first-order propagation through the normalisation of the
homography for the projective one). Evaluation always runs in conditioned coordinates, so a
cubic polynomial over pixel coordinates of 10^4 keeps full double precision.

Residuals follow the adjustment convention ``v = fitted - observed`` (destination units);
``sigma0 = sqrt(v' P v / r)`` with ``r = 2 n - u``; ``covariance = sigma0**2 * cofactor``.
With ``r = 0`` (as many equations as parameters) ``sigma0`` and ``covariance`` are NaN while
``cofactor`` is still defined.

Inverse: closed form for similarity, affine and projective (3 x 3 inverse) and for bilinear
(the quadratic in y, solved with the numerically stable root formula, polished by one Newton
step); vectorised Newton with the analytic Jacobian for the polynomials (start: the inverse of
the affine part). Points where Newton does not converge (outside the region where the
polynomial is one-to-one) come back as NaN.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from math import comb

import numpy as np

from softplot.errors import SoftplotError

__all__ = [
    "KINDS",
    "MIN_POINTS",
    "N_PARAMS",
    "PlaneTransform",
    "fit_transform",
    "transform_points",
    "from_params",
]

KINDS = ("similarity", "affine", "projective", "bilinear", "poly2", "poly3")

#: number of parameters of each model
N_PARAMS = {
    "similarity": 4,
    "affine": 6,
    "projective": 8,
    "bilinear": 8,
    "poly2": 12,
    "poly3": 20,
}

#: minimum number of point pairs for a determined fit
MIN_POINTS = {k: (u + 1) // 2 for k, u in N_PARAMS.items()}

# monomials (i, j) = x^i y^j of the linear models, in parameter order (per coordinate)
_MONOMIALS = {
    "affine": [(1, 0), (0, 1), (0, 0)],
    "bilinear": [(0, 0), (1, 0), (0, 1), (1, 1)],
    "poly2": [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2)],
    "poly3": [(0, 0), (1, 0), (0, 1), (2, 0), (1, 1), (0, 2), (3, 0), (2, 1), (1, 2), (0, 3)],
}

_NEWTON_TOL = 1e-12  # conditioned units
_NEWTON_MAXIT = 40


# ---------------------------------------------------------------------------------------------
# helpers


def _as_points(xy, what: str = "points") -> np.ndarray:
    a = np.asarray(xy, dtype=float)
    if a.ndim == 1 and a.shape[0] == 2:
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 2:
        raise SoftplotError(f"{what}: expected an (N, 2) array of x, y, got shape {a.shape}")
    return a


@dataclass(frozen=True)
class Conditioning:
    """Isotropic conditioning ``xc = (x - centre) / scale`` of one plane (its units)."""

    centre: tuple[float, float] = (0.0, 0.0)
    scale: float = 1.0

    @classmethod
    def of(cls, xy: np.ndarray) -> "Conditioning":
        """Centroid and scale giving a mean distance of sqrt(2) from the centroid."""
        c = xy.mean(axis=0)
        d = np.sqrt(((xy - c) ** 2).sum(axis=1)).mean()
        s = d / np.sqrt(2.0) if d > 0 else 1.0
        return cls((float(c[0]), float(c[1])), float(s))

    def apply(self, xy: np.ndarray) -> np.ndarray:
        return (xy - np.asarray(self.centre)) / self.scale

    def undo(self, xy: np.ndarray) -> np.ndarray:
        return xy * self.scale + np.asarray(self.centre)

    def matrix(self) -> np.ndarray:
        """3 x 3 homogeneous matrix of :meth:`apply`."""
        s = self.scale
        return np.array(
            [[1 / s, 0, -self.centre[0] / s], [0, 1 / s, -self.centre[1] / s], [0, 0, 1.0]]
        )


def _monomial_values(mons, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(N, m) values of the monomials x^i y^j."""
    deg = max(i + j for i, j in mons)
    xp = [np.ones_like(x)]
    yp = [np.ones_like(y)]
    for _ in range(deg):
        xp.append(xp[-1] * x)
        yp.append(yp[-1] * y)
    return np.stack([xp[i] * yp[j] for i, j in mons], axis=-1)


def _monomial_derivs(mons, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(N, m) d/dx and d/dy of the monomials."""
    deg = max(i + j for i, j in mons)
    xp = [np.ones_like(x)]
    yp = [np.ones_like(y)]
    for _ in range(deg):
        xp.append(xp[-1] * x)
        yp.append(yp[-1] * y)
    zero = np.zeros_like(x)
    dx = np.stack([i * xp[i - 1] * yp[j] if i else zero for i, j in mons], axis=-1)
    dy = np.stack([j * xp[i] * yp[j - 1] if j else zero for i, j in mons], axis=-1)
    return dx, dy


def _expansion(mons, cond: Conditioning) -> np.ndarray:
    """M with ``mono(xc) = M @ mono(x)`` for ``xc = (x - c) / s`` (exact binomial expansion)."""
    index = {m: k for k, m in enumerate(mons)}
    cx, cy = cond.centre
    s = cond.scale
    M = np.zeros((len(mons), len(mons)))
    for row, (i, j) in enumerate(mons):
        for p in range(i + 1):
            for q in range(j + 1):
                M[row, index[(p, q)]] += (
                    comb(i, p) * comb(j, q) * (-cx) ** (i - p) * (-cy) ** (j - q) / s ** (i + j)
                )
    return M


# ---------------------------------------------------------------------------------------------
# model kernels in conditioned coordinates (parameters theta in conditioned units)


def _lin_eval(kind: str, th: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    if kind == "similarity":
        a, b, c, d = th
        return np.stack([a * x - b * y + c, b * x + a * y + d], axis=-1)
    if kind == "affine":
        a, b, c, d, e, f = th
        return np.stack([a * x + b * y + c, d * x + e * y + f], axis=-1)
    if kind == "bilinear":
        a0, a1, a2, a3, b0, b1, b2, b3 = th
        xy = x * y
        return np.stack([a0 + a1 * x + a2 * y + a3 * xy, b0 + b1 * x + b2 * y + b3 * xy], axis=-1)
    mons = _MONOMIALS[kind]
    V = _monomial_values(mons, x, y)
    m = len(mons)
    return np.stack([V @ th[:m], V @ th[m:]], axis=-1)


def _proj_eval(th: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    a, b, c, d, e, f, g, h = th
    w = g * x + h * y + 1.0
    return np.stack([(a * x + b * y + c) / w, (d * x + e * y + f) / w], axis=-1)


def _eval(kind: str, th: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    if kind == "projective":
        return _proj_eval(th, x, y)
    return _lin_eval(kind, th, x, y)


def _design(kind: str, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(2N, u) design matrix of a linear model: rows X0, Y0, X1, Y1, ..."""
    n = x.shape[0]
    u = N_PARAMS[kind]
    A = np.zeros((n, 2, u))
    one = np.ones_like(x)
    if kind == "similarity":
        A[:, 0] = np.stack([x, -y, one, 0 * x], axis=-1)
        A[:, 1] = np.stack([y, x, 0 * x, one], axis=-1)
    else:
        mons = _MONOMIALS[kind]
        V = _monomial_values(mons, x, y)
        m = len(mons)
        A[:, 0, :m] = V
        A[:, 1, m:] = V
    return A.reshape(2 * n, u)


def _proj_jac_params(th: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(2N, 8) derivatives of the projective model w.r.t. its parameters."""
    a, b, c, d, e, f, g, h = th
    w = g * x + h * y + 1.0
    X = (a * x + b * y + c) / w
    Y = (d * x + e * y + f) / w
    n = x.shape[0]
    J = np.zeros((n, 2, 8))
    z = np.zeros_like(x)
    J[:, 0] = np.stack([x / w, y / w, 1 / w, z, z, z, -X * x / w, -X * y / w], axis=-1)
    J[:, 1] = np.stack([z, z, z, x / w, y / w, 1 / w, -Y * x / w, -Y * y / w], axis=-1)
    return J.reshape(2 * n, 8)


def _point_jacobian(kind: str, th: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(N, 2, 2) d(X, Y)/d(x, y) in conditioned coordinates."""
    n = x.shape[0]
    J = np.empty((n, 2, 2))
    if kind == "similarity":
        a, b = th[0], th[1]
        J[:] = [[a, -b], [b, a]]
    elif kind == "affine":
        J[:] = [[th[0], th[1]], [th[3], th[4]]]
    elif kind == "projective":
        a, b, c, d, e, f, g, h = th
        w = g * x + h * y + 1.0
        X = (a * x + b * y + c) / w
        Y = (d * x + e * y + f) / w
        J[:, 0, 0] = (a - g * X) / w
        J[:, 0, 1] = (b - h * X) / w
        J[:, 1, 0] = (d - g * Y) / w
        J[:, 1, 1] = (e - h * Y) / w
    else:
        mons = _MONOMIALS["bilinear" if kind == "bilinear" else kind]
        m = len(mons)
        dx, dy = _monomial_derivs(mons, x, y)
        J[:, 0, 0] = dx @ th[:m]
        J[:, 0, 1] = dy @ th[:m]
        J[:, 1, 0] = dx @ th[m:]
        J[:, 1, 1] = dy @ th[m:]
    return J


def _solve2(J: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Solve the (N, 2, 2) systems J d = r in closed form (NaN where singular)."""
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        dx = (J[:, 1, 1] * r[:, 0] - J[:, 0, 1] * r[:, 1]) / det
        dy = (-J[:, 1, 0] * r[:, 0] + J[:, 0, 0] * r[:, 1]) / det
    return np.stack([dx, dy], axis=-1)


def _proj_matrix(th: np.ndarray) -> np.ndarray:
    a, b, c, d, e, f, g, h = th
    return np.array([[a, b, c], [d, e, f], [g, h, 1.0]])


def _bilinear_inverse(th: np.ndarray, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Closed-form inverse of the bilinear model (conditioned coordinates), (N, 2)."""
    a0, a1, a2, a3, b0, b1, b2, b3 = th
    Xa = X - a0
    Yb = Y - b0
    A = b3 * a2 - b2 * a3
    B = Yb * a3 - b2 * a1 + b1 * a2 - b3 * Xa
    C = Yb * a1 - b1 * Xa
    with np.errstate(invalid="ignore", divide="ignore"):
        disc = np.sqrt(np.maximum(B * B - 4 * A * C, 0.0))
        q = -0.5 * (B + np.where(B >= 0, disc, -disc))
        # root continuous with the affine solution -C/B when A -> 0
        y = np.where(q != 0, C / q, 0.0)
        d1 = a1 + a3 * y
        d2 = b1 + b3 * y
        x = np.where(np.abs(d1) >= np.abs(d2), (Xa - a2 * y) / d1, (Yb - b2 * y) / d2)
    return np.stack([x, y], axis=-1)


# ---------------------------------------------------------------------------------------------
# the transform object


@dataclass(frozen=True, eq=False)
class PlaneTransform:
    """A fitted plane transform source -> destination with its precision.

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`.
    params : ndarray (u,)
        Natural parameters in the caller's units (order in the module docstring).
    covariance : ndarray (u, u)
        ``sigma0**2 * cofactor`` of ``params`` (NaN when the redundancy is 0).
    cofactor : ndarray (u, u)
        Cofactor matrix ``(A' P A)^-1`` of ``params`` (unit weight variance 1).
    sigma0 : float
        A-posteriori standard deviation of unit weight, destination units.
    redundancy : int
        ``2 n - u``.
    residuals : ndarray (n, 2)
        ``fitted - observed`` at the fitted points, destination units.
    src, dst : ndarray (n, 2)
        The fitted points (source and destination units).
    weights : ndarray (n,) or (n, 2, 2)
        Point weights used (1 when not given), or the 2 x 2 weight matrices.
    """

    kind: str
    params: np.ndarray
    covariance: np.ndarray
    cofactor: np.ndarray
    sigma0: float
    redundancy: int
    residuals: np.ndarray
    src: np.ndarray
    dst: np.ndarray
    weights: np.ndarray
    src_cond: Conditioning = field(default_factory=Conditioning)
    dst_cond: Conditioning = field(default_factory=Conditioning)
    cparams: np.ndarray = field(default=None)  # parameters in conditioned units

    # -- evaluation ---------------------------------------------------------------------------

    def forward(self, xy) -> np.ndarray:
        """Map source points (N, 2) to the destination plane (N, 2)."""
        p = self.src_cond.apply(_as_points(xy))
        out = _eval(self.kind, self.cparams, p[:, 0], p[:, 1])
        return self.dst_cond.undo(out)

    __call__ = forward

    def inverse(self, XY) -> np.ndarray:
        """Map destination points (N, 2) back to the source plane (N, 2).

        Closed form for similarity, affine, projective and bilinear; Newton otherwise (NaN
        where it does not converge).
        """
        P = self.dst_cond.apply(_as_points(XY))
        X, Y = P[:, 0], P[:, 1]
        th = self.cparams
        if self.kind in ("similarity", "affine", "projective"):
            H = np.linalg.inv(self.matrix(conditioned=True))
            w = H[2, 0] * X + H[2, 1] * Y + H[2, 2]
            x = (H[0, 0] * X + H[0, 1] * Y + H[0, 2]) / w
            y = (H[1, 0] * X + H[1, 1] * Y + H[1, 2]) / w
            return self.src_cond.undo(np.stack([x, y], axis=-1))
        if self.kind == "bilinear":
            xy = _bilinear_inverse(th, X, Y)
            xy = self._newton(xy, P, iterations=1)
            return self.src_cond.undo(xy)
        # polynomials: start from the inverse of the affine part, then Newton
        m = len(_MONOMIALS[self.kind])
        A = np.array([[th[1], th[2]], [th[m + 1], th[m + 2]]])
        x0 = np.linalg.solve(A, (P - np.array([th[0], th[m]])).T).T
        xy = self._newton(x0, P, iterations=_NEWTON_MAXIT, tol=_NEWTON_TOL)
        return self.src_cond.undo(xy)

    def _newton(self, xy: np.ndarray, P: np.ndarray, iterations: int, tol: float = 0.0):
        xy = xy.copy()
        active = np.arange(xy.shape[0])
        for _ in range(iterations):
            if active.size == 0:
                break
            p = xy[active]
            f = _eval(self.kind, self.cparams, p[:, 0], p[:, 1]) - P[active]
            J = _point_jacobian(self.kind, self.cparams, p[:, 0], p[:, 1])
            d = _solve2(J, f)
            xy[active] = p - d
            if tol:
                step = np.abs(d).max(axis=1)
                active = active[~(step <= tol)]
        if tol and active.size:
            # not converged: check the residual; keep points that did get there
            p = xy[active]
            f = _eval(self.kind, self.cparams, p[:, 0], p[:, 1]) - P[active]
            bad = ~(np.abs(f).max(axis=1) <= 1e-9)
            xy[active[bad]] = np.nan
        return xy

    def jacobian(self, xy) -> np.ndarray:
        """(N, 2, 2) derivatives d(X, Y)/d(x, y) (destination units per source unit)."""
        p = self.src_cond.apply(_as_points(xy))
        J = _point_jacobian(self.kind, self.cparams, p[:, 0], p[:, 1])
        return J * (self.dst_cond.scale / self.src_cond.scale)

    def matrix(self, conditioned: bool = False) -> np.ndarray:
        """3 x 3 homogeneous matrix (similarity, affine, projective only)."""
        th = self.cparams if conditioned else self.params
        if self.kind == "similarity":
            a, b, c, d = th
            return np.array([[a, -b, c], [b, a, d], [0, 0, 1.0]])
        if self.kind == "affine":
            return np.vstack([np.reshape(th, (2, 3)), [0, 0, 1.0]])
        if self.kind == "projective":
            return _proj_matrix(th)
        raise SoftplotError(f"a {self.kind} transform has no 3x3 matrix")

    @property
    def n_points(self) -> int:
        return int(self.src.shape[0])

    @property
    def rms(self) -> float:
        """RMS of the residual vector lengths (destination units)."""
        if self.residuals.size == 0:
            return 0.0
        return float(np.sqrt((self.residuals**2).sum(axis=1).mean()))

    def summary(self) -> str:
        return (
            f"{self.kind}: n={self.n_points} r={self.redundancy} sigma0={self.sigma0:.4g} "
            f"rms={self.rms:.4g}"
        )


# ---------------------------------------------------------------------------------------------
# natural <-> conditioned parameters


def _natural(kind, th, sc: Conditioning, dc: Conditioning) -> tuple[np.ndarray, np.ndarray]:
    """Natural parameters and the Jacobian d(natural)/d(conditioned)."""
    sd = dc.scale
    cd = np.asarray(dc.centre)
    if kind == "projective":
        D_inv = np.linalg.inv(dc.matrix())
        S = sc.matrix()
        M = D_inv @ _proj_matrix(th) @ S
        nat = np.array([M[0, 0], M[0, 1], M[0, 2], M[1, 0], M[1, 1], M[1, 2], M[2, 0], M[2, 1]])
        m22 = M[2, 2]
        T = np.zeros((8, 8))
        idx = [(0, 0), (0, 1), (0, 2), (1, 0), (1, 1), (1, 2), (2, 0), (2, 1)]
        for k, (i, j) in enumerate(idx):
            E = np.zeros((3, 3))
            E[i, j] = 1.0
            dM = D_inv @ E @ S
            T[:, k] = [
                (dM[p, q] * m22 - M[p, q] * dM[2, 2]) / m22**2 for (p, q) in idx
            ]
        return nat / m22, T
    if kind == "similarity":
        E = np.array(
            [[1, 0, 0, 0], [0, -1, 0, 0], [0, 0, 1, 0], [0, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 1.0]]
        )
        nat_aff, T_aff = _natural("affine", E @ th, sc, dc)
        R = np.zeros((4, 6))
        R[0, 0] = R[1, 3] = R[2, 2] = R[3, 5] = 1.0
        return R @ nat_aff, R @ T_aff @ E
    mons = _MONOMIALS[kind]
    m = len(mons)
    M = _expansion(mons, sc)
    const = mons.index((0, 0))
    T = np.zeros((2 * m, 2 * m))
    T[:m, :m] = sd * M.T
    T[m:, m:] = sd * M.T
    nat = T @ th
    nat[const] += cd[0]
    nat[m + const] += cd[1]
    return nat, T


def _conditioned(kind, nat, sc: Conditioning, dc: Conditioning) -> np.ndarray:
    """Conditioned parameters from natural ones (inverse of :func:`_natural`)."""
    if kind == "projective":
        M = dc.matrix() @ _proj_matrix(nat) @ np.linalg.inv(sc.matrix())
        M = M / M[2, 2]
        return np.array([M[0, 0], M[0, 1], M[0, 2], M[1, 0], M[1, 1], M[1, 2], M[2, 0], M[2, 1]])
    # linear models: nat = T th + t0
    u = N_PARAMS[kind]
    t0, T = _natural(kind, np.zeros(u), sc, dc)
    return np.linalg.solve(T, np.asarray(nat, float) - t0)


# ---------------------------------------------------------------------------------------------
# public functions


def transform_points(kind: str, params, xy) -> np.ndarray:
    """Evaluate a model from its natural parameters at source points (N, 2) -> (N, 2)."""
    _check_kind(kind)
    p = _as_points(xy)
    th = np.asarray(params, float)
    if th.shape != (N_PARAMS[kind],):
        raise SoftplotError(f"{kind}: expected {N_PARAMS[kind]} parameters, got {th.shape}")
    return _eval(kind, th, p[:, 0], p[:, 1])


def from_params(kind: str, params, src_scale_hint=None) -> PlaneTransform:
    """A :class:`PlaneTransform` from natural parameters (no fit: no precision attached).

    ``src_scale_hint`` (an (N, 2) array of typical source points) sets the conditioning used
    for evaluation; without it the identity conditioning is used.
    """
    _check_kind(kind)
    nat = np.asarray(params, float)
    if nat.shape != (N_PARAMS[kind],):
        raise SoftplotError(f"{kind}: expected {N_PARAMS[kind]} parameters, got {nat.shape}")
    if src_scale_hint is not None:
        s = _as_points(src_scale_hint)
        sc = Conditioning.of(s)
        dc = Conditioning.of(transform_points(kind, nat, s))
    else:
        sc = dc = Conditioning()
    th = _conditioned(kind, nat, sc, dc)
    u = N_PARAMS[kind]
    nanm = np.full((u, u), np.nan)
    empty = np.zeros((0, 2))
    return PlaneTransform(
        kind, nat, nanm, nanm.copy(), float("nan"), 0, empty, empty, empty, np.zeros(0),
        sc, dc, th,
    )


def _check_kind(kind: str) -> None:
    if kind not in KINDS:
        raise SoftplotError(f"unknown transform {kind!r}: expected one of {', '.join(KINDS)}")


def fit_transform(kind: str, src, dst, weights=None) -> PlaneTransform:
    """Least-squares fit of a plane transform ``src -> dst``.

    Parameters
    ----------
    kind : str
        similarity | affine | projective | bilinear | poly2 | poly3.
    src, dst : array_like (N, 2)
        Corresponding points in the source and destination planes (their own units, e.g.
        pixel and film mm).
    weights : array_like (N,) or (N, 2, 2), optional
        Point weights (inverse variances, relative): one per point, which both coordinates
        share, or a 2 x 2 weight matrix per point (the inverse of the destination error's
        covariance, e.g. of a mark measured precisely across a line only; it may be
        singular: no weight along the line).

    Returns
    -------
    PlaneTransform
        With natural parameters, covariance, sigma0, residuals.

    Raises
    ------
    SoftplotError
        Unknown kind; fewer points than the minimum (the message names the method and the
        counts); non-finite input; a degenerate configuration (collinear or repeated points).
    """
    _check_kind(kind)
    src = _as_points(src, f"{kind} fit: source points")
    dst = _as_points(dst, f"{kind} fit: destination points")
    n = src.shape[0]
    if dst.shape[0] != n:
        raise SoftplotError(
            f"{kind} fit: {n} source points but {dst.shape[0]} destination points"
        )
    need = MIN_POINTS[kind]
    if n < need:
        raise SoftplotError(f"{kind} transform needs at least {need} points, got {n}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise SoftplotError(f"{kind} fit: points must be finite numbers")
    Wm = None
    if weights is not None and np.ndim(weights) == 3:
        Wm = np.asarray(weights, float)
        if (Wm.shape != (n, 2, 2) or not np.all(np.isfinite(Wm))
                or not np.allclose(Wm, Wm.transpose(0, 2, 1), rtol=1e-9, atol=0.0)):
            raise SoftplotError(f"{kind} fit: weights must be {n} symmetric 2 x 2 matrices")
        lam, V = np.linalg.eigh(Wm)
        if np.any(lam < -1e-9 * np.maximum(lam.max(1, keepdims=True), 1e-300)):
            raise SoftplotError(f"{kind} fit: weight matrices must be positive semi-definite")
        # the whitening W^(1/2) of each point's two rows; the scalar weight of a point (its
        # mean eigenvalue) only starts the projective fit and counts the points with weight
        Wh = np.einsum("nij,nj,nkj->nik", V, np.sqrt(np.maximum(lam, 0.0)), V)
        weights = np.maximum(lam, 0.0).mean(1)
    if weights is None:
        w = np.ones(n)
    else:
        w = np.asarray(weights, float).reshape(-1)
        if w.shape != (n,) or not np.all(np.isfinite(w)) or np.any(w < 0):
            raise SoftplotError(f"{kind} fit: weights must be {n} non-negative finite numbers")
        if np.count_nonzero(w) < need:
            raise SoftplotError(
                f"{kind} transform needs at least {need} points with non-zero weight, "
                f"got {np.count_nonzero(w)}"
            )
    u = N_PARAMS[kind]
    sc = Conditioning.of(src)
    dc = Conditioning.of(dst)
    s = sc.apply(src)
    d = dc.apply(dst)
    x, y = s[:, 0], s[:, 1]
    l = d.reshape(-1)
    sw = np.repeat(np.sqrt(w), 2)

    def whiten(M):
        """Rows (2N, ...) of the x, y equations of each point, weighted."""
        if Wm is None:
            return M * (sw if M.ndim == 1 else sw[:, None])
        B = M.reshape(n, 2, -1)
        return np.einsum("nij,njk->nik", Wh, B).reshape(M.shape)

    if kind == "projective":
        th = _dlt(s, d, w)
        for _ in range(30):
            f = _proj_eval(th, x, y).reshape(-1)
            A = _proj_jac_params(th, x, y)
            step, *_ = np.linalg.lstsq(whiten(A), whiten(l - f), rcond=None)
            th = th + step
            if np.abs(step).max() < 1e-14:
                break
        A = _proj_jac_params(th, x, y)
    else:
        A = _design(kind, x, y)
        th, *_ = np.linalg.lstsq(whiten(A), whiten(l), rcond=None)
    Aw = whiten(A)
    sv = np.linalg.svd(Aw, compute_uv=False)
    if sv[-1] <= 1e-10 * sv[0]:
        raise SoftplotError(
            f"{kind} fit: degenerate point configuration ({n} points; collinear or repeated?)"
        )
    N = Aw.T @ Aw
    Qc = np.linalg.inv(N)
    fitted = _eval(kind, th, x, y)
    v_c = fitted - d  # conditioned destination units
    r = 2 * n - u
    if Wm is None:
        vpv = float((w[:, None] * v_c**2).sum()) * dc.scale**2
    else:
        vpv = float(np.einsum("ni,nij,nj->", v_c, Wm, v_c)) * dc.scale**2
    sigma0 = float(np.sqrt(vpv / r)) if r > 0 else float("nan")
    nat, T = _natural(kind, th, sc, dc)
    # Cov(th) = (sigma0 / scale_dst)^2 Qc: conditioned destination units are natural / scale
    Q = T @ Qc @ T.T / dc.scale**2
    cov = Q * sigma0**2 if r > 0 else np.full_like(Q, np.nan)
    return PlaneTransform(
        kind=kind,
        params=nat,
        covariance=cov,
        cofactor=Q,
        sigma0=sigma0,
        redundancy=r,
        residuals=v_c * dc.scale,
        src=src.copy(),
        dst=dst.copy(),
        weights=w if Wm is None else Wm,
        src_cond=sc,
        dst_cond=dc,
        cparams=th,
    )


def _dlt(s: np.ndarray, d: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Linear (DLT) homography estimate in conditioned coordinates, 8 parameters."""
    n = s.shape[0]
    x, y = s[:, 0], s[:, 1]
    X, Y = d[:, 0], d[:, 1]
    z = np.zeros(n)
    o = np.ones(n)
    r1 = np.stack([x, y, o, z, z, z, -X * x, -X * y, -X], axis=-1)
    r2 = np.stack([z, z, z, x, y, o, -Y * x, -Y * y, -Y], axis=-1)
    A = np.concatenate([r1, r2]) * np.sqrt(np.concatenate([w, w]))[:, None]
    _, sv, Vt = np.linalg.svd(A, full_matrices=A.shape[0] < 9)
    h = Vt[-1]
    if abs(h[8]) < 1e-12 * np.abs(h).max():
        raise SoftplotError(
            f"projective fit: degenerate point configuration ({n} points; collinear?)"
        )
    return h[:8] / h[8]
