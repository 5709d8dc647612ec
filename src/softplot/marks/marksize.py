"""Stage 5 of the reseau path: the crosses' real size, measured on the scan.

The certificate's arm length and line width are only a starting guess: :func:`mark_geometry`
profiles the bars of the crosses the NCC map confirms near their prediction
(:func:`softplot.marks.geometry.estimate_geometry`); where the profiles leave the arm length
in doubt (faint, one-armed or busy crosses: the certificate's kept, or the bars disagree),
and where they leave the line width in doubt
(:func:`softplot.marks.geometry.width_candidates`), the least-squares fit of the best
crosses decides (:func:`choose_width`; the arm by how well each explains the same
pixels, :func:`arm_profile`). The hand-over is
:class:`softplot.marks.geometry.MarkGeometry` (mark frame, nominal px).
"""

from __future__ import annotations

import numpy as np

from softplot.marks.geometry import (
    ARM_RANGE,
    CONSISTENT,
    MarkGeometry,
    estimate_geometry,
    width_candidates,
)
from softplot.marks.measure import AcceptRules, Fine, _template, measure, patches
from softplot.marks.prediction import Prediction
from softplot.marks.template import MarkShape
from softplot.runtime import thread_map

__all__ = ["mark_geometry", "centred_geometry", "choose_width", "arm_candidates", "arm_profile"]

#: arm lengths tried where the profiles leave the arm in doubt, times the profiles' (or the
#: certificate's) arm: steps of sqrt(2), so the nearest is within the acceptance tests' size
#: tolerance (:attr:`softplot.marks.measure.AcceptRules.scale_tol`) of the real arm
ARM_TRIALS = (1.0, 2.0 ** -0.5, 0.5, 2.0 ** 0.5, 2.0)

#: the arm lengths :func:`arm_profile` compares, between the shortest and the longest trial:
#: geometric steps of this ratio
ARM_STEP = 2.0 ** 0.125

#: fewest accepted trial fits :func:`arm_profile` compares the arm lengths on (else the
#: trials' best score decides)
PROFILE_LEAST = 3

#: least mean ``log(RSS_plane / RSS_cross)`` over those crosses (:func:`arm_profile`): the
#: crosses explain at least 14 % of their patches' variance about a plane, else (a faint
#: cross in a busy scene) the profile is flat and the trials' best score decides
PROFILE_MIN_DEPTH = 0.15

#: least mean ``log RSS`` per cross by which the profile's best arm must beat the
#: best-scoring trial's (:func:`arm_profile`), else the trial's arm is kept: where the pixels
#: hardly tell them apart, the measuring stage's own choice stands (sweep render 362: 0.3-0.9
#: % less RSS, long arms 1.16x -> 0.98x the true arm, and the lattice read off a row)
PROFILE_MIN_GAIN = 0.015


def mark_geometry(scan, pr: Prediction, guess: MarkShape, pitch_px: float) -> MarkGeometry:
    """The crosses' size profiled at the confirmed predictions of ``pr`` (pixel system);
    ``guess`` the certificate's cross (px), ``pitch_px`` the grid's smaller pitch (px)."""
    prof = np.where(pr.found)[0]
    return estimate_geometry(scan.grey, pr.start[prof], pr.A[prof], guess, pr.sign,
                             pitch_px=pitch_px, score=pr.ncc[prof])


def arm_candidates(geom: MarkGeometry, guess_arm: float) -> list[float]:
    """Arm lengths (px, mark frame) worth a least-squares trial, the profiles' first.

    Only the profiles' arm when they measured it consistently (``source`` "scan", the bars'
    robust spread within :data:`softplot.marks.geometry.CONSISTENT` of it); else steps of
    sqrt(2) around it (:data:`ARM_TRIALS`) within
    :data:`softplot.marks.geometry.ARM_RANGE` times the certificate's ``guess_arm``: a
    certificate's arm is sometimes wrong by a factor of two, and the profiles of faint or
    one-armed crosses do not see it.
    """
    L = float(geom.arm_px)
    if geom.source == "scan" and geom.arm_spread_px <= CONSISTENT[0] * L:
        return [L]
    lo, hi = ARM_RANGE[0] * guess_arm, ARM_RANGE[1] * guess_arm
    return [L] + [L * f for f in ARM_TRIALS[1:] if lo <= L * f <= hi]


def _trial_fit(scan, pr: Prediction, trial, arm, width, rules) -> Fine:
    """The fits of the crosses ``trial`` (indices into ``pr``) with a cross of ``arm`` x
    ``width`` px (mark frame), shape free."""
    return measure(scan, MarkShape("cross", length=arm, width=width), pr.start[trial],
                   pr.A[trial], pr.s0, pr.init_err, pr.sign, rules, anchor=pr.xy[trial],
                   max_shift=pr.max_shift)


def _trial_score(ft: Fine) -> float:
    """Mean score of the fits ``ft`` (0 where not accepted)."""
    return float(np.mean(np.where(ft.ok, ft.score, 0.0)))


def _lsq_rss(y: np.ndarray, m: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Residual sums of squares (N,) and coefficients (N, K) of the least-squares fits of
    ``y`` (N, P) by the columns of ``X`` (N, K, P) over the pixels where ``m`` (N, P) is 1."""
    G = np.einsum("nkp,np,nlp->nkl", X, m, X) + 1e-9 * np.eye(X.shape[1])
    b = np.linalg.solve(G, np.einsum("nkp,np,np->nk", X, m, y)[..., None])[..., 0]
    r = (y - np.einsum("nk,nkp->np", b, X)) * m
    return np.einsum("np,np->n", r, r), b


def arm_profile(scan, c: np.ndarray, A: np.ndarray, s: float, width: float,
                arms: np.ndarray, sign: int) -> tuple[np.ndarray, float]:
    """How well crosses of each arm length explain the same pixels: ``sum_i log RSS_i``
    (len(arms),) over the N crosses at centres ``c`` (N, 2; pixel system) with the
    pixel -> mark-frame affines ``A`` (N, 2, 2) held, blur ``s`` and line width ``width``
    (px), each cross's RSS that of a plane (in the patch's pixel x, y) plus a multiple of
    the blurred cross of that arm (tip to tip, px, mark frame) over one patch around it
    that holds the longest (the multiple held at 0 where it has not the marks' polarity
    ``sign``, -1 dark marks); and the same sum by the planes alone (no cross). A too-short
    cross leaves the outer arm unexplained, a too-long one paints arm where there is none;
    the shape fits' scores do not see that (a fit shrinks a long template and fails the
    size test; a short one stays put). The smallest is the arm the pixels favour (a
    likelihood with each cross's own noise level)."""
    sv = np.linalg.svd(A, compute_uv=False)
    grow = float(1.0 / max(sv.min(), 1e-3))
    half = int(np.ceil(0.5 * float(np.max(arms)) * grow + 3.0 * s + 3))
    stack, origin = patches(scan, c, half)
    n, h, w = stack.shape
    m = np.isfinite(stack).reshape(n, -1).astype(float)
    y = np.nan_to_num(stack.reshape(n, -1).astype(float))
    yy, xx = np.mgrid[0:h, 0:w]
    base = np.broadcast_to(np.stack([np.ones(h * w), (xx.ravel() - w / 2) / w,
                                     (yy.ravel() - h / 2) / h]), (n, 3, h * w))
    flat, _ = _lsq_rss(y, m, base)
    sb = np.full(n, s, float)
    prof = []
    for a in arms:
        T = _template(MarkShape("cross", length=float(a), width=width), origin, c, A, sb,
                      (h, w))
        full, b = _lsq_rss(y, m, np.concatenate([base, T.reshape(n, 1, -1)], axis=1))
        prof.append(np.sum(np.log(np.maximum(np.where(b[:, 3] * sign > 0, full, flat),
                                             1e-30))))
    return np.asarray(prof), float(np.sum(np.log(np.maximum(flat, 1e-30))))


def profiled_arm(scan, pr: Prediction, trial: np.ndarray, ft: Fine, arms: list[float],
                 chosen: float, width: float) -> float | None:
    """The arm length (px, mark frame) of :func:`arm_profile` over geometric steps of
    :data:`ARM_STEP` from the shortest to the longest of ``arms`` (the trials' arms), on
    the crosses ``trial`` (indices into ``pr``) that the best-scoring trial's fits ``ft``
    accepted (their centres and median blur, the prediction's affines); None with fewer than
    :data:`PROFILE_LEAST` of them, where the crosses explain too little of their patches
    (:data:`PROFILE_MIN_DEPTH`), or where the profile hardly prefers its arm to that trial's
    arm ``chosen`` (px; :data:`PROFILE_MIN_GAIN`)."""
    ok = np.asarray(ft.ok, bool)
    if ok.sum() < PROFILE_LEAST:
        return None
    lo, hi = min(arms), max(arms)
    grid = lo * ARM_STEP ** np.arange(int(np.floor(np.log(hi / lo) / np.log(ARM_STEP) + 1e-9)) + 1)
    s = float(np.median(ft.s[ok])) if ft.s is not None else float(pr.s0)
    prof, plane = arm_profile(scan, ft.xy[ok], pr.A[trial][ok], s, width, grid, pr.sign)
    at = int(np.argmin(np.abs(np.log(grid / chosen))))  # the best-scoring trial's arm
    if (plane - prof.min() < PROFILE_MIN_DEPTH * ok.sum()
            or prof[at] - prof.min() < PROFILE_MIN_GAIN * ok.sum()):
        return None
    return float(grid[int(np.argmin(prof))])


def centred_geometry(scan, pr: Prediction, guess: MarkShape, pitch_px: float,
                     rounds: int = 3) -> tuple[MarkGeometry, Prediction]:
    """:func:`mark_geometry`, and the prediction ``pr`` moved to the crosses' centres where
    their bars' ends show them off it by more than the fits reach (``pr.max_shift``; e.g. a
    lattice of correlation peaks along long arms): profiled again from there, up to
    ``rounds`` times (a profile reaches about half a pitch, so a far offset is found in
    steps). Returns ``(geometry, prediction)``."""
    geom = mark_geometry(scan, pr, guess, pitch_px)
    for _ in range(rounds):
        if np.hypot(*geom.offset_px) <= max(pr.max_shift, 1.0):
            break
        pr = pr.shifted(geom.offset_px)
        geom = mark_geometry(scan, pr, guess, pitch_px)
    return geom, pr


def choose_width(scan, pr: Prediction, geom: MarkGeometry, guess_width: float,
                 rules: AcceptRules | None, guess_arm: float | None = None) -> MarkGeometry:
    """``geom`` with its arm length and line width settled.

    The arm: the profiles' one, or, where they leave it in doubt (:func:`arm_candidates`
    around the certificate's ``guess_arm`` px, default the profiles' arm), the 8
    best-correlated crosses are fitted with each candidate, and the arm the pixels around
    the best-scoring candidate's accepted fits favour (:func:`profiled_arm`, between the
    shortest and the longest candidate) is taken; where that cannot judge, the
    best-scoring candidate (the scores favour a short cross: a fit shrinks a longer one and
    refuses it as the wrong size). The width: the profiles' one,
    or, where they contradict the certificate's ``guess_width`` (px), the candidate whose fits
    of those crosses score highest.
    """
    prof = np.where(pr.found)[0]
    trial = prof[np.argsort(-pr.ncc[prof])[:8]]
    arms = arm_candidates(geom, geom.arm_px if guess_arm is None else guess_arm)
    if len(arms) > 1 and len(trial):
        w = geom.width_px if np.isfinite(geom.width_px) else guess_width
        # each trial's fits are its own: the trials side by side on the process's threads
        fits = thread_map(lambda a: _trial_fit(scan, pr, trial, a, w, rules), arms)
        best = int(np.argmax([_trial_score(f) for f in fits]))
        arm = profiled_arm(scan, pr, trial, fits[best], arms, arms[best], w)
        arm = arms[best] if arm is None else arm
        if arm != geom.arm_px:
            geom = geom.with_arm(arm)
    widths = width_candidates(geom, guess_width)
    if len(widths) == 1 or not len(trial):
        return geom.with_width(widths[0])
    # the profiles contradict the guess: the least-squares fit of the best crosses decides
    # (each trial's fits are its own: the trials side by side on the process's threads)
    scores = thread_map(lambda w: _trial_score(_trial_fit(scan, pr, trial, geom.arm_px, w,
                                                          rules)), widths)
    return geom.with_width(widths[int(np.argmax(scores))])
