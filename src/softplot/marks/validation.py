"""Stage 7 of the reseau path: validation of the measured crosses against their neighbours.

:func:`validate` refits the global projective model to the measured crosses; a cross whose
residual departs from its neighbours' (a smooth film deformation moves neighbours alike) by
more than a robust threshold, or by more than :data:`OUTLIER_K` times what its own sigma and
the prediction's error lead one to expect (:func:`departure_model`), is "rejected"
(:func:`reject_outliers`; with fewer than 8 crosses measured, too few for that test, one far
off the affine of the others: :func:`few_outliers`); rejected and refused crosses are fitted
again from the neighbours' prediction, once without each half-arm (:func:`rescue`), and,
failing that, as a lone bar
(:func:`lone_arms`); a measured cross that departs from its neighbours' prediction far more
than its peers do, but passed the test by its own imprecision, is fitted again in the same
way and the refit kept where it lies much nearer the prediction (:func:`second_look`);
crosses the scan's edge cuts by one tip are measured last from their
other three half-arms (:func:`edge_crosses`). Fiducials, too few for a neighbourhood, are
tested against the pattern's model (:func:`validate_pattern`). The hand-over is
:class:`Validation`; the orchestrator refuses a scan whose measured crosses lie farther than
:data:`MAX_GRID_RMS_MM` (rms) off any projective grid.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

from softplot.marks import grid
from softplot.marks.common import inverse_2x2
from softplot.marks.measure import (
    AcceptRules,
    bar_share,
    measure,
    measure_one_arm,
    merge_fine,
    peer_gain,
)
from softplot.marks.measurement import Measurement, held_blur
from softplot.marks.neighbour_prior import deformation_miss, neighbour_update
from softplot.marks.neighbours import (
    local_fit,
    local_prediction,
    nearest,
    outline,
    position_affine,
    remembered,
)
from softplot.marks.precision import (
    DEFORMATION_FLOOR_UM,
    GLOBAL_DEFORMATION_FLOOR_UM,
    MIN_MARKS,
    variance_factor,
)
from softplot.marks.prediction import Prediction

__all__ = ["Validation", "validate", "validate_pattern", "pattern_model", "reject_outliers",
           "few_outliers", "FEW_OUTLIER_MM", "FEW_OUTLIER_PX", "FEW_MIN_LEFT",
           "rescue", "second_look", "SECOND_LOOK_SPREAD", "lone_arms", "one_bar_crosses",
           "edge_crosses", "edge_cut_part", "extrapolation", "prediction_cov",
           "lone_bar_prediction_cov",
           "h_parameter_jacobian", "similar_four", "SIMILAR_TOL_MM", "ONE_BAR_ABSENT",
           "ONE_BAR_MIN_SCORE", "departure_model", "expected_departure", "outlier_threshold",
           "robust_spread",
           "OUTLIER_K", "OUTLIER_FLOOR_MM", "OUTLIER_FLOOR_INNER", "MAX_GRID_RMS_MM",
           "LONE_ARM_ALONG_MAX_MM", "PATTERN_OUTLIER_MM",
           "REINSTATE_DEGREES", "RESCUE_MIN_GAIN", "RESCUE_MAX_SIGMA_RATIO", "EXTRAPOLATION_MAX",
           "RESCUE_CLOSE_SIGMA_RATIO", "RESCUE_CLOSE_K",
           "EDGE_CUT_MAX", "EDGE_MAX_SIGMA_RATIO", "EDGE_WHOLE", "consistent_outline",
           "CONSISTENT_K",
           "CONSISTENT_PRED_K", "outlier_floor", "reinstate", "smooth_residuals", "global_model"]

#: departures from the smooth deformation field below this (film mm) are never outliers on
#: the grid's outline, where the local quadratic extrapolates: it does not follow a 100 um
#: deformation better than a few micrometres there
OUTLIER_FLOOR_MM = 0.0025
#: the degrees of the global polynomial that judges a rejected outline cross again
#: (:func:`reinstate`), the one its leave-one-out error prefers
REINSTATE_DEGREES = (1, 2, 3, 4)
#: inside the grid the local cubic follows a 100 um deformation to a few tenths of a
#: micrometre (no false rejection in the sweep down to 0.02 px): floor max(px, film mm)
OUTLIER_FLOOR_INNER = (0.05, 0.0005)
#: a reseau's measured crosses lie within this (film mm, rms) of a projective grid: three
#: times the largest film deformation tested (100 um); more is not a reseau
MAX_GRID_RMS_MM = 0.3
#: a departure from the neighbours' prediction beyond this many times its expected size
#: (:func:`departure_model`: from the mark's own sigma and the scan's prediction error) is
#: an outlier (for a Gaussian departure a chance of exp(-2.75^2) = 5e-4 per mark)
OUTLIER_K = 2.75
#: the outlier test's floor grows at most this many times where a mark's neighbours'
#: prediction extrapolates further than is typical (:func:`extrapolation`)
EXTRAPOLATION_MAX = 2.0
#: a measured cross departing from its neighbours' prediction by more than this many times
#: the measured crosses' robust spread (:func:`robust_spread`, 1.4826 x the median of the
#: distances: about 1.74 standard deviations of one coordinate) is fitted again without each
#: half-arm (:func:`second_look`; at 1.5 the sweep kept 2 more gross fits, at 1.0 without
#: the refit's precision test 1 fewer, but replaced clean fits by their less precise
#: three-arm refits)
SECOND_LOOK_SPREAD = 1.0
#: a cross measured again (:func:`rescue`) has at least this share of the measured crosses'
#: median contrast (crosses under a 30 % dark region keep 0.3 of it)
RESCUE_MIN_GAIN = 0.1
#: a rescued cross's precision (independent-pixel sigma) is at most this many times the
#: measured crosses' median
RESCUE_MAX_SIGMA_RATIO = 2.0
#: ... or at most this many times, where the rescued fit lies within :data:`RESCUE_CLOSE_K` of
#: its own sigma of the neighbours' prediction (:func:`_rescue_close`): the robustness sweep's
#: rejected and refused crosses whose three-half-arm refits came out 2-6 times less precise
#: than their peers and within 2.5 of their sigmas of the prediction lay 0.002-0.8 px off
#: their truth (18 crosses, none gross); the refits it refuses lay 3-50 of their sigmas from
#: the prediction and mostly 0.4-5 px off their truth
RESCUE_CLOSE_SIGMA_RATIO = 6.0
#: ... see :data:`RESCUE_CLOSE_SIGMA_RATIO`
RESCUE_CLOSE_K = 2.5
#: the largest standard deviation (film mm, reported: after the scan's variance factor) of a
#: lone bar's position along it: the largest film deformation tested; where the neighbours
#: predict a position more poorly than that, a lone bar's point is a guess along the bar
#: (the sweep's busy low-dpi renders: 0.14-0.23 mm, and 2-5 px off)
LONE_ARM_ALONG_MAX_MM = 0.1
#: lone bars are measured where at least this many crosses are: a plane through four
#: neighbours and one to spare predicts their position (a 3 x 3 grid with three
#: one-armed crosses has six)
LONE_ARM_MIN_MEASURED = 5
#: a cross whose only tip beyond the scan's edge (or within a pixel of it) leaves by at most
#: this share of its half-arm is measured from its other three half-arms (:func:`edge_crosses`;
#: at a quarter, the sweep's quarter-frame render 435 lost a visible cross its fit placed
#: 0.3 of a half-arm out)
EDGE_CUT_MAX = 0.35
#: an outline cross the outlier test rejected is measured after all where each of its four
#: three-half-arm refits, started at its fit, lies within this many of its own sigmas of it
#: (:func:`consistent_outline`): a fit pulled by scene content along one half-arm moves
#: when that half-arm is left out (the sweep's gross rejected fits: 2.3-20 sigmas)
CONSISTENT_K = 2.5
#: ... and where its departure from its neighbours' prediction is at most this many times
#: that prediction's standard deviation (:func:`lone_bar_prediction_cov`): at a corner a
#: deformation the neighbours' extrapolation misses moves the prediction 3.3-5 standard
#: deviations off the sweep's correct crosses (0.02-0.2 px off their truth, 0.26-1.1 px off
#: the prediction); the gross rejected fits with consistent refits lay 5.7-6.2 off
CONSISTENT_PRED_K = 5.0
#: a cross the scan's edge cuts, measured from its three other half-arms (:func:`edge_crosses`),
#: is at most this many times less precise (independent-pixel sigma) than the measured
#: crosses' median: its patch is cut by the scan's edge (NaN pixels, no scene figure) and
#: the scan's corner often cuts a second half-arm short; the sweep's correct edge crosses
#: (0.08-0.15 px off their truth) came out 2.3-9 times less precise than their peers and were
#: refused at :data:`RESCUE_MAX_SIGMA_RATIO`. The departure from the neighbours' prediction
#: (the outlier test's threshold) still judges them.
EDGE_MAX_SIGMA_RATIO = 10.0
#: :func:`edge_cut_part`'s value for a cross none of whose tips leaves the scan: one the first
#: prediction placed across the scan's edge and the measured crosses' prediction places whole
#: on it (the sweep's render 327: R3C4's tip 1.3 px inside, never fitted), fitted whole
EDGE_WHOLE = 4


@dataclass
class Validation:
    """The measured crosses' model and residuals (hand-over of :func:`validate`).

    Attributes
    ----------
    H : (3, 3) ndarray
        The global projective model film mm -> full-resolution pixel, fitted to the measured
        crosses.
    residual : (N, 2) ndarray
        Measured minus modelled position (px, pixel system; NaN where not measured).
    rms : float
        RMS of the residuals (px).
    arms : (N,) int or None
        Arms each cross was measured by: 2 (the cross), 1 (a lone bar), 0 (not measured);
        None for fiducials.
    bar : (N, 2) ndarray or None
        The lone bars' unit vectors along the bar (pixel system x, y; where ``arms`` is 1),
        NaN elsewhere; None for fiducials.
    departure : (2, 2) ndarray or None
        The outlier test's :func:`departure_model` (None with fewer than 8 measured).
    kind : str
        The model's kind: "projective", or for a few fiducials "affine" / "similarity".
    variance_factor : float
        The factor the crosses' covariances were scaled by (the scan's variance factor from
        the grid's redundancy, :func:`softplot.marks.precision.variance_factor`; 1 for
        fiducials).
    """

    H: np.ndarray
    residual: np.ndarray
    rms: float
    arms: np.ndarray | None
    departure: np.ndarray | None
    kind: str = "projective"
    variance_factor: float = 1.0
    bar: np.ndarray | None = None
    #: (N,) bool: crosses whose position is their fit combined with the neighbours'
    #: prediction (:func:`neighbour_prior`); None where none was
    from_neighbours: np.ndarray | None = None


def validate(scan, pr: Prediction, m: Measurement, rules: AcceptRules | None) -> Validation:
    """Outlier test, rescue of the rejected and refused crosses, lone bars, the scan's
    variance factor; updates ``m``'s per-cross arrays (positions, covariances, status,
    reason) in place and scales ``m.cov`` by the variance factor. (The neighbours'
    predictions it asks for more than once are computed once: :func:`remembered`.)"""
    with remembered():
        return _validate(scan, pr, m, rules)


def _validate(scan, pr: Prediction, m: Measurement, rules: AcceptRules | None) -> Validation:
    """:func:`validate`."""
    film, ppm, shape, fine = pr.film, pr.px_per_mm, m.shape, m.fine
    xy, cov, cov_w, status, reason = m.xy, m.cov, m.cov_white, m.status, m.reason
    N, idx = len(film), m.fitted
    sigma = m.sigma()
    floor_px = outlier_floor(film, status, ppm)
    Hm, residual, rms, dep = reject_outliers(film, xy, status, reason, pr.H, sigma,
                                             floor_px=floor_px)
    # the affine of the accepted fits; a refused fit's ran wherever it went (a scale of 1.4
    # refused every later fit of that cross as the wrong size): the model's there
    A_fit = pr.A.copy()
    A_fit[idx] = np.where(np.isfinite(fine.A) & fine.ok[:, None, None], fine.A, pr.A[idx])
    fitted = np.zeros(N, bool)
    fitted[idx] = True
    close = []
    if rescue(scan, shape, film, xy, (cov, cov_w), status, reason, Hm, sigma, floor_px, A_fit,
              pr.s0, pr.init_err, pr.sign, rules, pr.max_shift, ppm, scene_tv=m.scene_tv,
              blur=held_blur(fine), fitted=fitted, departure=dep,
              gain_ref=peer_gain(fine, least=1), close=close):
        sigma = m.sigma()
        Hm, residual, rms, _ = reject_outliers(film, xy, status, reason, Hm, sigma,
                                               floor_px=floor_px)
    if second_look(scan, shape, film, xy, (cov, cov_w), status, Hm, sigma, floor_px, A_fit,
                   pr.s0, pr.init_err, pr.sign, rules, pr.max_shift, ppm,
                   scene_tv=m.scene_tv, blur=held_blur(fine),
                   gain_ref=peer_gain(fine, least=1)).size:
        sigma = m.sigma()
        Hm, residual, rms = global_model(film, xy, status, Hm)
    if len(reinstate(film, xy, status, reason, floor_px, Hm)):
        Hm, residual, rms = global_model(film, xy, status, Hm)
    arms = np.where(np.array(status) == "measured", 2, 0)
    bar = np.full((N, 2), np.nan)
    one_bar_crosses(scan, shape, film, xy, (cov, cov_w), status, arms, Hm, sigma, A_fit,
                    pr.s0, pr.sign, rules, pr.max_shift, held_blur(fine), fine, ppm,
                    along_max=LONE_ARM_ALONG_MAX_MM * ppm, bar=bar, fit=(m.score, m.cnr),
                    skip=close)
    # the errors the crosses' own fits cannot see, from their departures from each other
    # (of the two-armed crosses only: the lone bars below do not change it)
    two = arms == 2
    vfac = variance_factor(film[two], residual[two], cov[two], local_prediction, ppm, H=Hm)
    back = consistent_outline(scan, shape, film, xy, (cov, cov_w), status, reason, arms, Hm,
                              sigma, pr.s0, pr.init_err, pr.sign, rules, pr.max_shift, ppm,
                              vfac, scene_tv=m.scene_tv, blur=held_blur(fine),
                              gain_ref=peer_gain(fine, least=1))
    residual[back] = xy[back] - grid.apply_h(Hm, film[back])
    lone_arms(scan, shape, film, xy, (cov, cov_w), status, reason, arms, Hm, sigma, A_fit,
              pr.s0, pr.sign, rules, pr.max_shift, fitted, held_blur(fine), fine, ppm,
              along_max=LONE_ARM_ALONG_MAX_MM * ppm / np.sqrt(vfac), vfac=vfac, bar=bar,
              fit=(m.score, m.cnr), redo=close)
    if (arms == 1).any():
        residual[arms == 1] = xy[arms == 1] - grid.apply_h(Hm, film[arms == 1])
    m.cov = cov * vfac
    vrep = vfac
    cj = jpeg_share(m, two)
    if cj is not None:  # the reported covariances with the JPEG quantisation's share
        cov_q = cov + cj
        vrep = variance_factor(film[two], residual[two], cov_q[two], local_prediction, ppm,
                               H=Hm)
        m.cov = np.where(two[:, None, None], cov_q * vrep, m.cov)
    # crosses the scan's edge cuts by one tip: measured last, so that they feed no model
    got = edge_crosses(scan, pr, m, arms, Hm, vfac, floor_px, dep, rules)
    residual[got] = m.xy[got] - grid.apply_h(Hm, film[got])
    # where a two-armed cross's fit is flat along a direction, its neighbours' prediction is
    # the better part of its position: after the variance factor and every other
    # measurement, from the crosses' own fits (the updated positions feed nothing)
    got = neighbour_prior(film, m, two, Hm, sigma, ppm)
    residual[got] = m.xy[got] - grid.apply_h(Hm, film[got])
    from_nb = np.zeros(len(film), bool)
    from_nb[got] = True
    return Validation(H=Hm, residual=residual, rms=rms, arms=arms, departure=dep,
                      variance_factor=vrep, bar=bar, from_neighbours=from_nb)


def neighbour_prior(film, m: Measurement, two, H, sigma, ppm) -> np.ndarray:
    """The measured two-armed crosses ``two`` (N bool) of ``m`` updated in place by their
    neighbours' prediction where their fit is flat along a direction, and on a scan whose
    scene disturbs the fits (measured with the joint scene, ``m.scene_tv``) also where their
    fit is far less precise than the prediction
    (:func:`softplot.marks.neighbour_prior.neighbour_update`; ``film`` (N, 2) mm, ``H`` the
    global model film mm -> pixel system, ``sigma`` (N,) px, ``ppm`` px per mm); returns the
    indices updated."""
    idx = np.where(two)[0]
    xy2, cov2, sel = neighbour_update(film[idx], m.xy[idx], m.cov[idx], sigma[idx], H, ppm,
                                      DEFORMATION_FLOOR_UM, prediction_cov,
                                      disturbed=bool(m.scene_tv))
    m.xy[idx], m.cov[idx] = xy2, cov2
    return idx[sel]


def outlier_floor(film, status, ppm) -> np.ndarray:
    """The outlier test's floor (px, (M,)) of marks at ``film`` (M, 2) mm: on the outline of
    the marks measured (``status``) max(0.1 px, :data:`OUTLIER_FLOOR_MM`), inside the grid
    :data:`OUTLIER_FLOOR_INNER`; ``ppm`` px per film mm."""
    return np.where(outline(film, np.array(status) == "measured"),
                    max(0.1, OUTLIER_FLOOR_MM * ppm),
                    max(OUTLIER_FLOOR_INNER[0], OUTLIER_FLOOR_INNER[1] * ppm))


def jpeg_share(m: Measurement, two: np.ndarray) -> np.ndarray | None:
    """What the scan's JPEG quantisation adds to the covariance (N, 2, 2) px^2 of each
    two-armed cross ``two`` (N bool) whose reported fit is its first measurement's
    (:attr:`softplot.marks.measure.Fine.cov_jpeg`; 0 elsewhere), or None where there is none
    (a scan that was no JPEG). Kept out of the acceptance and outlier tests, which were set
    without it."""
    fine = m.fine
    if fine is None or getattr(fine, "cov_jpeg", None) is None:
        return None
    idx = np.asarray(m.fitted)
    cj = np.zeros((len(m.xy), 2, 2))
    same = two[idx] & np.all(fine.xy == m.xy[idx], 1)  # not replaced by a later fit
    cj[idx[same]] = fine.cov_jpeg[same]
    return cj if np.any(cj != 0.0) else None


#: film mm: a fiducial farther than this from the pattern's model is an outlier
PATTERN_OUTLIER_MM = 0.3


def validate_pattern(film: np.ndarray, m: Measurement, Lm: np.ndarray, t: np.ndarray,
                     px_per_mm: float) -> Validation:
    """The model of a pattern of a few marks (fiducials, ``film`` (N, 2) mm) fitted to the
    measured ones (:func:`pattern_model`; ``Lm`` (2, 2), ``t`` (2,) the pattern match's
    similarity film mm -> pixel); a mark whose residual exceeds :data:`PATTERN_OUTLIER_MM` is
    "rejected" (``m`` updated in place) and the model refitted."""
    status, reason, xy = m.status, m.reason, m.xy
    ok = np.array([s == "measured" for s in status])
    Hm = pattern_model(film[ok], xy[ok], Lm, t)
    r = xy - grid.apply_h(Hm, film)
    bad = ok & (np.hypot(*r.T) > PATTERN_OUTLIER_MM * px_per_mm)
    for i in np.where(bad)[0]:
        status[i] = "rejected"
        reason[i] = "outlier against the fiducial pattern"
    ok &= ~bad
    if bad.any():
        Hm = pattern_model(film[ok], xy[ok], Lm, t)
        r = xy - grid.apply_h(Hm, film)
    kind = "projective" if ok.sum() >= 5 else ("affine" if ok.sum() >= 3 else "similarity")
    rms = float(np.sqrt(np.mean(np.sum(r[ok] ** 2, 1)))) if ok.any() else float("nan")
    residual = np.where(ok[:, None], r, np.nan)
    return Validation(H=Hm, residual=residual, rms=rms, arms=None, departure=None, kind=kind)


def pattern_model(src, dst, Lm, t):
    """Film mm -> pixel (3, 3) of a few marks: projective (>= 5 points), affine (3-4), or the
    similarity ``Lm``, ``t`` from the pattern match shifted to the marks' mean (1-2)."""
    if len(src) >= 5:
        return grid.projective_fit(src, dst)
    if len(src) >= 3:
        return grid.projective_fit(src, dst)  # affine for < 5 points
    H = np.eye(3)
    H[:2, :2] = Lm
    H[:2, 2] = t
    if len(src) >= 1:
        H[:2, 2] += np.mean(dst - src @ Lm.T - t, axis=0)
    return H


def outlier_threshold(spread, floor, sigma, expected=None):
    """Largest departure (px) from the neighbours' prediction that is not an outlier:
    ``max(floor, 3 s, min(4.5 s, 4 sigma))`` (``s`` the departures' robust spread, ``sigma``
    the mark's own precision); with ``expected`` (px, the departure's expected size for that
    mark, :func:`departure_model`) at most ``max(floor, OUTLIER_K x expected)``: a precise
    mark among imprecise ones is held to its own precision. The outlier test and the rescue
    share it. Arrays of one value per mark (or scalars)."""
    thr = np.maximum(np.maximum(3.0 * spread, floor), np.minimum(4.5 * spread, 4.0 * sigma))
    if expected is None:
        return thr
    return np.minimum(thr, np.maximum(floor, OUTLIER_K * expected))


def departure_model(dev, sigma, edge, iterations=6, reach=None):
    """Coefficients of the expected squared departure of a mark from its neighbours'
    prediction, ``a sigma^2 + b``: ``a`` scales the mark's own variance (``sigma`` px from LSM,
    which a busy scene makes optimistic), ``b`` (px^2) is what every mark shares (the
    prediction's error: its neighbours' noise and the deformation the local polynomial does
    not follow).

    ``dev`` (M,) px departures, ``sigma`` (M,) px, ``edge`` (M,) bool (the grid's outline,
    extrapolated: its own ``a, b`` when both it and the inside have 8 marks or more). Fitted
    by non-negative least squares on ``dev^2``, weighted by the model's inverse square (the
    variance of a squared Gaussian departure grows with its mean); departures beyond 3 times
    the model's size are left out and the fit repeated. On a clean scan ``b`` dominates and
    the test is the spread's; over a busy scene it holds a precise cross to its own sigma.
    With ``reach`` (M,), how far each mark's prediction extrapolates beyond its group's
    typical (:func:`extrapolation`, 1 for most), a third term ``c (reach^2 - 1)`` is fitted
    with them: at a corner a deformation the local polynomial does not follow moves the
    prediction further. Returns (2, 3) then (columns ``a``, ``b``, ``c``).
    Returns (2, 2): rows outline, inside; columns ``a``, ``b``
    (:func:`expected_departure` evaluates it).
    """
    d2 = np.asarray(dev, float) ** 2
    s2 = np.nan_to_num(np.asarray(sigma, float), nan=1.0) ** 2
    x2 = None if reach is None else np.asarray(reach, float) ** 2 - 1.0
    edge = np.asarray(edge, bool)
    def fit(d2, s2, x2):
        a, b, c = 1.0, float(np.median(d2)) + 1e-12, 0.0
        for _ in range(iterations):
            mod = a * s2 + b + (0.0 if x2 is None else c * x2)
            keep = d2 <= 9.0 * mod
            if keep.sum() < 2:
                break
            wt = 1.0 / np.maximum(mod[keep], 1e-24)
            cols = [s2[keep], np.ones(int(keep.sum()))] + ([] if x2 is None else [x2[keep]])
            sol, _ = nnls(np.stack(cols, 1) * wt[:, None], d2[keep] * wt)
            a, b = float(sol[0]), max(float(sol[1]), 1e-12)
            c = float(sol[2]) if x2 is not None else 0.0
        return (a, b) if x2 is None else (a, b, c)

    if min(edge.sum(), (~edge).sum()) >= 8:
        return np.array([fit(d2[g], s2[g], None if x2 is None else x2[g])
                         for g in (edge, ~edge)])
    return np.tile(fit(d2, s2, x2), (2, 1))  # too few in a group: one model for both


def expected_departure(coef, sigma, edge, reach=None):
    """Expected departure (px) of marks with precision ``sigma`` (px) on the outline
    (``edge`` True) or inside the grid, from :func:`departure_model`'s ``coef``; with
    ``reach`` (how far each mark's prediction extrapolates) its prediction error grown
    with it."""
    c = coef[np.where(np.asarray(edge, bool), 0, 1)]
    sg = np.nan_to_num(np.asarray(sigma, float), nan=1.0)
    var = c[..., 0] * sg**2 + c[..., 1]
    if reach is not None and c.shape[-1] > 2:
        var = var + c[..., 2] * (np.asarray(reach, float) ** 2 - 1.0)
    return np.sqrt(var)


def robust_spread(dev, edge):
    """Robust spread (1.4826 x median) of departures, separately for the grid's outline."""
    spread = np.full(len(dev), 1.4826 * np.median(dev))
    for grp in (edge, ~edge):
        if grp.sum() >= 8:
            spread[grp] = 1.4826 * np.median(dev[grp])
    return spread


def reject_outliers(film, xy, status, reason, H0, sigma, floor_px=0.1):
    """Refit the global model to the measured marks; flag marks that disagree with it.

    A smooth film deformation moves neighbouring crosses alike, so each residual against the
    projective model is compared with a leave-one-out local quadratic fit to its neighbours'
    residuals (a local cubic inside the grid, a quadratic on its outline); a departure beyond
    ``max(floor, 3 s, min(4.5 s, 4 sigma))`` (``s``: the robust spread of the departures,
    separately for the marks on the grid's outline, which are extrapolated, and those inside
    it (the outline of the marks measured when the test starts: the edge of a cropped or
    partial frame counts, :func:`~softplot.marks.neighbours.outline`); ``sigma``: the mark's
    own precision; ``floor`` (px, scalar or one per mark): on the outline 0.1 px or
    :data:`OUTLIER_FLOOR_MM` on the film, inside :data:`OUTLIER_FLOOR_INNER`, whichever is
    larger) is an outlier (a mark locked onto something else, or pulled by a scratch along
    an arm); and
    beyond ``OUTLIER_K`` times the departure expected from the mark's own sigma and the
    prediction's error (:func:`departure_model`, fitted to the departures before any
    rejection), whichever is smaller, but never below the floor. The worst one is rejected
    and the test repeated. Modifies ``status`` and ``reason`` in place. Returns the global
    model (3, 3), the residuals (M, 2) px (NaN where not measured), their rms (px) and the
    departure model (None with fewer than 8 measured marks).
    """
    Hm = H0
    n_max = max(1, len(film) // 10)
    few_outliers(film, xy, status, reason, H0)
    edge = outline(film, np.array([s == "measured" for s in status]))
    coef = reach = None
    for _ in range(n_max):
        m = np.array([s == "measured" for s in status])
        if m.sum() < 8:
            break
        Hm = grid.projective_fit(film[m], xy[m])
        r = xy - grid.apply_h(Hm, film)
        idx = np.where(m)[0]
        pred = local_prediction(film[idx], r[idx], sigma=sigma[idx])
        dev = np.hypot(*(r[idx] - pred).T)
        # marks on the outline of the grid are predicted by extrapolation, which a strong
        # deformation makes worse than the interpolation inside: each group its own spread
        spread = robust_spread(dev, edge[idx])
        sg = np.nan_to_num(sigma[idx], nan=1.0)
        if reach is None:  # the marks measured when the test starts
            reach = np.ones(len(film))
            reach[idx] = extrapolation(film[idx], sigma[idx], edge[idx])
        if coef is None:  # from all measured marks, before any is rejected
            coef = departure_model(dev, sg, edge[idx], reach=reach[idx])
        fl = np.broadcast_to(floor_px, (len(film),))[idx] * reach[idx]
        thr = outlier_threshold(spread, fl, sg,
                                expected_departure(coef, sg, edge[idx], reach[idx]))
        bad = dev > thr
        if not bad.any():
            break
        worst = idx[int(np.argmax(np.where(bad, dev / thr, -1.0)))]
        status[worst] = "rejected"
        reason[worst] = "outlier against the global model and its neighbours"
    Hm, residual, rms = global_model(film, xy, status, Hm)
    return Hm, residual, rms, coef


#: with fewer than 8 crosses measured (too few for the neighbours' test of
#: :func:`reject_outliers`), a cross departing by more than this (film mm, and at least
#: :data:`FEW_OUTLIER_PX`) from the affine of the others is an outlier (:func:`few_outliers`):
#: a film deformation departs from an affine by a few hundredths of a millimetre over a few
#: crosses, a fit locked on a scene feature by several pixels (render 475: 9 px, 0.5 mm)
FEW_OUTLIER_MM = 0.15
#: ... and at least this (px)
FEW_OUTLIER_PX = 3.0
#: the fewest crosses that :func:`few_outliers` leaves measured (an affine of 4 judges one)
FEW_MIN_LEFT = 5


def few_outliers(film, xy, status, reason, H0) -> list[int]:
    """Where more than :data:`FEW_MIN_LEFT` and fewer than 8 marks are measured, reject
    (in place, in ``status`` and ``reason``) the one whose leaving out fits the others best
    (:func:`_loo_affine_departure`), when it departs from their affine model (film mm ->
    pixel system) by more than :data:`FEW_OUTLIER_MM` (at the scale of ``H0``, film mm ->
    pixel system, at the marks) and :data:`FEW_OUTLIER_PX`, and repeat while more than
    :data:`FEW_MIN_LEFT` stay measured. ``film`` (M, 2) mm, ``xy`` (M, 2)
    pixel system. Returns the indices rejected."""
    out = []
    while True:
        idx = np.flatnonzero(np.array([s == "measured" for s in status]))
        if not FEW_MIN_LEFT < len(idx) < 8:
            return out
        J = grid.h_jacobian(H0, film[idx].mean(0)[None])[0]
        thr = max(FEW_OUTLIER_MM * float(np.sqrt(abs(np.linalg.det(J)))), FEW_OUTLIER_PX)
        k, dev = _loo_affine_departure(film[idx], xy[idx])
        if not dev > thr:
            return out
        status[idx[k]] = "rejected"
        reason[idx[k]] = "outlier against the affine of the other crosses"
        out.append(int(idx[k]))


def _loo_affine_departure(film, xy) -> tuple[int, float]:
    """The mark whose leaving out fits the others best by an affine model film mm -> pixel
    system (the least sum of their squared residuals), and its distance (px) from that
    model: ``(k, dev)``. ``film`` (K, 2) mm, ``xy`` (K, 2) pixel system, K >= 5. (The
    largest leave-one-out residual alone would point at a corner mark extrapolated from a
    model that a gross mark among the others pulls.)"""
    K = len(film)
    A = np.column_stack([np.ones(K), film - film.mean(0)])
    others = np.nonzero(~np.eye(K, dtype=bool))[1].reshape(K, K - 1)  # row k: all but k
    As, ys = A[others], xy[others]  # (K, K-1, 3), (K, K-1, 2)
    sol = np.linalg.solve(np.einsum("kij,kil->kjl", As, As), np.einsum("kij,kil->kjl", As, ys))
    rest = np.sum((ys - As @ sol) ** 2, axis=(1, 2))
    k = int(np.argmin(rest))
    return k, float(np.hypot(*(xy[k] - A[k] @ sol[k])))


def global_model(film, xy, status, H0):
    """The projective model film mm -> pixel of the measured marks (``H0`` with fewer than
    4), their residuals (M, 2) px (pixel system; NaN where not measured) and rms (px)."""
    m = np.array([s == "measured" for s in status])
    Hm = grid.projective_fit(film[m], xy[m]) if m.sum() >= 4 else H0
    r = xy - grid.apply_h(Hm, film)
    residual = np.where(m[:, None], r, np.nan)
    rms = float(np.sqrt(np.mean(np.sum(r[m] ** 2, 1)))) if m.any() else float("nan")
    return Hm, residual, rms


def reinstate(film, xy, status, reason, floor_px, H) -> np.ndarray:
    """Outline marks rejected as outliers (:func:`reject_outliers`) and not measured again
    by the rescue, measured after all where a global polynomial of the measured marks'
    residuals (:func:`smooth_residuals`) places them within ``floor_px`` (px, scalar or (M,),
    the outlier test's floor): on a grid's outline the neighbours' local quadratic
    extrapolates a smooth film deformation 0.2-0.4 px wrong at 900-1700 dpi (the robustness
    sweep's correct outline crosses, 0.003-0.03 px off their truth, rejected), where the
    whole grid's polynomial follows it. ``film`` (M, 2) mm, ``xy`` (M, 2) pixel system,
    ``H`` (3, 3) the projective model film mm -> pixel of the measured marks
    (:func:`global_model`'s, which the outlier test has just fitted).
    Modifies ``status`` and ``reason`` in place; returns the indices measured again."""
    st = np.array(status)
    meas = st == "measured"
    cand = np.where((st == "rejected") & np.isfinite(xy).all(1)
                    & np.array([r.startswith("outlier") for r in reason]))[0]
    if len(cand) == 0 or meas.sum() < 8:
        return cand[:0]
    cand = cand[outline(film, meas)[cand]]
    pred = smooth_residuals(film[meas], xy[meas] - grid.apply_h(H, film[meas]), film[cand])
    if pred is None:
        return cand[:0]
    dev = np.hypot(*(xy[cand] - grid.apply_h(H, film[cand]) - pred).T)
    back = cand[dev <= np.broadcast_to(floor_px, (len(film),))[cand]]
    for i in back:
        status[i], reason[i] = "measured", ""
    return back


def smooth_residuals(film, r, at):
    """The residuals ``r`` (M, 2) px of marks at ``film`` (M, 2) mm from a projective model,
    evaluated at ``at`` (K, 2) mm by a global polynomial in film x, y of the degree of
    :data:`REINSTATE_DEGREES` whose leave-one-out error is smallest (of those the marks
    determine twice over); None when none is. Returns (K, 2) px."""
    c0, sc = film.mean(0), max(float(np.ptp(film, 0).max()), 1e-9)

    def basis(f, deg):
        u = (np.asarray(f, float) - c0) / sc
        return np.stack([u[:, 0] ** i * u[:, 1] ** j for i in range(deg + 1)
                         for j in range(deg + 1 - i)], 1)

    best = None
    for deg in REINSTATE_DEGREES:
        A = basis(film, deg)
        if len(film) < 2 * A.shape[1]:
            break
        q, _ = np.linalg.qr(A)
        lev = np.minimum((q**2).sum(1), 1 - 1e-9)
        coef = np.linalg.lstsq(A, r, rcond=None)[0]
        loo = float(np.mean(np.sum(((r - A @ coef) / (1 - lev)[:, None]) ** 2, 1)))
        if best is None or loo < best[0]:
            best = (loo, deg, coef)
    return None if best is None else basis(at, best[1]) @ best[2]


def extrapolation(film, sigma, edge, draws=16):
    """How far each mark's neighbours' prediction (:func:`local_prediction`) reaches beyond
    what is typical in its group (the grid's outline ``edge`` (M,) bool, or the inside):
    the square root of the prediction's variance for unit noise on the neighbours
    (``draws`` simulated sets) over its group's median, from 1 to :data:`EXTRAPOLATION_MAX`
    (M,). A corner of a strip of two rows beside a dark band, or of a cropped frame,
    extrapolates further than a mark along the outline: the deformation the local quadratic
    misses grows alike. A lone mark far from its neighbours (one measured on the noise of a
    dark region) extrapolates farther still, but is held to the cap."""
    z = np.random.default_rng(0).standard_normal((draws, len(film), 2))
    p = local_prediction(film, z, sigma=sigma)
    g = np.mean(p**2, axis=(0, 2))
    out = np.ones(len(film))
    for grp in (edge, ~edge):
        if grp.sum() >= 8:
            out[grp] = np.clip(np.sqrt(g[grp] / np.median(g[grp])), 1.0, EXTRAPOLATION_MAX)
    return out


def rescue(sc, shape, film, xy, cov, status, reason, Hm, sigma, floor_px, A, s0, init_err,
            sign, rules, max_shift, ppm, *, fitted, scene_tv=0, blur=None, departure=None,
            gain_ref=None, close=None):
    """Measure rejected and refused crosses again from three of their four half-arms.

    A cross rejected by the outlier test was usually pulled by scene content along one
    half-arm; one that the acceptance tests refused (``status`` "missing" among ``fitted``,
    (M,) bool: the crosses that were fitted, i.e. not cut by the scan edge) often has one
    half-arm on conflicting scene content. Each such
    cross is fitted four times, each time without one half-arm, from
    the position its neighbours predict and with the affine their positions predict held
    (:func:`position_affine`; where the neighbours do not surround the cross, at the grid's
    corners, the measured crosses' projective model's, :func:`model_affine`, unless the
    scene is busy (``scene_tv``); free from ``A`` (M, 2, 2) there): a free affine would let
    the remaining half of that bar set its direction alone (turned 10-28 degrees at the
    corners of sweep renders, refused as the wrong orientation), and the cross's precision
    would drop several times. A fit that passes
    the acceptance tests and lies within the outlier test's own threshold of that prediction
    is a measurement of the cross by its clean parts (of several such, the best-correlated).
    The blur is held at ``blur`` (px) when given; ``departure``, the outlier test's
    :func:`departure_model`, tightens that threshold as it does the test's. With
    ``gain_ref`` (the measured crosses' median contrast) a fit of less than
    :data:`RESCUE_MIN_GAIN` of it is no cross: over a flat region that exposes nothing the
    noise is quantised away, and a fit of no contrast passes the contrast-to-noise test. A
    cross that was not measured at all is predicted from the measured ones alone.
    ``cov``: the reported and the independent-pixel covariances (N, 2, 2) each. A refit
    less precise than :data:`RESCUE_MAX_SIGMA_RATIO` allows is taken where it lies as near
    the prediction as its own sigma says (:func:`_rescue_close`); with ``close`` (a list)
    the indices of the crosses measured so are appended to it (:func:`lone_arms` tries them
    as lone bars).
    Modifies the arrays in place; returns whether any cross was recovered.
    """
    st = np.array(status)
    rej = np.where((st == "rejected") | ((st == "missing") & np.asarray(fitted, bool)))[0]
    meas = np.where(st == "measured")[0]
    if rej.size == 0 or meas.size < 8:
        return False
    r = xy - grid.apply_h(Hm, film)
    miss = ~np.isfinite(r[rej]).all(1)
    ids = np.concatenate([meas, rej[~miss]])
    p_ids = local_prediction(film[ids], r[ids], sigma=sigma[ids])
    pred = np.zeros((meas.size + rej.size, 2))
    pred[: meas.size] = p_ids[: meas.size]
    pred[meas.size + np.where(~miss)[0]] = p_ids[meas.size :]
    if miss.any():  # not measured at all: predicted from the measured crosses alone
        q = rej[miss]
        pm = local_fit(film[q], film[meas], r[meas], 16, 2, n_sigma=sigma[meas])
        inner_q = ~outline(film)[q]
        if inner_q.any():
            pm[inner_q] = local_fit(film[q[inner_q]], film[meas], r[meas], 24, 3,
                                     n_sigma=sigma[meas])
        pred[meas.size + np.where(miss)[0]] = pm
    edge = outline(film, st == "measured")
    s_meas = float(np.median(sigma[meas]))
    dev_m = np.hypot(*(r[meas] - pred[: meas.size]).T)
    spread = robust_spread(dev_m, edge[meas])  # constant within each group
    s_in = float(spread[~edge[meas]][0]) if (~edge[meas]).any() else float(spread[0])
    s_out = float(spread[edge[meas]][0]) if edge[meas].any() else s_in
    sp_rej = np.where(edge[rej], s_out, s_in)
    target = grid.apply_h(Hm, film[rej]) + pred[meas.size :]
    best = np.full(rej.size, -np.inf)
    by_close = np.zeros(rej.size, bool)
    # at the grid's corners the measured crosses' model's affine held, unless the scene is
    # busy (the joint scene's): there a held affine let the three half-arms slide onto a
    # scene edge beside the cross (sweep renders' corner crosses 1-2.8 px off), where the
    # turn of a free fit shows the pull and refuses it
    for grp, Ag, fit_shape in _held_groups(film, xy, st == "measured", ppm, A, rej,
                                           H=None if scene_tv else Hm):
        for f2 in _three_arm_fits(sc, shape, target[grp], Ag, s0, init_err, sign, rules,
                                  max_shift, fit_shape, scene_tv, blur, gain_ref):
            sg = f2.sigma
            sp = sp_rej[grp]
            fl = floor_px[rej[grp]]
            exp = (None if departure is None
                   else expected_departure(departure, sg, edge[rej[grp]]))
            thr = outlier_threshold(sp, fl, sg, exp)
            d = np.hypot(*(f2.xy - target[grp]).T)
            good = f2.ok & (d <= thr) & (np.nan_to_num(f2.score, nan=-1.0) > best[grp])
            # three clean half-arms measure a cross nearly as well as four: a fit far less
            # precise than the measured crosses lies on the conflicting content it was to
            # avoid, unless it lies as near the prediction as its own sigma says
            like = _rescue_like(f2, s_meas, gain_ref)
            near = ~like & _rescue_close(f2, d, s_meas, gain_ref)
            for j in np.where(good & (like | near))[0]:
                i = rej[grp[j]]
                best[grp[j]] = f2.score[j]
                xy[i], cov[0][i], cov[1][i] = f2.xy[j], f2.cov[j], f2.cov_white[j]
                status[i], reason[i] = "measured", ""
                by_close[grp[j]] = near[j]
    if close is not None:
        close.extend(rej[by_close].tolist())
    return bool(np.isfinite(best).any())


def second_look(sc, shape, film, xy, cov, status, Hm, sigma, floor_px, A, s0, init_err,
                sign, rules, max_shift, ppm, *, scene_tv=0, blur=None, gain_ref=None):
    """Measure again, from their neighbours' prediction, the crosses that passed the outlier
    test by their own imprecision: a fit locked onto a road or a line of the scene beside an
    arm lies 1-4 px off its truth with a sigma of 0.3-3 px, which the outlier test's
    ``4 sigma`` lets through, while its neighbours' prediction is good to 0.1-0.5 px.

    A measured cross departing from its neighbours' prediction by more than
    :data:`SECOND_LOOK_SPREAD` times the robust spread of the measured crosses' departures
    (:func:`robust_spread`, about 1.7 standard deviations of them) and the outlier test's floor
    ``floor_px`` (px, (M,)) is fitted again from the prediction four times, each time without
    one half-arm (as :func:`rescue` fits, the affine the neighbours predict held, the blur held
    at ``blur``; at the grid's corners and outline with the affine of ``Hm`` held and free,
    :func:`_look_groups`). The best-correlated refit that passes the acceptance tests, is as
    precise as :func:`rescue` requires, lies within that reach of the prediction and at most
    half as far from it as the first fit, and is better supported than the first fit (its
    independent-pixel sigma no larger) replaces the first fit: three half-arms clear of the
    scene content measure the cross, where the first fit took the content for an arm. (A clean
    cross's three half-arms measure it less precisely than its four: its first fit stays; a
    refit chosen only for lying nearer the prediction would bias the departures the scan's
    variance factor and the lone bars' sigmas along them are taken from.)
    ``film`` (M, 2) mm; ``xy`` (M, 2) pixel system; ``cov`` the reported and the
    independent-pixel covariances (M, 2, 2) px^2 each; ``sigma`` (M,) px the independent-pixel
    precision; ``A`` (M, 2, 2) the fitted affines (pixel -> mark frame); ``Hm`` (3, 3) the
    global model film mm -> pixel. Modifies ``xy`` and ``cov`` in place; returns the indices
    measured again."""
    st = np.array(status)
    meas = np.where(st == "measured")[0]
    if meas.size < 8:
        return meas[:0]
    r = xy - grid.apply_h(Hm, film)
    pred = local_prediction(film[meas], r[meas], sigma=sigma[meas])
    edge = outline(film, st == "measured")
    dev = np.hypot(*(r[meas] - pred).T)
    reach = np.maximum(SECOND_LOOK_SPREAD * robust_spread(dev, edge[meas]),
                       np.broadcast_to(floor_px, (len(film),))[meas])
    # a first fit as precise as the scan's typical cross has no better-supported refit (its
    # three half-arms measure it less precisely than its four): not fitted again
    s_meas = float(np.median(sigma[meas]))
    sel = (dev > reach) & (np.nan_to_num(sigma[meas], nan=np.inf) > s_meas)
    if not sel.any():
        return meas[:0]
    cand, dev, reach = meas[sel], dev[sel], reach[sel]
    target = grid.apply_h(Hm, film[cand]) + pred[sel]
    best = np.full(cand.size, -np.inf)
    for grp, Ag, fit_shape in _look_groups(film, xy, st == "measured", ppm, A, cand, Hm):
        for f2 in _three_arm_fits(sc, shape, target[grp], Ag, s0, init_err, sign, rules,
                                  max_shift, fit_shape, scene_tv, blur, gain_ref):
            d = np.hypot(*(f2.xy - target[grp]).T)
            good = (f2.ok & (d <= reach[grp]) & (d <= 0.5 * dev[grp])
                    & (np.nan_to_num(f2.sigma, nan=np.inf) <= sigma[cand[grp]])
                    & (np.nan_to_num(f2.score, nan=-1.0) > best[grp])
                    & _rescue_like(f2, s_meas, gain_ref))
            for j in np.where(good)[0]:
                i = cand[grp[j]]
                best[grp[j]] = f2.score[j]
                xy[i], cov[0][i], cov[1][i] = f2.xy[j], f2.cov[j], f2.cov_white[j]
    return cand[np.isfinite(best)]


def consistent_outline(sc, shape, film, xy, cov, status, reason, arms, Hm, sigma, s0, init_err,
                       sign, rules, max_shift, ppm, vfac, *, scene_tv=0, blur=None,
                       gain_ref=None) -> np.ndarray:
    """Outline crosses rejected by the outlier test only because their neighbours'
    prediction is poor there, measured after all by their own fit.

    At a corner of the grid the neighbours' prediction extrapolates a deformation it does
    not follow: the robustness sweep's correct corner crosses (0.02-0.2 px off their truth)
    lay 0.26-1.1 px (3.3-5 of its standard deviations) off it, and a whole-grid polynomial
    (:func:`reinstate`) predicts them no better. Their own fit is what tells them from a fit
    pulled by scene content: each such cross (``status`` "rejected" by the outlier test,
    on the outline of the measured crosses) is fitted again four times, each time without one
    half-arm, started and anchored at its first fit ``xy`` (pixel system) with the affine of
    the global model ``Hm`` (film mm -> pixel system) held (:func:`model_affine`), the blur
    held at ``blur``. It is measured (its first fit kept) where every refit passes the
    acceptance tests, is as precise and as contrasted as :func:`rescue` asks, and lies within
    :data:`CONSISTENT_K` of its own sigma of the first fit (a fit pulled along one half-arm
    moves when that half-arm is left out), and where the first fit lies within
    :data:`CONSISTENT_PRED_K` standard deviations of the neighbours' prediction
    (:func:`lone_bar_prediction_cov` of the two-armed crosses ``arms`` == 2, for the scan's
    variance factor ``vfac``). Measured after the variance factor, they feed neither it nor
    the global model (the lone bars' neighbours, measured next, include them).
    ``film`` (M, 2) mm; ``cov`` the reported and the independent-pixel covariances (M, 2, 2)
    px^2 each; ``sigma`` (M,) px the independent-pixel precision. Modifies ``status``,
    ``reason`` and ``arms`` in place (the first fit's position and covariances are kept);
    returns the indices measured."""
    st = np.array(status)
    two = np.where((st == "measured") & (np.asarray(arms) == 2))[0]
    rej = np.array([s == "rejected" and r.startswith("outlier")
                    for s, r in zip(status, reason, strict=True)])
    q = np.where(rej & np.isfinite(xy).all(1) & outline(film, st == "measured"))[0]
    if q.size == 0 or two.size < 8 or shape is None or shape.kind != "cross":
        return q[:0]
    r = xy - grid.apply_h(Hm, film)
    pred = local_fit(film[q], film[two], r[two], 16, 2, n_sigma=sigma[two])
    loo = r[two] - local_prediction(film[two], r[two], sigma=sigma[two])
    pcov = lone_bar_prediction_cov(film, cov[0], sigma, two, q, Hm, loo, ppm, vfac) * vfac
    sd = np.sqrt(0.5 * np.maximum(pcov[:, 0, 0] + pcov[:, 1, 1], 0.0))
    near = np.hypot(*(r[q] - pred).T) <= CONSISTENT_PRED_K * sd
    q = q[near]
    if q.size == 0:
        return q
    s_meas = float(np.median(sigma[two]))
    good = np.ones(q.size, bool)
    for f3 in _three_arm_fits(sc, shape, xy[q], model_affine(Hm, film[q], ppm), s0, init_err,
                              sign, rules, max_shift, False, scene_tv, blur, gain_ref):
        d = np.hypot(*(f3.xy - xy[q]).T)
        good &= (f3.ok & _rescue_like(f3, s_meas, gain_ref)
                 & (d <= CONSISTENT_K * np.nan_to_num(f3.sigma, nan=0.0)))
    back = q[good]
    for i in back:
        status[i], reason[i], arms[i] = "measured", "", 2
    return back


def _look_groups(film, xy, ok, ppm, A, ids, H):
    """The groups of :func:`_held_groups` for :func:`second_look`'s refits of the crosses
    ``ids``: those whose neighbours do not surround them (at the grid's corners and along its
    outline) fitted twice, with the affine of the measured crosses' projective model ``H``
    (3, 3, film mm -> pixel system) held and free from ``A`` (M, 2, 2). Held, the three
    half-arms of a corner cross cannot turn onto a road beside its bars (sweep render 145's
    R7C0, 4.1 -> 1.5 px off its truth); free, the refit of render 452's corner cross R10C10
    correlates better and lies nearer its truth (1.03 px off with the affine held only): the
    better-correlated refit is taken.

    The corner and outline crosses held at the model's affine are a group (a call of
    :func:`measure`) of their own, apart from the surrounded crosses: a call judges its
    patches together (it takes the plane as their scene only where all are flat,
    :func:`~softplot.marks.measure.flat_scan`), and in one call with the outline crosses
    the surrounded crosses' refits came out otherwise, 0.2-0.5 px from their truth refused
    for fits 1.5-3.8 px off (the second renderer's aerial scan 189, 111 dpi: 19 more crosses
    over 1 px off)."""
    groups = _held_groups(film, xy, ok, ppm, A, ids)
    out = [g for g in groups if not g[2]]
    for grp, _, _ in (g for g in groups if g[2]):
        Am = model_affine(H, film[ids[grp]], ppm)
        fin = np.isfinite(Am).all((1, 2))
        if fin.any():
            out.append((grp[fin], Am[fin], False))
    return out + [g for g in groups if g[2]]


def _held_groups(film, xy, ok, ppm, A, ids, H=None):
    """The crosses ``ids`` in two groups, each ``(positions in ids, affines, fit_shape)``:
    those whose neighbours surround them, with the affine the neighbours' positions predict
    held (:func:`position_affine`), and the others (at the grid's corners the prediction
    extrapolates, its variance tens of times the typical), free from ``A`` (M, 2, 2), or,
    with ``H`` (3, 3, the measured crosses' projective model film mm -> pixel), with its
    affine held (:func:`model_affine`); ``ok`` (M,) bool the measured crosses; groups
    without a cross left out."""
    held, lev = position_affine(film, xy, ok, ppm)
    hold = (np.isfinite(held[ids]).all((1, 2))
            & (lev[ids] <= 4.0 * np.nanmedian(lev[np.asarray(ok, bool)])))
    if H is not None and not hold.all():
        held[ids[~hold]] = model_affine(H, film[ids[~hold]], ppm)
        hold = np.isfinite(held[ids]).all((1, 2))
    out = []
    for grp, fit_shape in ((np.where(hold)[0], False), (np.where(~hold)[0], True)):
        if grp.size:
            out.append((grp, A[ids[grp]] if fit_shape else held[ids[grp]], fit_shape))
    return out


def model_affine(H, film, ppm):
    """The pixel -> mark-frame affines (K, 2, 2) of crosses at ``film`` (K, 2) mm under the
    projective model ``H`` (film mm -> pixel system): the inverse of its Jacobian in the mark
    frame (u along film x, v along film -y, nominal px at ``ppm`` px per mm); NaN where the
    Jacobian is singular. Off by the film's deformation gradient only (a 100 um deformation
    over a 60 mm format: a few 1e-3), which turns and scales a symmetric cross without moving
    its centre."""
    return inverse_2x2(grid.h_jacobian(H, film) @ np.diag([1.0 / ppm, -1.0 / ppm]), 1e-12)


def _three_arm_fits(sc, shape, target, Ag, s0, init_err, sign, rules, max_shift, fit_shape,
                    scene_tv, blur, gain_ref):
    """The crosses at ``target`` (m, 2) pixel system (affines ``Ag`` (m, 2, 2)) fitted four
    times, each time without one half-arm (0: +u, 1: +v, 2: -u, 3: -v), anchored at
    ``target``: one call of :func:`measure`, as four calls would; a list of four
    :class:`~softplot.marks.measure.Fine` of m rows each."""
    m = len(target)
    f4 = measure(sc, shape, np.tile(target, (4, 1)), np.tile(Ag, (4, 1, 1)), s0, init_err,
                 sign, rules, anchor=np.tile(target, (4, 1)), max_shift=max_shift,
                 drop_part=np.repeat(np.arange(4), m), fit_shape=fit_shape,
                 scene_tv=scene_tv, blur=blur, gain_ref=gain_ref)
    return [f4.rows(slice(k * m, (k + 1) * m)) for k in range(4)]


def _rescue_like(f2, s_meas, gain_ref):
    """Refits (a :class:`~softplot.marks.measure.Fine`) as precise as :func:`rescue` asks
    (independent-pixel sigma at most :data:`RESCUE_MAX_SIGMA_RATIO` times the measured
    crosses' median ``s_meas`` px) and, with ``gain_ref``, of at least
    :data:`RESCUE_MIN_GAIN` of the crosses' contrast (bool per row)."""
    return ((np.nan_to_num(f2.sigma, nan=np.inf) <= RESCUE_MAX_SIGMA_RATIO * s_meas)
            & _rescue_gain_ok(f2, gain_ref))


def _rescue_gain_ok(f2, gain_ref):
    """Refits (a :class:`~softplot.marks.measure.Fine`) of at least :data:`RESCUE_MIN_GAIN`
    of the crosses' contrast ``gain_ref`` (bool per row; all where there is no reference)."""
    if gain_ref is None or f2.gain is None:
        return np.ones(np.shape(f2.sigma), bool)
    return np.abs(np.nan_to_num(f2.gain)) >= RESCUE_MIN_GAIN * gain_ref


def _rescue_close(f2, d, s_meas, gain_ref):
    """Refits (a :class:`~softplot.marks.measure.Fine`) less precise than :func:`_rescue_like`
    asks, up to :data:`RESCUE_CLOSE_SIGMA_RATIO` times the measured crosses' median
    independent-pixel sigma ``s_meas`` px, that lie within :data:`RESCUE_CLOSE_K` of their own
    sigma of the neighbours' prediction (``d`` px, pixel system distances) and, with
    ``gain_ref``, have at least :data:`RESCUE_MIN_GAIN` of the crosses' contrast (bool per
    row): a cross under a darker or busier patch than its peers, measured by its three clean
    half-arms where its neighbours say it is."""
    sg = np.nan_to_num(f2.sigma, nan=np.inf)
    return ((sg <= RESCUE_CLOSE_SIGMA_RATIO * s_meas) & (d <= RESCUE_CLOSE_K * sg)
            & _rescue_gain_ok(f2, gain_ref))


def lone_arms(sc, shape, film, xy, cov, status, reason, arms, Hm, sigma, A, s0, sign, rules,
               max_shift, fitted, blur, fine, ppm, along_max=np.inf, vfac=1.0, bar=None,
               fit=None, redo=()):
    """Crosses fitted but not measured (missing or rejected), measured again as a lone bar
    (:func:`softplot.marks.measure.measure_one_arm`): from the position and with the affine
    their neighbours predict; along the bar the position is that prediction, with its
    variance along the bar (:func:`lone_bar_prediction_cov`, for the scan's variance factor
    ``vfac``, which scales it later). The
    bar's contrast to noise, or its contrast, must be at least half the measured crosses'
    median (the noise under a lone bar is not always the crosses'). Where the per-axis RMS
    of the measured crosses' departures from their neighbours' (leave-one-out) predictions
    exceeds ``along_max`` (px; :data:`LONE_ARM_ALONG_MAX_MM` in px over the root of the
    scan's variance factor, which scales it later), no bar is measured: the scan's
    neighbours predict its crosses too poorly for any bar's point to be more than a guess
    along it. ``cov``:
    the reported and the independent-pixel covariances. Modifies the arrays in place
    (``arms`` 1 where a bar was measured; ``bar`` (N, 2), if given, the bar's unit vector
    there, pixel system; ``fit``, if given, the crosses' score and contrast-to-noise arrays
    (N,): the bar's fit's there, not the refused cross's). ``redo``: indices of crosses
    measured whole by a refit that is less sure of them (:func:`rescue`'s
    :func:`_rescue_close`), tried as lone bars as well, their whole fit kept where no bar
    passes (three half-arms of a one-armed cross with short, blurred arms pass as a whole
    cross, the missing bar's remaining half borrowing the central square's contrast: the
    sweep's render 345, 0.37 px across the bar off its truth against the lone bar's 0.10)."""
    st = np.array(status)
    st[np.array([i for i in redo if st[i] == "measured" and arms[i] == 2], int)] = "rejected"
    q = np.where(((st == "missing") | (st == "rejected")) & np.asarray(fitted, bool))[0]
    meas = np.where(st == "measured")[0]
    if q.size == 0 or meas.size < LONE_ARM_MIN_MEASURED or shape.kind != "cross":
        return
    r = xy - grid.apply_h(Hm, film)
    target = grid.apply_h(Hm, film[q]) + local_fit(film[q], film[meas], r[meas], 16, 2,
                                                     n_sigma=sigma[meas])
    loo = r[meas] - local_prediction(film[meas], r[meas], sigma=sigma[meas])
    rms = float(np.sqrt(np.mean(loo**2)))
    # judged before the floor: at 130 dpi the floor alone (0.5 px) exceeds the 0.1 mm
    # limit, and no bar of a well-predicted aerial frame was ever measured
    if rms > along_max:
        return
    pcov = lone_bar_prediction_cov(film, cov[0], sigma, meas, q, Hm, loo, ppm, vfac)
    f1 = _one_arm_fits(sc, shape, film, xy, st, q, meas, target, pcov, A, s0, sign, rules,
                       max_shift, blur, fine, ppm)
    for j, i in enumerate(q):
        if f1.ok[j]:
            xy[i], cov[0][i], cov[1][i] = f1.xy[j], f1.cov[j], f1.cov_white[j]
            status[i], reason[i], arms[i] = "measured", "", 1
            if bar is not None:
                bar[i] = f1.bar[j]
            if fit is not None:
                fit[0][i], fit[1][i] = f1.score[j], f1.cnr[j]


#: a cross measured whole is measured again as a lone bar only where its other bar's fit
#: finds less than this share of the bar's contrast (``bar_absent``'s half): on the sweep's
#: one-armed crosses measured whole 0-0.21, on whole crosses of busy, low-contrast or
#: saturated scans that one bar's fit sees more weakly 0.26-0.5
ONE_BAR_ABSENT = 0.25
#: ... and where the bar's fit correlates with its model at least this well: the sweep's
#: one-armed crosses measured whole 0.92-0.98, whole crosses on busy scenes 0.67-0.91 (of
#: those whose other bar's fit was below ``ONE_BAR_ABSENT``, 0.73)
ONE_BAR_MIN_SCORE = 0.85
#: where the crosses' joint regression (:func:`softplot.marks.measure.bar_share`) finds the
#: weaker bar below this share of the stronger's, the other bar's own fit may find up to
#: :data:`ONE_BAR_ABSENT_CLEAR` of the bar's contrast, the bar correlating with its model at
#: least :data:`ONE_BAR_MIN_SCORE_CLEAR`: on short, blurred arms that fit's pixels (those
#: nearer the missing bar's axis) hold the blurred central square and the bar's own blurred
#: flanks, which its whole-cross model gives the missing bar (the sweep's seed 53 R6C3:
#: 0.65 of the bar, the regression 0.00); the sweep's whole crosses of one-armed renders
#: with a regression below 0.3 and a half-plane fit below 0.7: bars correlating at most 0.83
ONE_BAR_CLEAR_SHARE = 0.3
ONE_BAR_ABSENT_CLEAR = 0.7
ONE_BAR_MIN_SCORE_CLEAR = 0.9


def _one_arm_fits(sc, shape, film, xy, st, q, meas, target, pcov, A, s0, sign, rules,
                  max_shift, blur, fine, ppm, **strict):
    """:func:`softplot.marks.measure.measure_one_arm` of the crosses ``q`` from ``target``
    (pixel system) with the affine their neighbours predict (:func:`position_affine`, ``A``
    where they do not surround the cross), along the bar the variance ``pcov`` (Q, 2, 2) px^2
    gives (pixel system, :func:`lone_bar_prediction_cov`), and the measured crosses'
    (``meas``) contrast and contrast to noise as the references; ``strict``: its ``absent``
    and ``min_score``. Returns the ``Fine``."""
    held, _ = position_affine(film, xy, st == "measured", ppm)
    Aq = np.where(np.isfinite(held[q]).all((1, 2))[:, None, None], held[q], A[q])
    cnr_ref = float(np.median(fine.cnr[fine.ok])) if fine.ok.any() else None
    return measure_one_arm(sc, shape, target, Aq, s0, sign, rules, max_shift=max_shift,
                           pred_cov=pcov, blur=blur, cnr_ref=cnr_ref,
                           gain_ref=peer_gain(fine, least=1), **strict)


def one_bar_crosses(sc, shape, film, xy, cov, status, arms, Hm, sigma, A, s0, sign, rules,
                    max_shift, blur, fine, ppm, along_max=np.inf, bar=None,
                    fit=None, skip=()) -> np.ndarray:
    """Crosses measured whole that show one bar only, measured again as a lone bar.

    A one-armed cross whose short or blurred arms let the missing bar's halves borrow the
    contrast of the shared central square passes the acceptance tests as a whole cross
    (:func:`softplot.marks.measure.lone_bar` sees its missing halves at half the contrast
    and more), and the missing bar in its model pulls the centre across the bar that is
    there. Each measured two-armed cross (``arms`` 2) whose bars look unlike each other
    (:func:`softplot.marks.measure.bar_share` below ``rules.bar_absent``) is fitted as a
    lone bar (:func:`_one_arm_fits`) from its neighbours' leave-one-out prediction; where
    one bar passes, correlates with its model at least :data:`ONE_BAR_MIN_SCORE` and the
    other's fit finds less than :data:`ONE_BAR_ABSENT` of its contrast (where the regression
    finds less than :data:`ONE_BAR_CLEAR_SHARE`: at least :data:`ONE_BAR_MIN_SCORE_CLEAR` and
    less than :data:`ONE_BAR_ABSENT_CLEAR`), the lone bar
    replaces the whole cross's fit (position across the bar, the prediction along it with
    its variance, :func:`lone_bar_prediction_cov`; ``arms`` 1). A whole cross, both bars
    seen, is left as it is. ``xy`` (N, 2) pixel system, ``film`` (N, 2) mm, ``cov``: the
    reported and the independent-pixel covariances; modified in place (and ``bar`` (N, 2),
    if given: the lone bar's unit vector, pixel system; ``fit``, if given, the score and
    contrast-to-noise arrays (N,): the bar's fit's). ``skip``: indices of crosses not looked
    at (:func:`rescue`'s close crosses, which :func:`lone_arms` tries as lone bars: here a
    second call of the lone bars' fit, 5 % of the CPU of a busy 1200 dpi scan). Returns the
    indices of the crosses measured again.
    """
    st = np.array(status)
    meas = np.where(st == "measured")[0]
    q = meas[np.asarray(arms)[meas] == 2]
    q = q[~np.isin(q, np.asarray(skip, int))]  # left to lone_arms, which tries them anyway
    if q.size == 0 or meas.size < LONE_ARM_MIN_MEASURED or shape.kind != "cross":
        return np.zeros(0, int)
    # the fits only where the crosses' bars look unlike each other (a cheap regression)
    share = bar_share(sc, shape, xy[q], A[q], blur if blur is not None else s0, sign)
    share = np.nan_to_num(share, nan=1.0)
    keep = share < (rules or AcceptRules()).bar_absent
    q, clear = q[keep], share[keep] < ONE_BAR_CLEAR_SHARE
    if q.size == 0:
        return np.zeros(0, int)
    r = xy - grid.apply_h(Hm, film)
    loo = r[meas] - local_prediction(film[meas], r[meas], sigma=sigma[meas])
    rms = float(np.sqrt(np.mean(loo**2)))
    if rms > along_max:
        return np.zeros(0, int)
    pos = np.searchsorted(meas, q)
    target = xy[q] - loo[pos]  # the neighbours' prediction of each (pixel system)
    # the scan's variance factor, which scales the covariances later, as the validation
    # will take it: without the crosses that may show one bar (measured whole, they lie off
    # and made it 5.4 where it is 1)
    rest = np.setdiff1d(meas, q)
    if rest.size < LONE_ARM_MIN_MEASURED:
        rest = meas
    vfac = variance_factor(film[rest], r[rest], cov[0][rest], local_prediction, ppm, H=Hm)
    pcov = lone_bar_prediction_cov(film, cov[0], sigma, rest, q, Hm,
                                   loo[np.searchsorted(meas, rest)], ppm, vfac)
    f1 = _one_arm_fits(sc, shape, film, xy, st, q, meas, target, pcov, A, s0, sign, rules,
                       max_shift, blur, fine, ppm,
                       absent=np.where(clear, ONE_BAR_ABSENT_CLEAR, ONE_BAR_ABSENT),
                       min_score=np.where(clear, ONE_BAR_MIN_SCORE_CLEAR, ONE_BAR_MIN_SCORE))
    ok = np.where(f1.ok)[0]
    xy[q[ok]], cov[0][q[ok]], cov[1][q[ok]] = f1.xy[ok], f1.cov[ok], f1.cov_white[ok]
    arms[q[ok]] = 1
    if bar is not None:
        bar[q[ok]] = f1.bar[ok]
    if fit is not None:
        fit[0][q[ok]], fit[1][q[ok]] = f1.score[ok], f1.cnr[ok]
    return q[ok]


#: film mm: four crosses measured on a grown lattice lie within this of the certificate's
#: grid under a similarity (a film scanner's anisotropy, 0.3 %, and a film's shrinkage over
#: a 6 x 4.5 frame's half-diagonal, and its deformation, stay well inside it)
SIMILAR_TOL_MM = 0.15


def similar_four(film, xy, status, reason, H, ppm) -> int:
    """Four measured crosses of a lattice grown from too few candidates, held to the
    certificate's grid under a similarity (rotation, one scale, shift; the handedness of the
    film mm -> pixel model ``H``): a projective model fits four crosses exactly, a similarity
    leaves four redundant coordinates. Each cross is predicted from the other three; when
    exactly one lies more than :data:`SIMILAR_TOL_MM` off that prediction and the other
    three within it of theirs from the rest, it is rejected (a scene feature measured at a
    node) and 3 is returned; when all four lie within it, 4; else 0 (no test passed).
    ``film`` (N, 2) mm, ``xy`` (N, 2) pixel system; modifies ``status``, ``reason``."""
    idx = np.where(np.array(status) == "measured")[0]
    if idx.size != 4:
        return 0
    flip = -1.0 if np.linalg.det(np.asarray(H, float)[:2, :2]) < 0 else 1.0
    u = np.column_stack([film[idx, 0], flip * film[idx, 1]])

    def off(fit, test):
        A = np.zeros((2 * len(fit), 4))
        A[0::2] = np.column_stack([u[fit, 0], -u[fit, 1], np.ones(len(fit)), np.zeros(len(fit))])
        A[1::2] = np.column_stack([u[fit, 1], u[fit, 0], np.zeros(len(fit)), np.ones(len(fit))])
        p = np.linalg.lstsq(A, xy[idx[fit]].ravel(), rcond=None)[0]
        a, b, tx, ty = p
        pred = np.column_stack([a * u[test, 0] - b * u[test, 1] + tx,
                                b * u[test, 0] + a * u[test, 1] + ty])
        return np.hypot(*(pred - xy[idx[test]]).T) / ppm

    tol = SIMILAR_TOL_MM
    loo = np.array([off(np.delete(np.arange(4), k), [k])[0] for k in range(4)])
    if (loo <= tol).all():
        return 4
    bad = np.where(loo > tol)[0]
    for k in bad:
        rest = np.delete(np.arange(4), k)
        inner = np.array([off(np.delete(rest, j), [rest[j]])[0] for j in range(3)])
        if (inner <= tol).all() and all((off(np.delete(rest, j), [k])[0] > tol)
                                        for j in range(3)):
            status[idx[k]] = "rejected"
            reason[idx[k]] = "off the grid the other crosses and the certificate give"
            return 3
    return 0


def h_parameter_jacobian(H, xy) -> np.ndarray:
    """Derivatives of a projective transform's output (pixel system) at ``xy`` (M, 2) (film
    mm) with respect to its eight parameters (``H`` scaled to ``H[2, 2] = 1``): (2M, 8),
    rows x and y of each point in turn."""
    H = np.asarray(H, float) / H[2, 2]
    xy = np.asarray(xy, float).reshape(-1, 2)
    x, y = xy[:, 0], xy[:, 1]
    w = H[2, 0] * x + H[2, 1] * y + 1.0
    out = grid.apply_h(H, xy)
    J = np.zeros((len(xy), 2, 8))
    for r in (0, 1):
        J[:, r, 3 * r:3 * r + 3] = np.column_stack([x, y, np.ones_like(x)]) / w[:, None]
        J[:, r, 6:] = -out[:, r, None] * xy / w[:, None]
    return J.reshape(-1, 8)


def prediction_cov(q_film, film, H, sigma, cov) -> np.ndarray:
    """Covariance (Q, 2, 2) px^2 (pixel system) of the neighbours' prediction of positions
    at ``q_film`` (Q, 2) mm, for independent errors of covariance ``cov`` (M, 2, 2) px^2
    (pixel system) on the marks at ``film`` (M, 2) mm, propagated exactly: the prediction
    (:func:`lone_arms`' target) is linear in the marks' positions. It is the global model
    ``H`` (film mm -> pixel system) fitted to the marks again (linearised, from 5 marks on)
    plus a local quadratic (:func:`local_fit`, weights from ``sigma`` (M,) px) of their
    residuals from it; a query point that is itself among the marks is left out of its own
    fit, as there. A corner of a small grid, extrapolated, gets the larger covariance."""
    q_film = np.asarray(q_film, float).reshape(-1, 2)
    film = np.asarray(film, float).reshape(-1, 2)
    M = len(film)
    # (Q, M) weights, non-zero only on the queries' neighbours (U): fitted to those columns
    # of the identity alone (all M of a 1000-cross grid took seconds)
    U = np.unique(nearest(q_film, film, min(16, M - 1) + 1)[1])
    L = np.zeros((len(q_film), M))
    L[:, U] = local_fit(q_film, film, np.eye(M)[:, U], 16, 2, n_sigma=sigma)
    G = L[:, :, None, None] * np.eye(2)  # d prediction_q / d position_j (Q, M, 2, 2)
    if M >= 5:
        Jm = h_parameter_jacobian(H, film)
        c = np.linalg.norm(Jm, axis=0)  # columns of very different scales
        dh = (np.linalg.pinv(Jm / c) / c[:, None]).reshape(8, M, 2)  # d h / d position_j
        # the model's change moves the query directly and the neighbours' residuals back
        Aq = (h_parameter_jacobian(H, q_film).reshape(-1, 2, 8)
              - np.einsum("qj,jrk->qrk", L, Jm.reshape(M, 2, 8)))
        G = G + np.einsum("qrk,kjc->qjrc", Aq, dh)
    return np.einsum("qjab,jbc,qjdc->qad", G, np.asarray(cov, float), G)


def lone_bar_prediction_cov(film, cov, sigma, meas, q, H, loo, ppm, vfac) -> np.ndarray:
    """Covariance (Q, 2, 2) px^2 (pixel system) of the neighbours' prediction of the lone
    bars ``q`` (indices into ``film`` (N, 2) mm), in the units of ``cov`` (N, 2, 2) px^2,
    the crosses' covariances before the scan's variance factor ``vfac`` scales them (it is
    divided out here): along a lone bar its position is that prediction.

    Two parts. What the measured crosses' (``meas``) own errors send through the prediction
    (:func:`prediction_cov`, their covariances times ``vfac``): it grows where the
    prediction extrapolates. And what the prediction misses of the film's deformation:
    their departures ``loo`` (M, 2) px from their neighbours' leave-one-out predictions,
    per axis in mean square, less what their own errors explain (their mean variance, and
    its share that the neighbours' prediction carries, for unit noise), isotropic, at least
    the deformation floor of :mod:`softplot.marks.precision` (a local fit's, or with fewer
    than its ``MIN_MARKS`` crosses the global model's). The spread of the departures alone
    (a 0.1 px floor) counted the crosses' own noise twice: normalised errors along the
    robustness sweep's lone bars of 0.43 (0.13-0.76 per condition); with this, 0.92."""
    meas = np.asarray(meas)
    Cm = np.asarray(cov, float)[meas] * vfac
    sg = np.asarray(sigma, float)[meas]
    floor_um = DEFORMATION_FLOOR_UM if len(meas) >= MIN_MARKS else GLOBAL_DEFORMATION_FLOOR_UM
    miss, _ = deformation_miss(loo, Cm, lambda v: local_prediction(film[meas], v, sigma=sg),
                               ppm, floor_um)
    pc = prediction_cov(film[q], film[meas], H, sg, Cm) + miss * np.eye(2)
    return pc / vfac


def edge_cut_part(xy, J, ppm, shape, width, height):
    """The half-arm by which each cross leaves the scan, where it is the only one and its tip
    leaves by at most :data:`EDGE_CUT_MAX` of the half-arm; :data:`EDGE_WHOLE` where no tip
    leaves (the cross lies whole on the scan); -1 elsewhere (N,) int (0: +u, 1: +v, 2: -u,
    3: -v of the mark frame, as :func:`~softplot.marks.measure.measure`'s ``drop_part``).
    ``xy`` (N, 2) the crosses' positions and ``J`` (N, 2, 2) the model's d pixel / d film mm
    there (pixel system), ``shape`` (px) the cross; a tip leaves where it lies less than a
    pixel inside the scan's ``width`` x ``height`` (as the test of what is fitted,
    :meth:`~softplot.marks.prediction.Prediction.inside`)."""
    ext = 0.5 * shape.length + 0.5 * shape.width
    # tips along film +x, -x, +y, -y: the mark frame's +u, -u, -v, +v
    d = np.stack([J[:, :, 0], -J[:, :, 0], J[:, :, 1], -J[:, :, 1]], 1) / ppm  # (N, 4, 2)
    tip = np.asarray(xy, float)[:, None, :] + ext * d
    hi = np.array([width - 1.5, height - 1.5])
    over = np.maximum(np.max(np.maximum(0.5 - tip, tip - hi), -1), 0.0)  # (N, 4) px
    k = np.argmax(over, 1)
    arm = ext * np.hypot(*d[np.arange(len(k)), k].T)
    one = ((over > 0).sum(1) == 1) & (over.max(1) <= EDGE_CUT_MAX * arm)
    part = np.where(one, np.array([0, 2, 3, 1])[k], -1)
    return np.where((over > 0).any(1), part, EDGE_WHOLE)


def edge_crosses(sc, pr: Prediction, m: Measurement, arms, Hm, vfac, floor_px, departure,
                 rules) -> np.ndarray:
    """Crosses not fitted because the scan's edge cuts them (:func:`edge_cut_part`: one
    half-arm's tip out by a little), measured from their other three half-arms (whole where
    the measured crosses' prediction places every tip on the scan, :data:`EDGE_WHOLE`), after
    the validation: from the position their measured neighbours predict (the model ``Hm`` plus
    a local quadratic of the residuals), with the affine their positions predict held
    (:func:`position_affine`, else the model's) and the blur held. Accepted as the rescue
    accepts (:func:`rescue`: a faint cross as the first pass accepts it, within the outlier
    test's threshold of the prediction, and as contrasted), but up to
    :data:`EDGE_MAX_SIGMA_RATIO` times less precise than its peers (the rescue's cap refused
    correct crosses whose patch the edge cuts). Measured last, they feed no neighbour's
    prediction, model or variance factor; their covariance is scaled by ``vfac``. Updates
    ``m`` and ``arms`` in place; returns the indices measured."""
    film, ppm, shape = pr.film, pr.px_per_mm, m.shape
    st = np.array(m.status)
    fitted = np.zeros(len(film), bool)
    fitted[m.fitted] = True
    meas = np.where(arms == 2)[0]
    q = np.where((st == "missing") & ~fitted)[0]
    if q.size == 0 or meas.size < 8 or shape is None or shape.kind != "cross":
        return np.zeros(0, int)
    sigma = m.sigma()
    r = m.xy - grid.apply_h(Hm, film)
    target = grid.apply_h(Hm, film[q]) + local_fit(film[q], film[meas], r[meas], 16, 2,
                                                     n_sigma=sigma[meas])
    part = edge_cut_part(target, pr.J[q], ppm, shape, sc.width, sc.height)
    keep = part >= 0
    q, target, part = q[keep], target[keep], part[keep]
    if q.size == 0:
        return q
    held, _ = position_affine(film, m.xy, arms == 2, ppm)
    A = np.where(np.isfinite(held[q]).all((1, 2))[:, None, None], held[q], pr.A[q])
    gain_ref = peer_gain(m.fine, least=1)
    f = _edge_fits(sc, shape, target, A, part, pr, rules, m.scene_tv, held_blur(m.fine),
                   gain_ref)
    # the outline's spread of the departures (the crosses at the scan's edge extrapolate)
    edge = outline(film, arms == 2)
    dev = np.hypot(*(r[meas] - local_prediction(film[meas], r[meas], sigma=sigma[meas])).T)
    sp = robust_spread(dev, edge[meas])
    s_out = float(sp[edge[meas]][0]) if edge[meas].any() else float(sp[0])
    sg = f.sigma
    exp = (None if departure is None
           else expected_departure(departure, sg, np.ones(q.size, bool)))
    # beyond the grid's outline the neighbours' prediction extrapolates further than on it
    thr = outlier_threshold(s_out, np.broadcast_to(floor_px, (len(film),))[q], sg, exp)
    thr = thr * _reach_beyond(film[q], film[meas], sigma[meas], edge[meas])
    good = f.ok & (np.hypot(*(f.xy - target).T) <= thr)
    good &= np.nan_to_num(sg, nan=np.inf) <= (
        EDGE_MAX_SIGMA_RATIO * float(np.median(sigma[meas])))
    if gain_ref is not None and f.gain is not None:
        good &= np.abs(np.nan_to_num(f.gain)) >= RESCUE_MIN_GAIN * gain_ref
    got = q[good]
    m.xy[got], m.cov[got], m.cov_white[got] = f.xy[good], f.cov[good] * vfac, f.cov_white[good]
    m.score[got], m.cnr[got] = f.score[good], f.cnr[good]
    for i in got:
        m.status[i], m.reason[i], arms[i] = "measured", "", 2
    return got


def _edge_fits(sc, shape, target, A, part, pr: Prediction, rules, scene_tv, blur, gain_ref):
    """:func:`edge_crosses`' fits of the crosses at ``target`` (Q, 2, pixel system) with the
    affines ``A`` (Q, 2, 2) held, anchored there: without the half-arm ``part`` (Q,) names,
    and whole where it is :data:`EDGE_WHOLE` (one call of
    :func:`~softplot.marks.measure.measure` each); a :class:`~softplot.marks.measure.Fine`
    of Q rows."""
    pieces = []
    for sel in (part != EDGE_WHOLE, part == EDGE_WHOLE):
        k = np.where(sel)[0]
        if k.size:
            drop = None if part[k[0]] == EDGE_WHOLE else part[k]
            pieces.append((k, measure(sc, shape, target[k], A[k], pr.s0, pr.init_err, pr.sign,
                                      rules, anchor=target[k], max_shift=pr.max_shift,
                                      drop_part=drop, fit_shape=False, scene_tv=scene_tv,
                                      blur=blur, gain_ref=gain_ref)))
    return pieces[0][1] if len(pieces) == 1 else merge_fine(len(part), pieces)


def _reach_beyond(q_film, film, sigma, edge, draws=16):
    """How much farther the neighbours' prediction of marks at ``q_film`` (Q, 2) mm (from the
    measured marks at ``film`` (M, 2) mm, local quadratic, as :func:`edge_crosses`) reaches
    than the leave-one-out predictions of the measured marks on the grid's outline
    (``edge`` (M,) bool): the square root of the ratio of their variances for unit noise on
    the marks (``draws`` simulated sets), from 1 to :data:`EXTRAPOLATION_MAX` (Q,)."""
    z = np.random.default_rng(0).standard_normal((draws, len(film), 2))
    pq = local_fit(q_film, film, z, 16, 2, n_sigma=sigma)
    pm = local_prediction(film, z, sigma=sigma)
    g = np.mean(pm**2, axis=(0, 2))
    ref = float(np.median(g[edge])) if edge.any() else float(np.median(g))
    return np.clip(np.sqrt(np.mean(pq**2, axis=(0, 2)) / ref), 1.0, EXTRAPOLATION_MAX)
