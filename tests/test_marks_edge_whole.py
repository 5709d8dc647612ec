"""Crosses the first prediction placed across the scan's edge, never fitted, that the measured
crosses' prediction places whole on the scan (:func:`softplot.marks.validation.edge_cut_part`
gives :data:`~softplot.marks.validation.EDGE_WHOLE`) are fitted whole by
:func:`~softplot.marks.validation.edge_crosses`; before, only a cross with one tip off the scan
was fitted (from its three other half-arms), and one with every tip on it never was."""

from __future__ import annotations

import numpy as np

from softplot.marks import validation
from softplot.marks.template import MarkShape
from softplot.marks.validation import EDGE_CUT_MAX, EDGE_WHOLE, edge_cut_part


def test_edge_cut_part_tells_whole_cut_and_lost_crosses():
    # crosses of 41 px (tip to tip) and 3 px lines at 20 px per mm, film x along pixel x and
    # film y along pixel -y, on a 400 x 300 px scan; the half-arm with the line's half width
    # reaches 22 px from the centre
    ppm, shape = 20.0, MarkShape("cross", length=41.0, width=3.0)
    ext = 0.5 * shape.length + 0.5 * shape.width
    J = np.tile(np.array([[ppm, 0.0], [0.0, -ppm]]), (5, 1, 1))
    xy = np.array([
        [ext + 1.0, 150.0],  # every tip a pixel in from the left edge (0.5 px): whole
        [ext + 0.5 - 0.2 * ext, 150.0],  # the -x tip out by a fifth of the half-arm
        [ext + 0.5 - (EDGE_CUT_MAX + 0.1) * ext, 150.0],  # out by more than allowed
        [ext - 1.0, ext - 1.0],  # a corner: two tips out
        [200.0, 150.0],  # the middle: whole
    ])
    part = edge_cut_part(xy, J, ppm, shape, 400, 300)
    # film -x is the mark frame's -u (2)
    assert part.tolist() == [EDGE_WHOLE, 2, -1, -1, EDGE_WHOLE]


def _r3c4(seed_renders, monkeypatch=None):
    """Sweep render 327 (a Rollei at 1486 dpi, a texture scene, the frame's left side off the
    scan): R3C4's tip 1.3 px inside the scan's edge, its first prediction's outside. Returns
    (status, error px, bound px, sigma px) of R3C4 and the render's score."""
    from softplot.synthetic.sweep import _bounds, make_case, render_case, run_case

    case = make_case(327)
    sc, det = run_case(case, cache=seed_renders)
    img, truth, scene, jr = render_case(case, seed_renders)
    t = next(m for m in truth["marks"] if m["name"] == "R3C4")
    assert t["state"] == "visible"
    i = det.name.index("R3C4")
    err = float(np.hypot(det.xy[i][0] - t["x"], det.xy[i][1] - t["y"]))
    return det.status[i], err, _bounds(case, truth, scene, jr)["R3C4"], det.sigma[i], sc


def test_sweep_cross_inside_the_edge_is_measured_whole(renders):
    status, err, bound, sigma, sc = _r3c4(renders)
    assert sc.result and sc.wrong == [] and sc.claimed == [] and sc.gross == []
    assert status == "measured"
    assert err <= 2.0 * bound, (err, bound)
    assert err <= 2.5 * float(np.max(sigma)), (err, sigma)


def test_sweep_cross_inside_the_edge_is_lost_without_the_whole_fit(renders, monkeypatch):
    # counterfactual: the whole crosses treated as the lost ones (-1), as before
    def cut_only(*a, **k):
        part = edge_cut_part(*a, **k)
        return np.where(part == EDGE_WHOLE, -1, part)

    monkeypatch.setattr(validation, "edge_cut_part", cut_only)
    status, *_ = _r3c4(renders)
    assert status != "measured"
