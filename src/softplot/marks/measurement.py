"""Stage 6 of the reseau path: least-squares measurement of every cross inside the scan.

:func:`measure_crosses` fits every cross whose extent lies inside the scan with least-squares
template matching at full resolution (:func:`softplot.marks.measure.measure`, robust weights,
against the scene under each cross as the grey opening estimates it; where the scene has sharp
edges at the crosses, or where the crosses depart from their neighbours far beyond their
own precision, the fits are refitted with the scene estimated jointly,
:mod:`softplot.marks.scene`); the acceptance tests (contrast, correlation, shape, support of
each arm) decide. Crosses whose fitted affine departs from their neighbours', or that failed,
are refitted with the neighbours' affine and blur held (:func:`shape_from_neighbours`);
crosses of another size (a larger centre cross) with their own (:func:`other_sizes`). The
hand-over is :class:`Measurement`. Marks of different shapes (fiducials) are measured one by
one (:func:`measure_marks`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from softplot.marks import grid
from softplot.marks.measure import (
    AcceptRules,
    Fine,
    measure,
    median_blur,
    merge_fine,
    peer_gain,
    peer_sigma,
)
from softplot.marks.neighbours import local_prediction, position_affine
from softplot.marks.precision import DEFORMATION_FLOOR_UM
from softplot.marks.prediction import Prediction
from softplot.marks.scene import JOINT_PASSES, busy_scene
from softplot.marks.template import MarkShape

__all__ = ["Measurement", "measure_crosses", "measure_marks", "shape_from_neighbours",
           "other_sizes", "held_blur"]

#: the expected blur of a second pass: this multiple of the first pass's median fitted blur.
#: Fitted in windows too narrow for it, the blur comes out low (a sweep render of blur sigma
#: 2.15 px fitted 1.30 px in windows for 1.04 px, 1.80 px in windows for 2.5-4 px); windows
#: for 1.6 x the fitted blur reach about the real blur
BLUR_REFIT = 1.6
#: the second pass runs where its expected blur exceeds the first's (``s0``) this many times
BLUR_GROW = 1.4
#: it is kept if it accepts at least this share of the first pass's crosses and its crosses
#: agree better with their neighbours (:func:`_fits_better`)
BLUR_KEEP = 0.95
#: and if the median square departure of its crosses from their neighbours' prediction is
#: at most this share of the first pass's (clearly better: that median over 100 crosses
#: varies by about 15 % from draw to draw)
BLUR_BETTER = 0.8


@dataclass
class Measurement:
    """The crosses measured (hand-over of :func:`measure_crosses`); the validation stage
    updates the per-cross arrays in place.

    Attributes
    ----------
    shape : MarkShape or None
        The cross fitted (mark frame px); None for marks of several shapes.
    fitted : (M,) int
        Indices of the crosses fitted (whole inside the scan), into the certificate's list.
    fine : softplot.marks.measure.Fine or None
        The fits of those M crosses (pixel system; ``A`` pixel -> mark-frame affines); None
        for marks measured one by one.
    scene_tv : int
        Joint-scene passes the fits took (0: the opening's scene).
    xy : (N, 2) ndarray
        Measured positions, full-resolution pixel system (NaN where not measured).
    cov : (N, 2, 2) ndarray
        Their covariance (px^2), correlated noise included.
    cov_white : (N, 2, 2) ndarray
        Their covariance for independent pixel noise (px^2): the outlier tests' precision.
    score, cnr : (N,) ndarray
        Correlation and contrast-to-noise of each fit (NaN where not fitted).
    status : list of str
        "measured" or "missing" per cross.
    reason : list of str
        Why a cross is not measured ("" where it is).
    """

    shape: MarkShape | None
    fitted: np.ndarray
    fine: Fine | None
    scene_tv: int
    xy: np.ndarray
    cov: np.ndarray
    cov_white: np.ndarray
    score: np.ndarray
    cnr: np.ndarray
    status: list
    reason: list

    def sigma(self) -> np.ndarray:
        """Each cross's precision for independent pixel noise (N,) px (NaN unmeasured)."""
        cw = self.cov_white
        return np.sqrt(0.5 * (cw[:, 0, 0] + cw[:, 1, 1]))


def measure_crosses(scan, shape: MarkShape, pr: Prediction, inside: np.ndarray,
                    on_img: np.ndarray, rules: AcceptRules | None,
                    scene: str = "auto") -> Measurement:
    """Fit every cross ``inside`` (N,) bool the scan (``on_img`` (N,) bool: centre on the
    scan, for the others' reason) from the prediction ``pr``, with the scene model ``scene``
    ("auto", "opening", "joint"). Where :data:`BLUR_REFIT` times the crosses' median fitted
    blur exceeds :data:`BLUR_GROW` times the expected one (``pr.s0``), they are fitted again
    with windows for that blur; if that fits better (:func:`_fits_better`) it is kept and
    ``pr.s0`` raised to it (the blur later refits and rescues start from). With ``scene``
    "auto", crosses fitted over the opening's scene that depart from their neighbours far
    beyond their own precision (:func:`_scene_disturbs`) are fitted again with the joint
    scene, kept if that fits better (:func:`_keep_opening`)."""
    idx = np.where(inside)[0]
    c0, A0, pred, ppm = pr.start, pr.A, pr.xy, pr.px_per_mm
    s0, init_err, sign, max_shift = pr.s0, pr.init_err, pr.sign, pr.max_shift
    def fit(s):
        # "auto": the joint scene where the first pass sees sharp scene edges at the crosses
        return measure(scan, shape, c0[idx], A0[idx], s, init_err, sign, rules,
                       anchor=pred[idx], max_shift=max_shift,
                       scene_tv=JOINT_PASSES if scene == "joint" else 0,
                       auto_tv=JOINT_PASSES if scene == "auto" else 0, busy=busy_scene,
                       contrast=True, gain_ref="set", opacity=True)

    fine = fit(s0)
    held = held_blur(fine)
    if held is not None and BLUR_REFIT * held > BLUR_GROW * s0 and idx.size >= 16:
        # the scan is blurrier than expected: the windows and the opening's disc, sized for
        # ``s0``, cut the blurred bars' skirts (and biased the fitted blur low); fitted again
        # with windows for the blur found, kept where that fits clearly better
        s1 = BLUR_REFIT * held
        f1 = fit(s1)
        if _fits_better(f1, fine, pr.film[idx]):
            fine, s0 = f1, s1
            pr.s0 = s1  # the blur later refits and rescues start from
    if scene == "auto" and not fine.scene_tv and _scene_disturbs(fine, pr.film[idx], ppm):
        # the crosses disagree with each other far more than their fits say: scene content
        # the opening's estimate leaves under them; the joint scene kept where it fits better
        f1 = measure(scan, shape, c0[idx], A0[idx], s0, init_err, sign, rules,
                     anchor=pred[idx], max_shift=max_shift, scene_tv=JOINT_PASSES,
                     contrast=True, gain_ref="set")
        if _fits_better(f1, fine, pr.film[idx]):
            fine = _keep_opening(f1, fine, pr.film[idx])
    tv = fine.scene_tv
    if fine.opacity != shape.opacity:  # the later fits take the crosses' opacity found
        shape = shape.with_opacity(fine.opacity)
    shape_from_neighbours(scan, shape, pr.film[idx], c0[idx], pred[idx], fine, s0, init_err,
                          sign, rules, max_shift, ppm, scene_tv=tv, A0=A0[idx])
    other_sizes(scan, shape, c0[idx], A0[idx], pred[idx], fine, s0, init_err, sign, rules,
                max_shift, scene_tv=tv)
    blob_size(scan, shape, c0[idx], A0[idx], pred[idx], fine, s0, init_err, sign, rules,
              max_shift, scene_tv=tv)
    few_faint(fine, rules or AcceptRules())
    N = len(pr.film)
    xy = np.full((N, 2), np.nan)
    cov = np.full((N, 2, 2), np.nan)
    cov_w = np.full((N, 2, 2), np.nan)  # independent pixels: the outlier tests' precision
    score = np.full(N, np.nan)
    cnr = np.full(N, np.nan)
    status = ["missing"] * N
    reason = ["outside the scan" if not on_img[i] else "cut by the scan edge" for i in range(N)]
    for k, i in enumerate(idx):
        score[i] = fine.score[k]
        cnr[i] = fine.cnr[k]
        if fine.ok[k]:
            xy[i] = fine.xy[k]
            cov[i], cov_w[i] = fine.cov[k], fine.cov_white[k]
            status[i] = "measured"
            reason[i] = ""
        else:
            reason[i] = fine.reason[k] or "not found"
    return Measurement(shape=shape, fitted=idx, fine=fine, scene_tv=tv, xy=xy, cov=cov,
                       cov_white=cov_w, score=score, cnr=cnr, status=status, reason=reason)


#: ``scene="auto"`` refits with the joint scene where the crosses' departures from their
#: neighbours exceed their own precision this many times (rms per axis, :func:`_scene_disturbs`;
#: scans of a flat or smooth scene 0.7-1.3, a strong texture under thin lines 1.7-4)
SCENE_DISTURBED = 1.5
#: a cross the opening refused and the joint scene's refit puts this many times the crosses'
#: median departure off its neighbours' prediction is refused (:func:`_keep_opening`)
SCENE_OFF = 3.0
#: faint crosses (:func:`softplot.marks.measure.faint`) are measured only with at least this
#: many crosses measured in all: a faint fit is weaker evidence than one that passes the
#: per-pixel tests, and a few of them on a busy scene's corners (4 fit a projective grid of
#: their own exactly) would make a reseau of a lattice the strong crosses refuse
FAINT_GRID = 6


def few_faint(fine: Fine, rules: AcceptRules) -> None:
    """Refuse (in place) the faint crosses of ``fine`` when fewer than :data:`FAINT_GRID`
    crosses are accepted in all."""
    if fine.ok.sum() >= FAINT_GRID:
        return
    weak = fine.ok & ((np.nan_to_num(fine.cnr) < rules.min_cnr)
                      | (np.nan_to_num(fine.score) < rules.min_score))
    for i in np.where(weak)[0]:
        fine.ok[i] = False
        fine.reason[i] = "faint, and too few crosses measured"


def measure_marks(scan, shapes, start: np.ndarray, A: np.ndarray, s0: float,
                  init_err: float, sign: int, rules: AcceptRules | None) -> Measurement:
    """Fit marks of different shapes one by one (fiducials): mark ``i`` of shape
    ``shapes[i]`` (px) from ``start[i]`` (N, 2) pixel system with the pixel -> mark-frame
    affine ``A`` (2, 2); a mark within its extent and 2 px of the scan's edge is cut (not
    fitted)."""
    N = len(shapes)
    xy = np.full((N, 2), np.nan)
    cov = np.full((N, 2, 2), np.nan)
    cov_w = np.full((N, 2, 2), np.nan)
    score = np.full(N, np.nan)
    cnr = np.full(N, np.nan)
    status = ["missing"] * N
    reason = ["not found"] * N
    fitted = []
    for m, shp in enumerate(shapes):
        ext = shp.extent + 2.0
        if not (ext <= start[m, 0] <= scan.width - 1 - ext
                and ext <= start[m, 1] <= scan.height - 1 - ext):
            reason[m] = "cut by the scan edge"
            continue
        fitted.append(m)
        fine = measure(scan, shp, start[m : m + 1], A[None], s0, init_err, sign, rules)
        score[m] = fine.score[0]
        cnr[m] = fine.cnr[0]
        if fine.ok[0]:
            xy[m] = fine.xy[0]
            cov[m] = fine.cov[0]
            if fine.cov_white is not None:
                cov_w[m] = fine.cov_white[0]
            status[m] = "measured"
            reason[m] = ""
        else:
            reason[m] = fine.reason[0] or "not found"
    return Measurement(shape=None, fitted=np.array(fitted, int), fine=None, scene_tv=0, xy=xy,
                       cov=cov, cov_white=cov_w, score=score, cnr=cnr, status=status,
                       reason=reason)


def shape_from_neighbours(sc, shape, film, c0, pred, fine, s0, init_err, sign, rules,
                           max_shift, ppm, z_max=2.5, scene_tv=0, A0=None):
    """Refit marks whose shape was pulled by the scene, with the shape of their neighbours.

    A cross's affine (scale, rotation, shear of the film and scanner at that place) varies
    smoothly over the film, so its neighbours' positions predict it
    (:func:`position_affine`). A scene edge along one half-arm pulls that half, and a free
    affine absorbs the pull by turning that bar, which hides it from LSM's half-arm test.
    So each element of the fitted affine is compared with the prediction: where one departs
    from it by more than ``z_max`` times the robust spread of that element's departures over
    all accepted marks (scaled by the prediction's own variance factor, larger at the grid's
    outline), or where the mark was not accepted, the mark is fitted again with the predicted
    affine held (the half-arm test then sees a pulled half and drops it), and the blur held
    at the accepted marks' median (:func:`held_blur`); the refit replaces the first when
    accepted. The spread adapts to the scan: where the prediction is the
    weaker of the two (a 100 um deformation at 2400 dpi, low noise) only the marks the scene
    really pulled stand out. Where fewer than 4 marks were accepted (the neighbours predict
    no affine) every mark is refitted with ``A0`` (N, 2, 2), the global model's affine; those
    refits are kept only if they lie on a grid (:func:`on_a_grid`). Modifies ``fine`` in
    place.
    """
    cons, lev, near = position_affine(film, fine.xy, fine.ok, ppm, with_position=True)
    # too few accepted for the neighbours to say (tiny crosses whose free affines scatter by
    # 40 % and 20 degrees): the global model's affine, and the refits judged as a grid
    few = A0 is not None and not np.isfinite(cons).all((1, 2)).any()
    if few:
        # the global model's affine, the same prediction everywhere: no position-dependent
        # variance factor (the neighbours' ``lev`` of a fit too degenerate for an affine is
        # not one: a near-singular normal matrix makes it any sign)
        cons = np.array(A0, float)
        lev = np.ones(len(film))
    have = np.isfinite(cons).all((1, 2))
    fin = have & np.isfinite(fine.A).all((1, 2))
    ref = fin & fine.ok
    z = np.full(len(film), np.inf)
    if ref.sum() >= 4:
        dth = np.full((len(film), 4), np.nan)
        dth[fin] = (fine.A[fin] - cons[fin]).reshape(-1, 4)
        med = np.median(dth[ref], axis=0)
        spread = 1.4826 * np.median(np.abs(dth[ref] - med), axis=0) + 1e-9
        scale = spread * np.sqrt(lev / np.median(lev[ref]))[:, None]
        z[fin] = np.max(np.abs(dth[fin] - med) / scale[fin], axis=1)
    redo = np.where(have & (~fine.ok | (z > z_max)))[0]
    if redo.size == 0:
        return
    # a refused mark starts where its neighbours put it: its own start may have been a scene
    # feature the lattice took for it (a prediction 8-13 px off, fits locked beside it); so
    # does an accepted one that lies far from there (a fit slid 5 px along an arm)
    start = np.where(fine.ok[redo, None], fine.xy[redo], c0[redo])
    d = np.hypot(*(fine.xy - near).T)
    okd = fine.ok & np.isfinite(d)
    lim = (max(3.0 * 1.4826 * float(np.median(d[okd])), 2.0 * init_err) if okd.sum() >= 4
           else np.inf)
    far = ~fine.ok | (d > lim)
    use = far[redo] & np.isfinite(near[redo]).all(1)
    start[use] = near[redo][use]
    blur = held_blur(fine)
    # started from the neighbours' position, the retry starts there too (the prediction's
    # start had been refused)
    anchor = np.where(use[:, None], start, pred[redo])
    f2 = measure(sc, shape, start, cons[redo], s0, init_err, sign, rules, anchor=anchor,
                 max_shift=max_shift, fit_shape=False, scene_tv=scene_tv, blur=blur,
                 sigma_ref=peer_sigma(fine), gain_ref=peer_gain(fine))
    # a refit started where the neighbours put the mark that ends as far from there as a
    # slid fit lies has slid too (onto the scene beside a cross on a busy 3 x 3 grid)
    f2.ok[use & (np.hypot(*(f2.xy - near[redo]).T) > lim)] = False
    # of two accepted fits of one mark, keep the one that agrees better with its neighbours:
    # the outlier test's leave-one-out prediction of its residual against a projective model
    both = fine.ok[redo] & f2.ok
    if both.any() and fine.ok.sum() >= 8:
        m = np.where(fine.ok)[0]
        k = redo[both]
        at = neighbours_place(film[m], fine.xy[m])[np.searchsorted(m, k)]
        worse = np.hypot(*(f2.xy[both] - at).T) > np.hypot(*(fine.xy[k] - at).T)
        f2.ok[np.where(both)[0][worse]] = False
    if few and not on_a_grid(film[redo], f2.xy, f2.ok, f2.sigma):
        return
    for j, i in enumerate(redo):
        if f2.ok[j]:
            _take(fine, i, f2, j)
            fine.A[i] = cons[i]  # the affine held in the refit


#: refits with the global model's affine are a grid when the median distance of their
#: positions from a projective model fitted to them is at most this many times their median
#: precision (a median of |r| of about 1.2 sigma for a 2-D Gaussian; fits locked on the
#: texture of a faint scan lie tens of sigmas off)
GRID_FIT_K = 3.0
#: ... and when at least this many are accepted (a projective model of 8 parameters is
#: judged by 8 marks' 16 coordinates)
GRID_FIT_MIN = 8


def on_a_grid(film: np.ndarray, xy: np.ndarray, ok: np.ndarray, sigma: np.ndarray) -> bool:
    """Do the accepted fits ``ok`` (M,) bool (positions ``xy`` (M, 2) pixel system, of marks
    at ``film`` (M, 2) mm, precision ``sigma`` (M,) px) lie on a projective grid: at least
    :data:`GRID_FIT_MIN` of them, their median distance from the model fitted to them at
    most :data:`GRID_FIT_K` times their median precision?"""
    ok = np.asarray(ok, bool) & np.isfinite(xy).all(1) & np.isfinite(sigma)
    if ok.sum() < GRID_FIT_MIN:
        return False
    H = grid.projective_fit(film[ok], xy[ok])
    r = np.hypot(*(xy[ok] - grid.apply_h(H, film[ok])).T)
    return bool(np.median(r) <= GRID_FIT_K * float(np.median(sigma[ok])))


#: fits of a cross of another size (:func:`other_sizes`) at most: each refit refused as the
#: wrong size starts the next at the size it found
OTHER_SIZE_ROUNDS = 3


def other_sizes(sc, shape, c0, A0, pred, fine, s0, init_err, sign, rules, max_shift,
                 scene_tv=0, steps=(0.5, 2.5), rounds=OTHER_SIZE_ROUNDS):
    """Measure crosses of another size than the others (a larger centre cross) with their own.

    A cross refused as "wrong size" had its fitted affine scale the mark by ``k`` (the square
    root of the determinants' ratio, fitted over predicted ``A0`` (N, 2, 2), pixel ->
    mark frame); when ``k`` lies within ``steps`` it is fitted again with the shape scaled by
    ``k`` (arms and lines) from its fitted centre (else ``c0`` (N, 2), pixel system) and the
    predicted affine, and an accepted fit replaces the refusal. A refit refused as the wrong
    size again scales the mark by its own ``k``: the product is fitted next, up to ``rounds``
    fits (a cross twice the others' size, fitted in a window for the others, came out 1.47
    times their size, and the 1.5 times larger template 1.47 times larger again).
    Modifies ``fine`` in place."""
    if fine.A is None:
        return
    bad = np.array([not o and r == "wrong size" for o, r in zip(fine.ok, fine.reason,
                                                                   strict=True)])
    bad &= np.isfinite(fine.A).all((1, 2))
    if not bad.any():
        return
    idx = np.where(bad)[0]
    k = _scale(A0[idx], fine.A[idx])
    start = np.where(np.isfinite(fine.xy[idx]).all(1, keepdims=True), fine.xy[idx], c0[idx])
    for _ in range(rounds):
        inside = (k >= steps[0]) & (k <= steps[1])
        idx, k, start = idx[inside], k[inside], start[inside]
        if idx.size == 0:
            return
        again = np.zeros(idx.size, bool)
        k_next = np.full(idx.size, np.nan)
        xy_next = start.copy()
        # one fit per size class (scales rounded to a tenth)
        for kk in np.unique(np.round(k, 1)):
            sel = np.where(np.round(k, 1) == kk)[0]
            grp = idx[sel]
            big = MarkShape("cross", length=shape.length * kk, width=shape.width * kk)
            f2 = measure(sc, big, start[sel], A0[grp], s0 * max(kk, 1.0), init_err, sign,
                         rules, anchor=pred[grp], max_shift=max_shift, scene_tv=scene_tv,
                         sigma_ref=peer_sigma(fine), gain_ref=peer_gain(fine))
            for j, i in enumerate(grp):
                if f2.ok[j]:
                    _take(fine, i, f2, j)
            size = np.array([not o and r == "wrong size" for o, r in zip(f2.ok, f2.reason,
                                                                        strict=True)])
            size &= np.isfinite(f2.A).all((1, 2)) & np.isfinite(f2.xy).all(1)
            again[sel] = size
            k_next[sel] = kk * _scale(A0[grp], f2.A)
            xy_next[sel] = np.where(size[:, None], f2.xy, start[sel])
        # a refit that scales the mark as the last did has found no other size
        again &= np.abs(np.round(k_next, 1) - np.round(k, 1)) >= 0.1
        idx, k, start = idx[again], k_next[again], xy_next[again]


def _take(fine: Fine, i: int, f2: Fine, j: int) -> None:
    """Cross ``i`` of ``fine`` accepted as fit ``j`` of ``f2`` (in place)."""
    fine.xy[i], fine.cov[i], fine.A[i] = f2.xy[j], f2.cov[j], f2.A[j]
    fine.score[i], fine.cnr[i], fine.ok[i], fine.reason[i] = f2.score[j], f2.cnr[j], True, ""
    if fine.s is not None and f2.s is not None:
        fine.s[i] = f2.s[j]
    for extra in ("cov_white", "arms", "gain", "cov_jpeg"):
        a, b = getattr(fine, extra, None), getattr(f2, extra, None)
        if a is not None and b is not None:
            a[i] = b[j]


#: at least this many crosses (and more than are accepted) refused as "wrong size" at one
#: common size (:func:`blob_size`) are crosses whose size the scan does not resolve
BLOB_MIN = 4


def blob_size(sc, shape, c0, A0, pred, fine, s0, init_err, sign, rules, max_shift,
              scene_tv=0) -> None:
    """Measure crosses whose fits shrink the template whatever size it starts from.

    Crosses of arms a few pixels long under blur and JPEG blocks (one block across) show
    as blobs whose size the fitted affine does not settle: it shrinks the template, and
    shrinks it again when :func:`other_sizes` starts from the shrunk size, so no template
    size passes the size test. When at least :data:`BLOB_MIN` crosses, and more than are
    accepted, are refused as "wrong size" with scales ``k`` (fitted over predicted ``A0``,
    as :func:`other_sizes`) that agree with their median ``km`` within half the size
    tolerance (robust spread), they are fitted again from ``c0`` (pixel system) with the
    arm scaled by ``km`` and the size tolerance widened by ``|1/km - 1|``; a fit is accepted
    when its scale lies within the size tolerance of the median scale of those accepted
    (the crosses' common size; a scene feature fitted at a node takes its own).
    Modifies ``fine`` in place."""
    if fine.A is None:
        return
    rules = rules or AcceptRules()
    bad = np.array([not o and r == "wrong size" for o, r in zip(fine.ok, fine.reason,
                                                                   strict=True)])
    bad &= np.isfinite(fine.A).all((1, 2))
    if bad.sum() < max(BLOB_MIN, fine.ok.sum()):
        return
    idx = np.where(bad)[0]
    k = _scale(A0[idx], fine.A[idx])
    km = float(np.median(k))
    if 1.4826 * float(np.median(np.abs(k - km))) > 0.5 * rules.scale_tol * km:
        return  # no common size: each fitted to something of its own
    wide = replace(rules, scale_tol=abs(1.0 / km - 1.0) + rules.scale_tol)
    blob = MarkShape("cross", length=shape.length * km, width=shape.width)
    f2 = measure(sc, blob, c0[idx], A0[idx], s0, init_err, sign, wide, anchor=pred[idx],
                 max_shift=max_shift, scene_tv=scene_tv, sigma_ref=peer_sigma(fine),
                 gain_ref=peer_gain(fine))
    if f2.A is None:
        return
    k2 = _scale(A0[idx], f2.A)
    k2m = float(np.median(k2[f2.ok])) if f2.ok.any() else np.nan
    agree = np.abs(k2 / k2m - 1.0) <= rules.scale_tol
    for j, i in enumerate(idx):
        if f2.ok[j] and agree[j]:
            _take(fine, i, f2, j)


def _scale(A0: np.ndarray, A: np.ndarray) -> np.ndarray:
    """The scale ``k`` of marks fitted with the affines ``A`` (K, 2, 2) over their predicted
    ``A0`` (K, 2, 2): the square root of the determinants' ratio (NaN where not fitted)."""
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.abs(np.linalg.det(A0)) / np.maximum(np.abs(np.linalg.det(A)), 1e-12))


def neighbours_place(film: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Where each mark's neighbours put it (M, 2) px, pixel system: the projective model of
    all marks (``film`` (M, 2) mm -> ``xy`` (M, 2) px) plus the outlier test's leave-one-out
    prediction of its residual (:func:`softplot.marks.neighbours.local_prediction`)."""
    Hm = grid.projective_fit(film, xy)
    at = grid.apply_h(Hm, film)
    return at + local_prediction(film, xy - at)


def _scene_disturbs(fine: Fine, film: np.ndarray, ppm: float | None = None) -> bool:
    """Do the accepted crosses (``film`` (M, 2) mm) depart from their neighbours' prediction
    (:func:`neighbours_place`) more than :data:`SCENE_DISTURBED` times what their own
    precision and, at ``ppm`` px per mm, the film deformation the neighbours' prediction
    misses explain (rms per axis: the median square departure, px^2, against twice the
    median variance of the independent-pixel covariance plus the square of
    :data:`~softplot.marks.precision.DEFORMATION_FLOOR_UM`)?
    A textured scene the opening's estimate does not follow under thin, blurred lines moves
    the fits so, while their own precision, for flat noise, does not show it. At high
    resolution the crosses' precision is far below the deformation's share (a textured
    Rollei scan at 2400 dpi: departures of 0.006 px, sigmas of 0.003 px): that is no scene's
    doing, and the joint scene's refit tripled the scan's detection time."""
    ok = fine.ok & np.isfinite(fine.xy).all(1)
    if ok.sum() < 16:
        return False
    d = fine.xy[ok] - neighbours_place(film[ok], fine.xy[ok])
    dep = float(np.median(np.sum(np.square(d), 1)))
    var = float(np.median(np.square(fine.sigma[ok])))
    floor = 0.0 if ppm is None else (DEFORMATION_FLOOR_UM * 1e-3 * ppm) ** 2
    return dep > 2.0 * SCENE_DISTURBED**2 * (var + floor)


def _keep_opening(f1: Fine, f0: Fine, film: np.ndarray) -> Fine:
    """The joint scene's fits ``f1`` of the crosses (``film`` (M, 2) mm), with the opening's
    ``f0`` kept where the joint pass refused a cross the opening accepted; a cross the
    opening refused and the joint pass moved off its neighbours (departure from their
    leave-one-out prediction, :func:`neighbours_place`, beyond :data:`SCENE_OFF` times the
    joint fits' median: a scene edge beside a thin bar taken for the bar) is refused, and
    the later refits from the neighbours' shape measure it again."""
    keep = f0.ok & ~f1.ok
    k0, k1 = np.where(keep)[0], np.where(~keep)[0]
    out = merge_fine(len(keep), [(k1, f1.rows(k1)), (k0, f0.rows(k0))])
    if out.ok.sum() < 8:
        return out
    ok = np.where(out.ok)[0]
    d = np.full(len(keep), np.nan)
    d[ok] = np.hypot(*(out.xy[ok] - neighbours_place(film[ok], out.xy[ok])).T)
    off = f1.ok & ~f0.ok & (np.nan_to_num(d) > SCENE_OFF * float(np.median(d[ok])))
    for i in np.where(off)[0]:
        out.ok[i], out.reason[i] = False, "moved away from its neighbours"
    return out


def _fits_better(f1: Fine, f0: Fine, film: np.ndarray) -> bool:
    """Does the second pass ``f1`` (windows for a wider blur) measure the crosses (``film``
    (M, 2) mm) better than the first ``f0``? It must accept at least :data:`BLUR_KEEP` of
    the first's crosses and, over the crosses both accept (at least 8; else accept twice as
    many), depart clearly less from their neighbours (median square distance, px^2, to the
    outlier test's leave-one-out prediction, at most :data:`BLUR_BETTER` times the first's;
    the median: one cross on a scene feature must not decide): the grid sees the real
    errors, which wider windows over a strong texture or a busy scene may raise."""
    n0, n1 = int(f0.ok.sum()), int(f1.ok.sum())
    if n1 < BLUR_KEEP * n0:
        return False
    both = f1.ok & f0.ok
    if both.sum() < 8:  # too few for the neighbours to judge: only if it accepts many more
        return n1 >= max(8, 2 * n0)

    def departure(xy):
        d = xy[both] - neighbours_place(film[both], xy[both])
        return float(np.median(np.sum(np.square(d), 1)))

    return departure(f1.xy) <= BLUR_BETTER * departure(f0.xy)


def held_blur(fine) -> float | None:
    """The blur (px) that refits and rescues hold (:func:`softplot.marks.measure.median_blur`
    of the accepted marks)."""
    return median_blur(fine.s, fine.ok) if fine.s is not None else None
