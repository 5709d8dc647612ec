"""A position prior from the neighbours, for crosses whose own fit is flat along a direction.

A cross fitted over a busy scene, with a road along an arm or a thin, blurred arm in a JPEG
web copy, can leave its fit's objective nearly flat along one direction: its reported
covariance says so (the scan's normalised errors there are near 1), yet the fit sits 1-2 px
off its truth along it. Its neighbours know its position: a smooth film deformation moves
neighbouring crosses alike, and the leave-one-out prediction from them (the outlier test's,
the quadratic :func:`~softplot.marks.neighbours.local_fit` of the crosses' residuals from
the global model) has a covariance that :func:`~softplot.marks.validation.prediction_cov`
propagates exactly from their covariances, plus what the prediction misses of the film's
deformation.

A cross's fit is flat along a direction where its covariance ``C`` is long there: its largest
variance at least :data:`PRIOR_FLAT` times the median of the scan's crosses'. There, where the
prediction's covariance ``P`` is the smaller along some direction (the largest eigenvalue of
``P^-1 C`` above :data:`PRIOR_MIN_RATIO`), the two are combined as a Bayesian update:
``W = (C^-1 + P^-1)^-1`` and ``x = W (C^-1 x_fit + P^-1 x_pred)``, with ``W`` reported. On a scan
whose scene disturbs the fits (a busy scene, measured with the joint scene of
:mod:`softplot.marks.scene_tv`) every cross may be imprecise, so that none is flat beside its
peers, while a road or a field edge along an arm leaves some 1-4 px off with a sigma that says
so: there a cross is updated too where its fit's variance along some direction exceeds the
prediction's :data:`PRIOR_ANY_RATIO` times (flat or not). Every prediction is made from the
crosses' own fits (none from an updated position), after the scan's variance factor is taken
from their departures: the prior enters neither the factor nor another cross's prior. The other
crosses keep their own fits (on a clean grid the prediction is 2-4 times as precise as a
typical cross, yet the reported crosses stay independent measurements where their fits hold).
"""

from __future__ import annotations

import numpy as np

from softplot.marks import grid
from softplot.marks.common import inverse_2x2
from softplot.marks.neighbours import local_fit

__all__ = ["neighbour_update", "neighbour_posterior", "prediction_miss", "deformation_miss",
           "PRIOR_FLAT", "PRIOR_MIN_RATIO", "PRIOR_ANY_RATIO", "PRIOR_MIN_MARKS"]

#: a cross's fit is flat where its largest variance is at least this many times the median
#: of the scan's measured two-armed crosses' largest variances (the robustness sweep: at 2
#: gross fits 57 -> 38, RMS/CRB 1.62 -> 1.49, one-armed across 2.26 -> 1.89, normalised
#: errors 1.02, 0.94-1.11 per condition; at 3 or 4 1.54-1.56; at 0, every cross whose
#: neighbours predict it better than its fit along some direction, 23 gross and 1.03, with
#: normalised errors 0.99, but most crosses of a clean large grid updated)
PRIOR_FLAT = 2.0
#: ... and the prior is applied there where the fit's variance along some direction exceeds
#: the neighbours' prediction's this many times
PRIOR_MIN_RATIO = 1.0
#: on a scan whose scene disturbs the fits (``disturbed`` of :func:`neighbour_update`), any
#: cross, flat or not, whose fit's variance along some direction exceeds the neighbours'
#: prediction's this many times takes the update too: for crosses of equal precision the
#: prediction's variance is a quarter to a third of a cross's (16 neighbours, a local
#: quadratic), so this picks the crosses that their scene leaves less precise than their
#: neighbours (the robustness sweep, 137 disturbed renders: at 4 gross fits 37 -> 29, RMS/CRB
#: 1.486 -> 1.426, 21 % of their crosses updated; at 3 28 and 1.381, 33 %; at 2 27 and
#: 1.328, 50 %; normalised errors 1.02 and no render worse at each)
PRIOR_ANY_RATIO = 3.0
#: ... on grids of at least this many measured two-armed crosses: on a small grid the
#: prediction leans on the global model, which the cross itself helps to fit (its error and
#: its prediction's are not independent)
PRIOR_MIN_MARKS = 25


def deformation_miss(loo, cov, predict, ppm, floor_um) -> tuple[float, float]:
    """What a neighbours' prediction misses of the film's deformation (px^2 per axis): the
    mean square per axis of the crosses' departures ``loo`` (M, 2) px from their
    leave-one-out predictions, less what their own errors explain (their mean variance from
    ``cov`` (M, 2, 2) px^2, pixel system, and its share the prediction carries, for unit
    noise: ``predict`` maps values (K, M, 2) at the crosses to their leave-one-out
    predictions), plus the deformation floor ``floor_um`` (film micrometres, at ``ppm`` px
    per mm). Shared by this prior and the lone bars' variance along the bar
    (:func:`~softplot.marks.validation.lone_bar_prediction_cov`), each with its predictor.
    Returns the miss and that share (the median cross's)."""
    own = float(np.mean(0.5 * (cov[:, 0, 0] + cov[:, 1, 1])))
    z = np.random.default_rng(0).standard_normal((16, len(loo), 2))
    share = float(np.median(np.mean(predict(z)**2, axis=(0, 2))))
    miss = max(float(np.mean(np.square(loo))) - own * (1.0 + share), 0.0)
    return miss + (floor_um * 1e-3 * ppm) ** 2, share


def prediction_miss(film, r, cov, sigma, ppm, floor_um) -> tuple[float, float]:
    """:func:`deformation_miss` of this prior's prediction, the local quadratic of the
    residuals ``r`` (M, 2) px from the global model at ``film`` (M, 2) mm, weighted by the
    crosses' precisions ``sigma`` (M,) px."""
    def predict(v):
        return local_fit(film, film, v, 16, 2, n_sigma=sigma)

    return deformation_miss(r - predict(r), cov, predict, ppm, floor_um)


def neighbour_update(film, xy, cov, sigma, H, ppm, floor_um, prediction_cov, disturbed=False):
    """The Bayesian update of the crosses at ``film`` (M, 2) mm, measured at ``xy`` (M, 2)
    pixel system with the reported covariances ``cov`` (M, 2, 2) px^2 (pixel system, the
    scan's variance factor applied), by their neighbours' leave-one-out prediction where
    their fit is flat along a direction (:data:`PRIOR_FLAT`) and the prediction is the more
    precise there (:data:`PRIOR_MIN_RATIO`; module docstring). ``sigma`` (M,) px the
    crosses' precisions, ``H`` (3, 3) the global model film mm -> pixel system, ``ppm`` px
    per film mm, ``floor_um`` the deformation floor (film um), ``prediction_cov`` the exact
    propagation (:func:`softplot.marks.validation.prediction_cov`), computed for the flat
    fits alone. ``disturbed``: the scan's scene disturbs the fits (a busy scene, measured
    with the joint scene): a cross whose fit is far less precise than its prediction
    (:data:`PRIOR_ANY_RATIO`) is updated too, flat or not.

    Returns ``(xy, cov, sel)``: the updated positions (M, 2) and covariances (M, 2, 2)
    (pixel system; the fit's own where not updated) and which crosses were (M,) bool. With
    fewer than :data:`PRIOR_MIN_MARKS` crosses none is."""
    film = np.asarray(film, float).reshape(-1, 2)
    xy = np.array(xy, float).reshape(-1, 2)
    cov = np.array(cov, float).reshape(-1, 2, 2)
    sigma = np.asarray(sigma, float).reshape(-1)
    sel = np.zeros(len(xy), bool)
    if len(xy) < PRIOR_MIN_MARKS:
        return xy, cov, sel
    lam = np.linalg.eigvalsh(cov)[:, 1]  # the largest variance (px^2)
    flat = lam > PRIOR_FLAT * np.median(lam)
    if not (flat.any() or disturbed):
        return xy, cov, sel
    r = xy - grid.apply_h(H, film)
    miss, share = prediction_miss(film, r, cov, sigma, ppm, floor_um)
    any_ratio = PRIOR_ANY_RATIO if disturbed else np.inf
    cand = np.where(flat | _far_worse(lam, cov, share, miss, any_ratio))[0]
    if cand.size == 0:
        return xy, cov, sel
    post, W, ratio = neighbour_posterior(film, xy, cov, sigma, H, miss, prediction_cov, cand)
    ratio = np.nan_to_num(ratio, nan=-np.inf)
    ok = np.where(flat[cand], ratio > PRIOR_MIN_RATIO, ratio > any_ratio)
    sel[cand[ok]] = True
    xy[cand[ok]], cov[cand[ok]] = post[ok], W[ok]
    return xy, cov, sel


def _far_worse(lam, cov, share, miss, ratio) -> np.ndarray:
    """The crosses (M,) bool whose largest variance ``lam`` (M,) px^2 may exceed their
    neighbours' prediction's ``ratio`` times: more than half that many times
    the typical prediction's variance, ``share`` (the prediction's share of unit noise,
    :func:`deformation_miss`) times the median cross's mean variance (``cov`` (M, 2, 2)
    px^2, pixel system) plus ``miss`` (px^2). Only these get the exact propagation (its
    cost grows with the square of the crosses)."""
    typical = share * float(np.median(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]))) + miss
    return lam > 0.5 * ratio * typical


def neighbour_posterior(film, xy, cov, sigma, H, miss, prediction_cov, q):
    """The crosses ``q`` (Q,) of those at ``film`` (M, 2) mm, measured at ``xy`` (M, 2)
    pixel system with the reported covariances ``cov`` (M, 2, 2) px^2 (pixel system), each
    combined with its neighbours' leave-one-out prediction. ``sigma`` (M,) px the crosses'
    precisions (the prediction's weights), ``H`` (3, 3) the global model film mm -> pixel
    system, ``miss`` (px^2 per axis) what the prediction misses of the film's deformation
    (:func:`prediction_miss`), ``prediction_cov`` the exact propagation
    (:func:`softplot.marks.validation.prediction_cov`).

    Returns the posterior positions (Q, 2) and covariances (Q, 2, 2) (pixel system) and the
    largest eigenvalue of ``P^-1 C`` (Q,): how many times the fit's variance exceeds the
    prediction's along its flattest direction (NaN where either is singular)."""
    r = xy - grid.apply_h(H, film)
    fq = film[q]
    pred = grid.apply_h(H, fq) + local_fit(fq, film, r, 16, 2, n_sigma=sigma)
    P = prediction_cov(fq, film, H, sigma, cov) + miss * np.eye(2)
    C = cov[q]
    Pi = inverse_2x2(P, 1e-30)
    Ci = inverse_2x2(C, 1e-30)
    W = inverse_2x2(Ci + Pi, 1e-30)
    W = 0.5 * (W + W.transpose(0, 2, 1))
    post = np.einsum("nij,nj->ni", W, np.einsum("nij,nj->ni", Ci, xy[q])
                     + np.einsum("nij,nj->ni", Pi, pred))
    K = Pi @ C  # its eigenvalues are real and positive (P, C symmetric positive)
    tr, det = K[:, 0, 0] + K[:, 1, 1], K[:, 0, 0] * K[:, 1, 1] - K[:, 0, 1] * K[:, 1, 0]
    with np.errstate(invalid="ignore"):
        ratio = 0.5 * tr + np.sqrt(np.maximum(0.25 * tr * tr - det, 0.0))
    bad = ~(np.isfinite(post).all(1) & np.isfinite(W).all((1, 2)))
    ratio[bad] = np.nan
    return post, W, ratio
