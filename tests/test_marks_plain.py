"""Detection on scans of a second renderer (softplot.synthetic.plain), written apart from the one
the detector grew up with: supersampled bar coverage, a film response with the reseau's shadow
recorded sharp, defocus discs, clumped grain, OpenCV's JPEG, scenes of its own. Every figure a
user cannot know (arm length, line width, opacity, polarity, crop) is drawn independently of the
certificate. The full run is ``tools/sweep_plain.py`` (docs/accuracy.md)."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.camera import load_camera
from softplot.marks import grid
from softplot.synthetic.plain import _bars_cover, make_plain, run_plain, summarise

#: a sample of the independent scans: every camera, both polarities, RGB, 16 bit, JPEG,
#: crops, dark rows, a larger centre cross, a 23 x 47 aerial reseau at 120 dpi, unknown dpi
#: (seeds divisible by 3)
SAMPLE = (1, 2, 3, 5, 9, 12, 13, 15, 21, 22, 27, 29, 34, 37, 43, 47, 57, 58, 65)


def _overlap(i, lo, hi):
    return np.clip(np.minimum(i + 0.5, hi) - np.maximum(i - 0.5, lo), 0.0, None)


def test_coverage_is_exact():
    """The renderer's truth convention and its coverage integral: an upright cross's coverage
    of each pixel (pixel system, (0, 0) the centre of the top-left pixel) is the exact area
    of the two bars less their common square in that pixel; turned, the total area holds."""
    c = np.array([20.3, 18.7])
    L, w = 21.0, 1.7
    py, px = np.mgrid[0:40, 0:42].astype(float)
    cov = _bars_cover(px, py, c, 0.0, L, w, None)
    bar1 = _overlap(px, c[0] - L / 2, c[0] + L / 2) * _overlap(py, c[1] - w / 2, c[1] + w / 2)
    bar2 = _overlap(px, c[0] - w / 2, c[0] + w / 2) * _overlap(py, c[1] - L / 2, c[1] + L / 2)
    both = _overlap(px, c[0] - w / 2, c[0] + w / 2) * _overlap(py, c[1] - w / 2, c[1] + w / 2)
    assert np.abs(cov - (bar1 + bar2 - both)).max() < 1e-9
    for ang in (2.5, 7.0, 30.0):
        cov = _bars_cover(px, py, c, np.deg2rad(ang), L, w, None)
        assert abs(cov.sum() - (2 * L * w - w * w)) < 5e-3
        # a cross is symmetric under a half turn about its centre, and so is its coverage:
        # centred at pixel (20, 18), pixel (x, y) maps to (40 - x, 36 - y)
        d = _bars_cover(px, py, np.array([20.0, 18.0]), np.deg2rad(ang), L, w, None)
        assert np.abs(d[:37, :41] - d[36::-1, 40::-1]).max() < 1e-9


def test_overrides_change_only_what_they_name():
    a = make_plain(12, max_side=600)
    b = make_plain(12, max_side=600, negative=not a.params["negative"])
    assert b.params["negative"] != a.params["negative"]
    assert {k: v for k, v in a.params.items() if k != "negative"} == {
        k: v for k, v in b.params.items() if k != "negative"}
    with pytest.raises(ValueError, match="no figure"):
        make_plain(12, max_side=600, colour=1)


def test_spacing_ignores_peaks_found_twice():
    """A peak found twice at one place is not its own neighbour: the lattice's spacing, not
    0 (which made the dpi estimate divide by a singular lattice basis)."""
    xy = np.mgrid[0:4, 0:4].reshape(2, -1).T * 50.0
    twins = np.repeat(xy, 2, axis=0) + np.tile([[0.0, 0.0], [0.4, -0.3]], (len(xy), 1))
    assert grid.estimate_spacing(twins) == pytest.approx(50.0, abs=0.5)


def test_peaks_along_one_line_give_no_lattice_not_an_error():
    """Peaks along one row fix no second lattice direction; with a free scale (dpi unknown)
    the lattice fit used to invert a singular basis."""
    res = load_camera("pentax-645").reseau
    k = 30.0
    row = [[100 + i * 23 * k + d, 500.0 + d] for i in range(3) for d in (0.0, 0.3)]
    xy = np.array(row + [[400.0, 900.0], [1700.0, 130.0]])
    lat = grid.find_lattice(xy, np.ones(len(xy)), res, px_per_mm=k, scale_tol=None)
    if lat is not None:
        b = lat.B
        n = np.hypot(b[0], b[1])
        assert abs(np.linalg.det(b)) > 0.5 * n[0] * n[1]


@pytest.mark.parametrize("seed", [69, 87])
def test_unknown_dpi_on_small_grids(seed):
    """A 5 x 5 (Hasselblad) and a 3 x 3 (Pentax) scan without a dpi: the dpi estimate takes
    the lattice stage's candidates (scored by their arms) and scales in 3 % steps below the
    size-based guess; it used to give up ("cannot estimate the dpi") on both."""
    case, row = run_plain(seed, dpi_known=False)
    assert row["result"], row["error"]
    assert row["dpi_source"] == "estimated"
    assert abs(row["dpi"] / case.dpi - 1) < 0.005
    assert row["measured"] == row["visible"] and not row["wrong"] and not row["claimed"]


def test_independent_scans_sample():
    """The sample: every scan that shows 3 x 3 crosses gives a result, no wrong id, no claim,
    at least 98 % of the visible crosses measured, median error under 0.06 px (0.25 px on
    the aerial scan at 120 dpi, whose lines are 1 px wide), and honest covariances
    (normalised errors with an RMS within 0.75-1.4)."""
    rows = [run_plain(s)[1] for s in SAMPLE]
    s = summarise(rows)
    refused = [(r["seed"], r["error"]) for r in rows if r["expected"] and not r["result"]]
    assert not refused
    assert s["wrong"] == 0 and s["claimed"] == 0, s
    assert s["measured"] >= 0.98, s
    assert 0.75 <= s["z"] <= 1.4, s
    film = summarise([r for r in rows if r["camera"] != "aerial-23x47"])
    aerial = summarise([r for r in rows if r["camera"] == "aerial-23x47"])
    assert film["median_px"] < 0.06, film
    assert aerial["median_px"] < 0.25, aerial


def test_shadow_on_a_negative_is_not_taken_for_the_border():
    """Independent scan 118: a Rollei negative whose top row lies under a shadow (clear film,
    as bright as the unexposed border) that also covers half of the second row's crosses (not
    among the candidates). The crosses alone favoured the naming two rows off, which puts the
    format's edge on the shadow's; every cross came out two rows off. The format's edge the
    scan shows must decide: every measured cross with its own row and column."""
    case, row = run_plain(118)
    assert row["result"], row["error"]
    assert row["wrong"] == [] and row["claimed"] == []
    assert row["measured"] >= 0.9 * row["visible"]


def test_weak_peaks_on_the_nodes_are_not_missed_crosses():
    """Independent scan 279 (dpi estimated): a Rollei negative whose two bottom rows lie under
    a shadow as bright as the border. The lattice holds the shadow's crosses, but as peaks too
    weak to count as evidence; the naming counted their nodes as missed crosses, and the
    naming two rows up (its top rows outside the scan) won: 99 crosses two rows off. A weak
    peak on a node counts neither for a naming nor against it."""
    case, row = run_plain(279)
    assert row["result"], row["error"]
    assert row["wrong"] == [] and row["claimed"] == []
    assert row["measured"] >= 99


def test_crosses_beyond_the_format_count_against_a_naming():
    """Independent scan 128: a Rollei negative cropped at the top and the bottom, with a
    shadow as bright as the border over rows 7 and 8. The naming four rows down put its
    top rows outside the scan and the two rows below the shadow beyond its format, where the
    border's peaks count for nothing: all 77 crosses above the shadow came out four rows off.
    Crosses on the lattice more than a pitch beyond the format's edge count against it."""
    case, row = run_plain(128)
    assert row["result"], row["error"]
    assert row["wrong"] == [] and row["claimed"] == []
    assert row["measured"] >= 0.95 * row["visible"]


def test_format_edge_beside_a_bright_shadow_is_judged_on_the_film():
    """Independent scan 93 (dpi estimated): a Hasselblad negative whose three middle rows lie
    under a shadow as bright as the border; 10 crosses show, in the top and bottom rows. Two
    weak peaks in the shadow made it count as film, so the format's side edges, three fifths
    beside the shadow, showed no step, and the naming a column off (its outer column off the
    scan) won once weak peaks stopped counting as missed crosses. The edges are judged beside
    the film the counted crosses lie on: every cross the scan gives has its own row and col."""
    case, row = run_plain(93)
    assert row["wrong"] == [] and row["claimed"] == []
    if row["result"]:
        assert row["measured"] == row["visible"] == 10


def test_a_cross_the_noise_carries_through_black_is_not_invisible():
    """Independent scan 55: a cross inside a scene block that the sensor clips to black. The
    noise-free scan does not change there, but the stored one does: with the grain and the
    sensor's noise the film beside the lines is black in only about half its pixels, the
    lines in all, and the detector measures the cross within 0.3 px. The renderer counts it
    as faint (neither expected nor a claim), not as an invisible cross; the scan's
    every visible cross is measured and nothing is claimed."""
    case = make_plain(55)
    m = {t["name"]: t for t in case.truth["marks"]}["R3C4"]
    assert m["contrast"] < 0.005 and m["state"] == "faint"
    case, row = run_plain(55)
    assert row["claimed"] == [] and row["wrong"] == []
    assert row["measured"] == row["visible"] == 120


def test_lone_bars_of_a_low_resolution_aerial_frame_are_measured():
    """Independent scan 143: a 23 x 47 aerial reseau at 127 dpi with 95 one-armed crosses. A
    lone bar is measured where the neighbours predict the crosses to within 0.1 mm; that
    was judged on the prediction's spread after its 0.5 px floor, which alone is 0.1 mm at
    127 dpi, so no bar of such a scan was ever measured (86 of the 95 missed). Every lone bar
    is measured, across it as precisely as its covariance says, along it within it."""
    case = make_plain(143)
    lone = [t for t in case.truth["marks"] if t["arms"] == 1 and t["state"] == "visible"]
    case, row = run_plain(143)
    z = np.asarray(row["z_lone"]).reshape(-1, 2)  # (across, along) in sigmas
    assert len(lone) >= 90 and len(z) >= 0.97 * len(lone)
    assert np.sqrt(np.mean(z[:, 0] ** 2)) < 1.5
    assert np.abs(z[:, 1]).max() < 3.0
    s = summarise([row])
    assert s["lone"] == len(z) and abs(s["z_across"] - np.sqrt(np.mean(z[:, 0] ** 2))) < 1e-9


def test_a_whole_grid_decides_the_polarity():
    """Independent scan 231: a Hasselblad negative, 25 clear crosses on dense film inside a
    bright border full of grain. The border's bright peaks set the clutter level of the
    crosses' polarity so high that the whole grid scored 0.73, while 7 noise peaks of the other
    polarity on a lattice scored 4.97: the scan was read as a positive and four noise points
    were given as crosses 190 px off. A fit that holds the whole grid decides."""
    case, row = run_plain(231, dpi_known=True)
    assert row["result"], row["error"]
    assert row["wrong"] == [] and row["claimed"] == []
    assert row["measured"] == row["visible"] == 25


def test_unknown_dpi_on_noise_is_refused_in_one_line():
    """Without a dpi, a scan with no grid makes the estimate try every scale of both
    polarities: it must end in the one-line refusal, never in another error."""
    from softplot.io import Scan
    from softplot.marks import DetectionError, detect

    noise = np.random.default_rng(3).integers(0, 255, (900, 900)).astype(np.uint8)
    with pytest.raises(DetectionError, match="cannot estimate the dpi|no reseau"):
        detect(Scan.from_array(noise, dpi=None), "hasselblad-mk70")


def test_unknown_dpi_tries_the_second_polarity():
    """Independent scan 150 (a grainy Rollei colour negative without a dpi): no fit of the
    likelier polarity holds the whole grid, so the estimate goes on to the other polarity's
    candidates; the dpi within 0.5 %, every cross named right."""
    case, row = run_plain(150, dpi_known=False)
    assert row["result"], row["error"]
    assert abs(row["dpi"] / case.dpi - 1) < 0.005
    assert row["wrong"] == [] and row["claimed"] == []
