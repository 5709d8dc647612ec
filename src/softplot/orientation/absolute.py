"""Absolute orientation: 7-parameter 3-D similarity model -> object, weighted by control.

Model (``docs/orientation.md``)::

    object = scale * M(omega, phi, kappa)^T @ model + T

with ``M = Mk Mp Mo`` of :mod:`softplot.geometry.rotation` (so ``M`` rotates object axes into
model axes, as for a photo). The model coordinates are treated as error-free; the control
object coordinates are the observations, weighted by their standard errors ``sX, sY, sZ``
(a coordinate with no standard error is observed with unit weight, a full point may be left
out). Start: the closed-form similarity of Umeyama (1991) / Horn (1987); then Gauss-Newton
(:func:`softplot.adjust.least_squares`), with residuals per control point, sigma0, redundancy
``3n - 7`` and Baarda's data snooping.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softplot.adjust import Adjustment, least_squares, snooping_json
from softplot.errors import SoftplotError
from softplot.geometry.rotation import angles_from_matrix, rotation_derivatives, rotation_matrix
from softplot.orientation._adjusted import AdjustedResult

__all__ = ["AbsoluteOrientation", "absolute_orientation", "similarity_start", "kabsch"]

PARAMS = ("scale", "omega", "phi", "kappa", "TX", "TY", "TZ")


def kabsch(P, Q, weights=None, with_scale: bool = False):
    """Closed-form ``Q ~ s R P + t`` (Umeyama 1991; Kabsch without scale).

    Parameters
    ----------
    P, Q : array_like, shape (N, 3)
        Corresponding points, source and target frames.
    weights : array_like (N,), optional
        Point weights.
    with_scale : bool
        Estimate the scale ``s`` (else ``s = 1``).

    Returns
    -------
    s : float
    R : ndarray, shape (3, 3)
        Proper rotation (det = +1) taking source axes to target axes.
    t : ndarray, shape (3,)
    """
    P = np.asarray(P, dtype=float)
    Q = np.asarray(Q, dtype=float)
    w = np.ones(len(P)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    mp = w @ P
    mq = w @ Q
    Pc = P - mp
    Qc = Q - mq
    S = (Qc * w[:, None]).T @ Pc
    U, d, Vt = np.linalg.svd(S)
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U) * np.linalg.det(Vt)) or 1.0
    R = U @ D @ Vt
    s = float(np.sum(d * np.diag(D)) / np.sum(w * np.sum(Pc**2, axis=1))) if with_scale else 1.0
    t = mq - s * R @ mp
    return s, R, t


def similarity_start(model, obj, weights=None):
    """Closed-form start ``(scale, omega, phi, kappa, TX, TY, TZ)`` of the similarity.

    Parameters
    ----------
    model : array_like, shape (N, 3)
        Model coordinates.
    obj : array_like, shape (N, 3)
        Object coordinates.
    weights : array_like (N,), optional
        Point weights.
    """
    s, R, t = kabsch(model, obj, weights, with_scale=True)
    o, p, k = angles_from_matrix(R.T)
    return np.array([s, float(o), float(p), float(k), *t])


def transform(params, model) -> np.ndarray:
    """Apply ``object = scale * M^T @ model + T`` to model points (N, 3) -> object (N, 3)."""
    p = np.asarray(params, dtype=float)
    M = rotation_matrix(*p[1:4])
    return p[0] * np.asarray(model, dtype=float) @ M + p[4:7]


@dataclass
class AbsoluteOrientation(AdjustedResult):
    """Result of :func:`absolute_orientation`.

    Attributes
    ----------
    params : ndarray, shape (7,)
        ``scale, omega, phi, kappa`` (radians), ``TX, TY, TZ`` (object units).
    adjustment : Adjustment
        Unknowns named as :data:`PARAMS`.
    residuals : ndarray, shape (N, 3)
        Object-frame residuals (transformed minus given control), nan for unobserved.
    standardized : ndarray, shape (N, 3)
        Baarda's w per coordinate (nan where unobserved or uncontrolled).
    flagged : ndarray of bool, shape (N,)
        Control points with a coordinate beyond the critical value.
    names : tuple of str
        Control point names.
    """

    params: np.ndarray
    adjustment: Adjustment
    residuals: np.ndarray
    standardized: np.ndarray
    flagged: np.ndarray
    names: tuple
    #: the control point name of every observation of the adjustment (for ``blunders``)
    obs_labels: tuple = ()

    def snooping_json(self) -> dict:
        """``{"blunders": [point names, most likely first], "snooping_test": {...}}``."""
        return snooping_json(self.adjustment.snooping, list(self.obs_labels) or None)

    @property
    def scale(self) -> float:
        return float(self.params[0])

    @property
    def angles(self) -> np.ndarray:
        """``(omega, phi, kappa)`` in radians."""
        return self.params[1:4].copy()

    @property
    def M(self) -> np.ndarray:
        """Rotation object -> model axes."""
        return rotation_matrix(*self.params[1:4])

    @property
    def T(self) -> np.ndarray:
        return self.params[4:7].copy()

    @property
    def covariance(self) -> np.ndarray:
        """7x7 covariance in :data:`PARAMS` order."""
        return self.adjustment.covariance

    @property
    def std(self) -> np.ndarray:
        return self.adjustment.std

    def apply(self, model) -> np.ndarray:
        """Model points (N, 3) -> object (N, 3)."""
        return transform(self.params, model)


def absolute_orientation(
    model,
    obj,
    sigma=None,
    *,
    names=None,
    alpha0: float = 0.001,
    sigma0_prior: float = 1.0,
) -> AbsoluteOrientation:
    """7-parameter similarity from control points (closed-form start, then weighted LS).

    Parameters
    ----------
    model : array_like, shape (N, 3)
        Model coordinates of the control points (error-free).
    obj : array_like, shape (N, 3)
        Object coordinates of the control points; ``nan`` marks an unobserved coordinate
        (e.g. a height-only or plan-only control point).
    sigma : float or array_like (N, 3), optional
        Standard errors of the object coordinates, object units (unit weights if None; a
        ``nan`` or non-positive entry is replaced by 1).
    names : sequence of str, optional
        Control point names.
    alpha0 : float
        Significance level of data snooping.
    sigma0_prior : float
        A priori standard error of unit weight (1: sigma0 is then the ratio a posteriori / a
        priori when ``sigma`` is given).

    Returns
    -------
    AbsoluteOrientation

    Raises
    ------
    UndeterminedError
        Degenerate control (fewer than 7 observed coordinates, or collinear points - the
        rotation about their line is not determined).
    """
    model = np.asarray(model, dtype=float)
    obj = np.asarray(obj, dtype=float)
    if model.ndim != 2 or model.shape[1] != 3 or obj.shape != model.shape:
        raise SoftplotError(
            f"absolute orientation: model and control must both be (N,3), got "
            f"{model.shape} and {obj.shape}"
        )
    n = len(model)
    names = tuple(names) if names is not None else tuple(str(i) for i in range(n))
    if not np.all(np.isfinite(model)):
        raise SoftplotError("absolute orientation: model coordinates must be finite")
    obs_mask = np.isfinite(obj)
    if obs_mask.sum() < 7:
        raise SoftplotError(
            f"absolute orientation: {int(obs_mask.sum())} observed control coordinates, need >= 7"
        )
    sig = np.ones((n, 3)) if sigma is None else np.broadcast_to(np.asarray(sigma, float), (n, 3))
    sig = np.where(np.isfinite(sig) & (sig > 0), sig, 1.0)
    full = obs_mask.all(axis=1)
    if full.sum() >= 3:
        start = similarity_start(model[full], obj[full], 1.0 / np.mean(sig[full] ** 2, axis=1))
    else:
        start = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
        if full.any():
            start[4:7] = np.mean(obj[full] - model[full], axis=0)
    # reduce to centroids for conditioning
    cm = model.mean(axis=0)
    co = np.nanmean(np.where(obs_mask, obj, np.nan), axis=0)
    co = np.where(np.isfinite(co), co, 0.0)
    mr = model - cm
    # object = s R (mr + cm) + T = s R mr + (T + s R cm) -> T' = T + s R cm - co
    R0 = rotation_matrix(*start[1:4]).T
    x0 = start.copy()
    x0[4:7] = start[4:7] + start[0] * R0 @ cm - co
    idx = np.nonzero(obs_mask.ravel())[0]
    l = (obj - co).ravel()[idx]

    def fun(x):
        s = x[0]
        M = rotation_matrix(*x[1:4])
        dM = rotation_derivatives(*x[1:4])
        Rm = mr @ M  # (R m) with R = M^T  -> rows: m^T M
        f = s * Rm + x[4:7]
        J = np.zeros((n, 3, 7))
        J[:, :, 0] = Rm
        for i in range(3):
            J[:, :, 1 + i] = s * (mr @ dM[i])
        J[:, :, 4:7] = np.eye(3)
        return f.ravel()[idx], J.reshape(3 * n, 7)[idx]

    adj = least_squares(
        fun,
        x0,
        l,
        sig.ravel()[idx],
        names=PARAMS,
        sigma0_prior=sigma0_prior,
        alpha0=alpha0,
        what="absolute orientation",
        precision_known=sigma is not None,
    )
    xs = adj.x.copy()
    R = rotation_matrix(*xs[1:4]).T
    xs[4:7] = xs[4:7] + co - xs[0] * R @ cm
    # covariance of T in the original frame: T = T' + co - s R cm (propagate)
    Jt = np.eye(7)
    dM = rotation_derivatives(*xs[1:4])
    Jt[4:7, 0] = -(R @ cm)
    for i in range(3):
        Jt[4:7, 1 + i] = -xs[0] * dM[i].T @ cm
    adj.cofactor = Jt @ adj.cofactor @ Jt.T
    adj.x = xs
    res = np.full((n, 3), np.nan)
    res.ravel()[idx] = adj.residuals
    wst = np.full((n, 3), np.nan)
    wst.ravel()[idx] = adj.standardized
    fl = np.zeros((n, 3), dtype=bool)
    fl.ravel()[idx] = adj.flagged
    return AbsoluteOrientation(
        params=xs,
        adjustment=adj,
        residuals=res,
        standardized=wst,
        flagged=fl.any(axis=1),
        names=names,
        obs_labels=tuple(np.repeat(np.asarray(names, dtype=object), 3)[idx]),
    )
