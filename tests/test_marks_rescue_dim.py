"""The rescue of refused crosses (:func:`softplot.marks.validation.rescue`) on a faint scan:
a faint cross is judged as the first pass judges it, and its precision at its peers'
contrast (:func:`softplot.marks.validation.at_peers`)."""

from __future__ import annotations

import numpy as np

from softplot.marks.validation import RESCUE_MIN_GAIN, at_peers


def test_precision_is_taken_to_the_peers_contrast_within_limits():
    g = np.array([-0.05, -0.2, -0.4, -0.8, np.nan])
    f = at_peers(g, 0.4)
    # half the contrast: twice the sigma, judged as the peers' half of it; never below
    # RESCUE_MIN_GAIN (no contrast at all is no cross) and never above 1 (a stronger fit is
    # not held to more than its peers' precision)
    assert np.allclose(f, [0.125, 0.5, 1.0, 1.0, RESCUE_MIN_GAIN])
    assert at_peers(g, None) == 1.0


def test_a_faint_cross_of_a_low_contrast_scan_is_rescued_near_its_truth():
    # the robustness sweep's seed 192: a Hasselblad at 648 dpi, contrast 0.06, 16 bit. R0C3
    # was refused as "contrast too low" (contrast-to-noise 2.7, matched-filter
    # signal-to-noise 8.6: a faint cross the first pass accepts among its peers); its rescue
    # fits held no faint cross and judged its precision, 2.2-2.4 times the peers' at 0.45
    # of their contrast, as a fit on conflicting content: 24 of 25 measured
    from softplot.synthetic.sweep import make_case, render_case, run_case

    case = make_case(192)
    sc, det = run_case(case)
    assert not sc.wrong and not sc.claimed and not sc.gross
    assert sc.measured == sc.visible == 25, sc.missed
    _, truth, _, _ = render_case(case)
    t = next(m for m in truth["marks"] if m["name"] == "R0C3")
    i = det.name.index("R0C3")
    err = float(np.hypot(*(det.xy[i] - (t["x"], t["y"]))))
    # its bound is 0.21 px: measured from three of its half-arms 0.58 px off, far from a
    # fit on the texture (1-5 px off) and within its own reported precision
    assert err < 0.75, err
    e = det.xy[i] - (t["x"], t["y"])
    z = float(np.sqrt(e @ np.linalg.solve(det.cov[i], e) / 2))
    assert z < 2.0, z


def test_a_dim_cross_the_scan_edge_cuts_is_measured_near_its_truth():
    # the robustness sweep's seed 413: a Rollei at 455 dpi, JPEG q44, opacity 0.68. R8C6,
    # cut by the scan's edge by one tip, was fitted from its other three half-arms 0.14 px
    # from its truth (bound 0.18 px) at 0.37 of its peers' contrast, and refused: its
    # sigma was 3.2 times the measured crosses' median (at their contrast 1.2 times)
    from softplot.synthetic.sweep import make_case, render_case, run_case

    case = make_case(413)
    sc, det = run_case(case)
    assert not sc.wrong and not sc.claimed and not sc.gross
    assert not any(m.startswith("R8C6:") for m in sc.missed), sc.missed
    _, truth, _, _ = render_case(case)
    t = next(m for m in truth["marks"] if m["name"] == "R8C6")
    i = det.name.index("R8C6")
    e = det.xy[i] - (t["x"], t["y"])
    assert float(np.hypot(*e)) < 0.4, e
    z = float(np.sqrt(e @ np.linalg.solve(det.cov[i], e) / 2))
    assert z < 2.0, z
