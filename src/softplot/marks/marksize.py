"""Stage 5 of the reseau path: the crosses' real size, measured on the scan.

The certificate's arm length and line width are only a starting guess: :func:`mark_geometry`
profiles the bars of the crosses the NCC map confirms near their prediction
(:func:`softplot.marks.geometry.estimate_geometry`); where the profiles leave the arm length
in doubt (faint, one-armed or busy crosses: the certificate's kept, or the bars disagree),
and where they leave the line width in doubt
(:func:`softplot.marks.geometry.width_candidates`), the least-squares fit of the best
crosses decides (:func:`choose_width`). The hand-over is
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
from softplot.marks.measure import AcceptRules, measure
from softplot.marks.prediction import Prediction
from softplot.marks.template import MarkShape
from softplot.runtime import thread_map

__all__ = ["mark_geometry", "centred_geometry", "choose_width", "arm_candidates"]

#: arm lengths tried where the profiles leave the arm in doubt, times the profiles' (or the
#: certificate's) arm: steps of sqrt(2), so the nearest is within the acceptance tests' size
#: tolerance (:attr:`softplot.marks.measure.AcceptRules.scale_tol`) of the real arm
ARM_TRIALS = (1.0, 2.0 ** -0.5, 0.5, 2.0 ** 0.5, 2.0)


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


def _trial_score(scan, pr: Prediction, trial, arm, width, rules) -> float:
    """Mean score of the fits of the crosses ``trial`` (0 where not accepted) with a cross of
    ``arm`` x ``width`` px."""
    ft = measure(scan, MarkShape("cross", length=arm, width=width), pr.start[trial],
                 pr.A[trial], pr.s0, pr.init_err, pr.sign, rules, anchor=pr.xy[trial],
                 max_shift=pr.max_shift)
    return float(np.mean(np.where(ft.ok, ft.score, 0.0)))


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
    around the certificate's ``guess_arm`` px, default the profiles' arm), the candidate
    whose fits of the 8 best-correlated crosses score highest. The width: the profiles' one,
    or, where they contradict the certificate's ``guess_width`` (px), the candidate whose fits
    of those crosses score highest.
    """
    prof = np.where(pr.found)[0]
    trial = prof[np.argsort(-pr.ncc[prof])[:8]]
    arms = arm_candidates(geom, geom.arm_px if guess_arm is None else guess_arm)
    if len(arms) > 1 and len(trial):
        w = geom.width_px if np.isfinite(geom.width_px) else guess_width
        scores = thread_map(lambda a: _trial_score(scan, pr, trial, a, w, rules), arms)
        best = int(np.argmax(scores))
        if best:
            geom = geom.with_arm(arms[best])
    widths = width_candidates(geom, guess_width)
    if len(widths) == 1 or not len(trial):
        return geom.with_width(widths[0])
    # the profiles contradict the guess: the least-squares fit of the best crosses decides
    # (each trial's fits are its own: the trials side by side on the process's threads)
    scores = thread_map(lambda w: _trial_score(scan, pr, trial, geom.arm_px, w, rules), widths)
    return geom.with_width(widths[int(np.argmax(scores))])
