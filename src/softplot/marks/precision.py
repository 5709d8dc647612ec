"""The scan's variance factor: how far the crosses' reported covariances understate their
real errors, from the redundancy of the grid.

Each cross's covariance from least-squares matching sees only what its residuals show. Some
errors leave no trace there: the part of a structured disturbance that looks like a shift of
the mark is absorbed by the fitted shift (JPEG's quantisation of the mark's own edges, a
scene edge along an arm), and the residuals are orthogonal to it. On such scans the reported
covariances are too small (normalised errors of 1.5-2.5 on web-size JPEG copies).

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
"""

from __future__ import annotations

import numpy as np

__all__ = ["variance_factor", "DEFORMATION_FLOOR_UM", "MIN_MARKS"]

#: what a local polynomial through the neighbours may miss of a real film deformation (um on
#: the film; at 2400 dpi 0.2 um is 0.02 px, about the local cubic's departure on a 100 um
#: deformation)
DEFORMATION_FLOOR_UM = 0.3
#: the factor needs at least this many two-armed measured crosses (else 1)
MIN_MARKS = 12
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


def variance_factor(film: np.ndarray, r: np.ndarray, cov: np.ndarray, predict,
                    px_per_mm: float, seed: int = 0) -> float:
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
    """
    film = np.asarray(film, float).reshape(-1, 2)
    r = np.asarray(r, float).reshape(-1, 2)
    C = np.asarray(cov, float).reshape(-1, 2, 2)
    ok = np.isfinite(r).all(1) & np.isfinite(C.reshape(-1, 4)).all(1)
    film, r, C = film[ok], r[ok], C[ok]
    if len(film) < MIN_MARKS:
        return 1.0
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
    b = 2.0 * (DEFORMATION_FLOOR_UM * 1e-3 * px_per_mm) ** 2  # two axes
    q = np.sort(d2 / (E + b))
    keep = q[: max(int(np.floor((1.0 - TRIM) * len(q))), 1)]
    k2 = float(np.mean(keep) / _TRIMMED_MEAN)
    if not np.isfinite(k2):
        return 1.0
    return float(np.clip(k2, 1.0, MAX_FACTOR))
