"""The scan's variance factor: how far the crosses' reported covariances understate their
real errors, from the redundancy of the grid.

Each cross's covariance from least-squares matching sees only what its residuals show. Some
errors leave no trace there: the part of a structured disturbance that looks like a shift of
the mark is absorbed by the fitted shift (JPEG's quantisation of the mark's own edges, a
scene edge along an arm), and the residuals are orthogonal to it. On such scans the reported
covariances are too small (normalised errors of 1.5-2.5 on web-size JPEG copies). JPEG's
share is estimated for each cross from the scan's quantisation (:mod:`softplot.marks.jpegq`)
and added to its covariance before the factor is taken (the factor then sees what remains).

The grid sees them. A smooth film deformation moves neighbouring crosses alike, so each
cross's departure ``d_i`` from the leave-one-out local fit through its neighbours' positions
(the outlier test's prediction) has, if the covariances ``C_j`` are right, the expected
square ``E_i = E|e_i - pred_i(e)|^2`` of independent errors ``e_j ~ N(0, C_j)`` sent through
the same fit (simulated: the fit is linear in its data). With Gaussian errors
``|d_i|^2 / E_i`` is exponential with mean 1, so the mean of ``|d_i|^2 / (E_i + b)`` without
its largest :data:`TRIM` share, over that share's expected value for an exponential, is
``k^2``, the factor by which the covariances understate the errors (``b``: the square of
what the local fit may miss of a real deformation, a floor in film micrometres: at high
resolution it, not the measurement, dominates the departures). :func:`variance_factor`
returns ``k^2``, at least 1: the covariances are only ever enlarged (a scan whose
departures are smaller than its covariances predict keeps them).

A small grid (fewer than :data:`MIN_MARKS` crosses: a Pentax 645's 3 x 3, a part of a 5 x 5)
has too few neighbours for a local fit. There the crosses' departures are taken from the
scan's global projective model instead (:func:`projective_prediction`: the residuals'
weighted projection on the model's eight parameters, whose redundancy 2M - 8 the simulated
``E_i`` carry); from :data:`MIN_GLOBAL_MARKS` crosses on.
"""

from __future__ import annotations

import numpy as np

__all__ = ["variance_factor", "projective_prediction", "DEFORMATION_FLOOR_UM", "MIN_MARKS",
           "MIN_GLOBAL_MARKS"]

#: what a local polynomial through the neighbours may miss of a real film deformation (um on
#: the film; at 2400 dpi 0.2 um is 0.02 px, about the local cubic's departure on a 100 um
#: deformation)
DEFORMATION_FLOOR_UM = 0.3
#: the factor needs at least this many two-armed measured crosses (else 1)
MIN_MARKS = 12
#: below :data:`MIN_MARKS`, the factor from the global projective model needs this many
#: (redundancy 2M - 8 >= 4)
MIN_GLOBAL_MARKS = 6
#: the deformation floor (um on the film) of the factor from the global projective model: what
#: a projective transform through a small grid leaves of a smooth film deformation (2-3 um
#: over a 6 x 4.5 film's 3 x 3 crosses), which the crosses' departures carry besides their
#: own errors
GLOBAL_DEFORMATION_FLOOR_UM = 2.5
#: simulated error draws for the expected departures
DRAWS = 24
#: the largest share of the departure ratios left out (crosses the outlier test kept but
#: which are off for another reason than their precision)
TRIM = 0.05
#: the mean of an exponential variable of mean 1 below its (1 - TRIM) quantile
_TRIMMED_MEAN = (1.0 - TRIM * (1.0 - np.log(TRIM))) / (1.0 - TRIM)
#: the factor is at most this (a scan whose departures are larger still has outliers or a
#: deformation the local fit does not follow, not imprecise crosses)
MAX_FACTOR = 16.0


def projective_prediction(H: np.ndarray):
    """A ``predict`` for :func:`variance_factor` on a small grid: the residuals' weighted
    least-squares projection on the eight parameters of the projective transform ``H``
    (3 x 3, film mm -> pixel) at the crosses, i.e. the part of the residuals a refit of the
    global model would take up. ``predict(film, r, sigma=None)``: ``film`` (M, 2) mm, ``r``
    (M, 2) or (B, M, 2) px residuals, ``sigma`` (M,) px; returns the same shape as ``r``."""
    H = np.asarray(H, float)

    def predict(film, r, sigma=None):
        film = np.asarray(film, float).reshape(-1, 2)
        X, Y = film[:, 0], film[:, 1]
        w = H[2, 0] * X + H[2, 1] * Y + H[2, 2]
        u = (H[0, 0] * X + H[0, 1] * Y + H[0, 2]) / w
        v = (H[1, 0] * X + H[1, 1] * Y + H[1, 2]) / w
        one, zero = np.ones_like(X), np.zeros_like(X)
        # d(u, v) / d(h00 h01 h02 h10 h11 h12 h20 h21): rows u_1..u_M, v_1..v_M
        Ju = np.column_stack([X, Y, one, zero, zero, zero, -u * X, -u * Y]) / w[:, None]
        Jv = np.column_stack([zero, zero, zero, X, Y, one, -v * X, -v * Y]) / w[:, None]
        A = np.vstack([Ju, Jv])
        s = np.ones(len(film)) if sigma is None else np.asarray(sigma, float)
        wt = np.concatenate([1.0 / s, 1.0 / s])
        Aw = A * wt[:, None]
        c = np.linalg.norm(Aw, axis=0)  # columns of very different scales (mm, px, px mm)
        A, Aw = A / c, Aw / c
        P = A @ np.linalg.pinv(Aw) * wt[None, :]  # (2M, 2M): fitted values from the data
        rr = np.asarray(r, float)
        flat = np.concatenate([rr[..., 0], rr[..., 1]], -1)  # (..., 2M)
        fit = flat @ P.T
        m = len(film)
        return np.stack([fit[..., :m], fit[..., m:]], -1)

    return predict


def variance_factor(film: np.ndarray, r: np.ndarray, cov: np.ndarray, predict,
                    px_per_mm: float, seed: int = 0, H: np.ndarray | None = None) -> float:
    """The variance factor ``k^2 >= 1`` of a scan's measured crosses (module docstring).

    Parameters
    ----------
    film : (M, 2)
        Film positions (mm) of the measured two-armed crosses.
    r : (M, 2)
        Their residuals (px) against the global film -> pixel model.
    cov : (M, 2, 2)
        Their reported covariances (px^2, pixel system).
    predict : callable
        ``predict(film, r, sigma=...) -> (M, 2)``: the leave-one-out prediction of each residual
        from its neighbours' (the outlier test's), ``sigma`` (M,) px their precision; it is
        given the simulated draws as one batch ``r`` (B, M, 2) and returns (B, M, 2).
    px_per_mm : float
        Scan resolution (the deformation floor's unit).
    seed : int
        Of the simulated errors (the result is deterministic).
    H : (3, 3), optional
        The global film mm -> pixel model the residuals are taken against: with fewer than
        :data:`MIN_MARKS` crosses the departures are taken from it
        (:func:`projective_prediction`) instead of ``predict``; without it such a scan gets 1.
    """
    film = np.asarray(film, float).reshape(-1, 2)
    r = np.asarray(r, float).reshape(-1, 2)
    C = np.asarray(cov, float).reshape(-1, 2, 2)
    ok = np.isfinite(r).all(1) & np.isfinite(C.reshape(-1, 4)).all(1)
    film, r, C = film[ok], r[ok], C[ok]
    floor_um = DEFORMATION_FLOOR_UM
    if len(film) < MIN_MARKS:
        if H is None or len(film) < MIN_GLOBAL_MARKS:
            return 1.0
        predict = projective_prediction(H)
        floor_um = GLOBAL_DEFORMATION_FLOOR_UM
    try:
        L = np.linalg.cholesky(C)
    except np.linalg.LinAlgError:
        return 1.0
    sig = np.sqrt(0.5 * (C[:, 0, 0] + C[:, 1, 1]))
    d2 = np.sum((r - predict(film, r, sigma=sig)) ** 2, 1)
    # the draws in one batch (``predict`` takes (B, M, 2) as B calls would)
    z = np.random.default_rng(seed).standard_normal((DRAWS, len(film), 2))
    e = np.einsum("nij,bnj->bni", L, z)
    E = np.sum(np.sum((e - predict(film, e, sigma=sig)) ** 2, 2), 0) / DRAWS
    b = 2.0 * (floor_um * 1e-3 * px_per_mm) ** 2  # two axes
    q = np.sort(d2 / (E + b))
    keep = q[: max(int(np.floor((1.0 - TRIM) * len(q))), 1)]
    k2 = float(np.mean(keep) / _TRIMMED_MEAN)
    if not np.isfinite(k2):
        return 1.0
    return float(np.clip(k2, 1.0, MAX_FACTOR))
