"""A faint grid judged as a whole: crosses that each fail the acceptance tests, but lie on
a projective grid together.

Over a strong texture a heavily blurred, faint reseau's crosses each correlate 0.2-0.45 with
their fits (the texture's share of the window; a cross needs 0.45), and each is refused,
though all of them lie where the lattice puts them. Their joint evidence is the lattice's
projective consistency: fitted with the global model's affine held, each where it correlates
best near its prediction, fits to scene content scatter about the nodes (lattices of scene
clutter: 4-30 times the fits' precision off a projective grid), fits to the crosses do not.
:func:`faint_grid` measures the crosses so, accepts them together where their departure from
the projective grid fitted to them is within :data:`FAINT_GRID_K` times their median
precision, and reports that departure as their precision where it exceeds their own
(pixel system throughout; film mm for the grid's nodes).
"""

from __future__ import annotations

import numpy as np

from softplot.marks import grid
from softplot.marks.measure import AcceptRules, Fine, measure
from softplot.marks.measurement import Measurement
from softplot.marks.prediction import Prediction
from softplot.marks.template import MarkShape

__all__ = ["faint_grid", "grid_departure", "alike_contrast", "FAINT_GRID_MIN", "FAINT_GRID_K",
           "FAINT_GRID_SIGMA", "FAINT_GRID_GAIN_SPREAD"]

#: crosses inside the scan that a faint grid needs: a projective model (8 parameters) is
#: judged by their 2 n coordinates, 10 to spare with 9
FAINT_GRID_MIN = 9
#: their departure from the projective grid fitted to them (rms over the spare coordinates)
#: at most this many times their median precision (a blurred faint reseau over a texture:
#: 1.8; lattices of scene clutter or noise fitted so: 4.4-31)
FAINT_GRID_K = 2.5
#: their median precision at most this many times ``rules.max_sigma`` (fits to the noise of
#: a scan whose crosses are below detection: 1.8 px, a third of a pitch's blur: 12 px)
FAINT_GRID_SIGMA = 2.0
#: their fitted contrasts all of the marks' sign, their robust spread (1.4826 MAD) at most this
#: share of their median: the crosses of one reseau are alike (a faint reseau over a texture:
#: 0.26), fits to a plain photograph's texture or noise at a lattice's nodes are of either
#: sign (the spread of the 17 such lattices of plain sweep renders: 0.5-170)
FAINT_GRID_GAIN_SPREAD = 0.4


def grid_departure(film: np.ndarray, xy: np.ndarray) -> float:
    """The rms departure (px) of ``xy`` (n, 2) pixel system from the projective grid fitted
    to them from ``film`` (n, 2) mm, per spare coordinate (``2 n - 8``), n >= 5."""
    H = grid.projective_fit(film, xy)
    r = xy - grid.apply_h(H, film)
    return float(np.sqrt(np.sum(r * r) / max(2 * len(xy) - 8, 1)))


def alike_contrast(gain: np.ndarray, sign: int) -> bool:
    """Are the fitted contrasts ``gain`` (n,) grey units all of the marks' ``sign`` and
    alike (robust spread at most :data:`FAINT_GRID_GAIN_SPREAD` of their median)?"""
    g = sign * np.asarray(gain, float)
    if not (np.isfinite(g).all() and (g > 0).all()):
        return False
    med = float(np.median(g))
    return bool(1.4826 * np.median(np.abs(g - med)) <= FAINT_GRID_GAIN_SPREAD * med)


def _on_faint_grid(fine: Fine, film: np.ndarray, pred: np.ndarray, max_shift: float,
                   sign: int, rules: AcceptRules) -> float | None:
    """The fits ``fine`` (pixel system) of the crosses at ``film`` (n, 2) mm predicted at
    ``pred`` (n, 2) px, marks of ``sign``, as a grid: the factor their precision is raised
    by (>= 1), or None where they are no grid (a fit not finite or farther than ``max_shift``
    from its prediction, too imprecise, too little contrast, contrasts unlike each other,
    or off a projective grid)."""
    sig = fine.sigma
    if not (np.isfinite(fine.xy).all() and np.isfinite(sig).all()):
        return None
    if fine.gain is None or not alike_contrast(fine.gain, sign):
        return None
    if np.hypot(*(fine.xy - pred).T).max() > max_shift:
        return None
    s_med = float(np.median(sig))
    if not s_med <= FAINT_GRID_SIGMA * rules.max_sigma:
        return None
    if not float(np.median(np.nan_to_num(fine.cnr))) >= rules.min_cnr:
        return None
    ratio = grid_departure(film, fine.xy) / s_med
    return max(ratio, 1.0) if ratio <= FAINT_GRID_K else None


def faint_grid(scan, shape: MarkShape, pr: Prediction, inside: np.ndarray,
               rules: AcceptRules | None, m: Measurement) -> Measurement | None:
    """Measure the crosses ``inside`` (N,) bool the scan as a faint grid (module docstring),
    where the fits one by one (``m``) make no reseau: at least :data:`FAINT_GRID_MIN` of
    them, fitted with the shape ``shape`` (mark frame px) and the global model's affine
    ``pr.A`` held from the prediction ``pr`` (pixel system), accepted together where they
    lie on a projective grid (:func:`_on_faint_grid`); their covariances raised to the
    grid's departure. Returns the new :class:`Measurement` (``m``'s crosses outside the
    scan as they were), or None."""
    rules = rules or AcceptRules()
    idx = np.where(inside)[0]
    if idx.size < FAINT_GRID_MIN:
        return None
    fine = measure(scan, shape, pr.start[idx], pr.A[idx], pr.s0, pr.init_err, pr.sign, rules,
                   fit_shape=False, anchor=pr.xy[idx], max_shift=pr.max_shift)
    k = _on_faint_grid(fine, pr.film[idx], pr.xy[idx], pr.max_shift, pr.sign, rules)
    if k is None:
        return None
    cov = fine.cov * k * k
    cov_w = (fine.cov if fine.cov_white is None else fine.cov_white) * k * k
    xy, c, cw = m.xy.copy(), m.cov.copy(), m.cov_white.copy()
    score, cnr = m.score.copy(), m.cnr.copy()
    status, reason = list(m.status), list(m.reason)
    xy[idx], c[idx], cw[idx] = fine.xy, cov, cov_w
    score[idx], cnr[idx] = fine.score, fine.cnr
    for i in idx:
        status[i], reason[i] = "measured", ""
    fine.ok[:] = True
    fine.reason = [""] * idx.size
    fine.cov, fine.cov_white = cov, cov_w
    return Measurement(shape=shape, fitted=idx, fine=fine, scene_tv=fine.scene_tv, xy=xy,
                       cov=c, cov_white=cw, score=score, cnr=cnr, status=status,
                       reason=reason)
