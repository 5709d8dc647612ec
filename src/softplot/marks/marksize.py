"""Stage 5 of the reseau path: the crosses' real size, measured on the scan.

The certificate's arm length and line width are only a starting guess: :func:`mark_geometry`
profiles the bars of the crosses the NCC map confirms near their prediction
(:func:`softplot.marks.geometry.estimate_geometry`); where the profiles leave the line width
in doubt (:func:`softplot.marks.geometry.width_candidates`), the least-squares fit of the best
crosses decides (:func:`choose_width`). The hand-over is
:class:`softplot.marks.geometry.MarkGeometry` (mark frame, nominal px).
"""

from __future__ import annotations

import numpy as np

from softplot.marks.geometry import MarkGeometry, estimate_geometry, width_candidates
from softplot.marks.measure import AcceptRules, measure
from softplot.marks.prediction import Prediction
from softplot.marks.template import MarkShape

__all__ = ["mark_geometry", "choose_width"]


def mark_geometry(scan, pr: Prediction, guess: MarkShape, pitch_px: float) -> MarkGeometry:
    """The crosses' size profiled at the confirmed predictions of ``pr`` (pixel system);
    ``guess`` the certificate's cross (px), ``pitch_px`` the grid's smaller pitch (px)."""
    prof = np.where(pr.found)[0]
    return estimate_geometry(scan.grey, pr.start[prof], pr.A[prof], guess, pr.sign,
                             pitch_px=pitch_px, score=pr.ncc[prof])


def choose_width(scan, pr: Prediction, geom: MarkGeometry, guess_width: float,
                 rules: AcceptRules | None) -> MarkGeometry:
    """``geom`` with its line width settled: the profiles' one, or, where they contradict the
    certificate's ``guess_width`` (px), the candidate whose fits of the 8 best-correlated
    crosses score highest."""
    widths = width_candidates(geom, guess_width)
    if len(widths) == 1:
        return geom.with_width(widths[0])
    # the profiles contradict the guess: the least-squares fit of the best crosses decides
    prof = np.where(pr.found)[0]
    trial = prof[np.argsort(-pr.ncc[prof])[:8]]
    scores = []
    for w in widths:
        ft = measure(scan, MarkShape("cross", length=geom.arm_px, width=w), pr.start[trial],
                     pr.A[trial], pr.s0, pr.init_err, pr.sign, rules, anchor=pr.xy[trial],
                     max_shift=pr.max_shift)
        scores.append(float(np.mean(np.where(ft.ok, ft.score, 0.0))))
    return geom.with_width(widths[int(np.argmax(scores))])
