"""Lattice and identification of the reseau on scans that show few crosses among strong clutter,
parts of the grid, and rows made invisible: every cross with its own row and col, never a
silent guess (:mod:`softplot.marks.grid`)."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.camera import load_camera
from softplot.marks import grid


def _small_grid_points(seed, camera="hasselblad-mk70", rows=range(5), cols=range(5),
                       rot_deg=-3.5, dpi=412, clutter_score=(0.45, 0.86)):
    """Peaks of (a part of) a small reseau (pixel system) among clutter peaks as strong as the
    crosses (a textured scene, JPEG blocks; as many as the detector keeps, 100 more than
    three per cross): the crosses' peaks scatter by 0.7 px, each cross
    is found with a probability of 0.8. Returns (xy, score, reseau, size, ppm, node of each
    true peak)."""
    res = load_camera(camera).reseau
    ppm = dpi / 25.4
    th = np.radians(rot_deg)
    Rm = ppm * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]) @ np.diag([1, -1])
    rc = res.row_col()
    sel = np.isin(rc[:, 0], list(rows)) & np.isin(rc[:, 1], list(cols))
    rng = np.random.default_rng(seed)
    sel &= rng.uniform(size=len(sel)) < 0.8
    pix = res.film() @ Rm.T
    lo = pix[sel].min(0) - 0.6 * res.pitch_x * ppm
    pix = pix - lo
    size = tuple(int(v) for v in pix[sel].max(0) + 0.6 * res.pitch_x * ppm)
    true_xy = pix[sel] + rng.normal(0, 0.7, (sel.sum(), 2))
    n_clutter = 100 + 3 * res.count - sel.sum()
    clutter = rng.uniform(0, size, (n_clutter, 2))
    xy = np.vstack([true_xy, clutter])
    score = np.concatenate([rng.uniform(0.45, 0.9, sel.sum()),
                            rng.uniform(*clutter_score, n_clutter)])
    return xy, score, res, size, ppm, np.where(sel)[0]


@pytest.mark.parametrize("seed", range(6))
@pytest.mark.parametrize("camera,rot", [("hasselblad-mk70", -3.5), ("pentax-645", 179.0)])
def test_few_crosses_among_as_strong_clutter_are_all_on_the_lattice(seed, camera, rot):
    """A small grid (a 5 x 5 or a 3 x 3, a fifth of its crosses not among the peaks) among
    10-20 times as many clutter peaks scoring as high as the crosses: the lattice takes the
    crosses that agree with it, not a median that is clutter's. Every cross found is on it
    with its row and col (the whole grid shown, so no shift is possible), no clutter peak
    is taken for a cross."""
    xy, score, res, size, ppm, nodes = _small_grid_points(seed, camera, rot_deg=rot)
    g = grid.fit_grid(xy, score, res, size, px_per_mm=ppm, rotate_deg=180.0 if rot > 90 else 0,
                      scale_tol=0.03, part=(0, res.cols, 0, res.rows))
    assert g is not None
    got = dict(zip(g.index.tolist(), g.node.tolist(), strict=True))
    true = {k: v for k, v in got.items() if k < len(nodes)}
    assert all(true[k] == nodes[k] for k in true), "a cross with the wrong row/col"
    assert len(true) >= len(nodes) - 1
    # a clutter peak may stand in only where the cross is not among the peaks
    assert not set(v for k, v in got.items() if k >= len(nodes)) & set(nodes.tolist())


def _named(det, truth):
    """(right, wrong, claimed, visible) of a detection against its truth: a measured cross
    more than 1 px from its own truth is wrong."""
    tm = {m["name"]: m for m in truth["marks"]}
    right = wrong = claimed = 0
    for i, n in enumerate(det.name):
        if det.status[i] != "measured":
            continue
        t = tm[n]
        if t["state"] != "visible":
            claimed += 1
        elif np.hypot(*(det.xy[i] - (t["x"], t["y"]))) > 1.0:
            wrong += 1
        else:
            right += 1
    return right, wrong, claimed, sum(m["state"] == "visible" for m in truth["marks"])


@pytest.mark.parametrize("seed,crop,rot", [
    (1, (0.0, 118.0, 232.0, 0.0), 0.7),     # bottom-left quarter
    (2, (236.0, 0.0, 0.0, 118.0), -1.2),    # top-right quarter
])
def test_a_quarter_of_a_large_grid_is_named_from_its_one_edge_per_axis(seed, crop, rot):
    """A quarter of the 23 x 47 aerial reseau: on each axis the scan shows one edge of the
    format, the film fills most of it (its grey range is the film's: a low-contrast frame
    with a thin border), so the border's step is many times that range. Counted at most one
    step per edge, the edge still tells the right columns from the 11 other shifts that
    fit the crosses alike: every cross with its own row and col."""
    from softplot.io import Scan
    from softplot.marks import detect
    from softplot.synthetic import ScanSpec, render_scan

    spec = ScanSpec(dpi=300, crop_mm=crop, rotation_deg=rot, contrast=0.2,
                    mark_width_scale=1.4, scene="none")
    img, truth = render_scan("aerial-23x47", spec, seed)
    det = detect(Scan.from_array(img, dpi=300), "aerial-23x47")
    right, wrong, claimed, visible = _named(det, truth)
    assert (wrong, claimed) == (0, 0)
    assert right >= 0.98 * visible


@pytest.fixture(scope="module")
def dark_top():
    """A Rollei scan cut through the bottom rows and the right columns whose top row lies
    under a flat black region (a sky) reaching over the format's edge into the border: the
    dark region's edge looks like the format's."""
    from softplot.synthetic import ScanSpec, render_scan

    spec = ScanSpec(dpi=600, crop_mm=(0, 0, 19, 19), rotation_deg=0.5, dark_rows=((0, 0),),
                    dark_level=0.0)
    return render_scan("rollei-6006", spec, 2)


def test_a_dark_region_over_the_only_edge_row_is_given_but_said_ambiguous(dark_top):
    """Which row is the top one the scan cannot tell: the crosses are returned (never a
    refusal), ``ids_ambiguous`` is true in the result and its JSON, and one warning says
    the rows and columns are ambiguous; nothing is claimed where no cross shows."""
    from softplot.io import Scan
    from softplot.marks import detect

    img, truth = dark_top
    det = detect(Scan.from_array(img, dpi=600), "rollei-6006")
    assert det.measured.sum() >= 40
    assert det.ids_ambiguous and det.to_json()["ids_ambiguous"] is True
    said = [w for w in det.warnings if "ambiguous" in w]
    assert len(said) == 1 and "\n" not in said[0] and "--grid-part" in said[0]


def test_a_dark_row_inside_the_part_leaves_the_naming_certain():
    """The same crop with a black region over a middle row instead: the top row and the
    format's edge show, so the naming is certain and right."""
    from softplot.io import Scan
    from softplot.marks import detect
    from softplot.synthetic import ScanSpec, render_scan

    spec = ScanSpec(dpi=600, crop_mm=(0, 0, 19, 19), rotation_deg=0.5, dark_rows=((3, 3),),
                    dark_level=0.0)
    img, truth = render_scan("rollei-6006", spec, 2)
    det = detect(Scan.from_array(img, dpi=600), "rollei-6006")
    right, wrong, claimed, visible = _named(det, truth)
    assert not det.ids_ambiguous and det.to_json()["ids_ambiguous"] is False
    assert wrong == 0 and right >= visible - 1


@pytest.mark.parametrize("seed", range(3))
def test_the_centres_win_over_a_lattice_of_weaker_peaks_along_long_arms(seed):
    """Long crosses give weaker correlation peaks along their arms, at the same offset from
    every centre and about as many: that lattice agrees with as many nodes as the centres'
    does; the centres, scoring higher, must be the lattice."""
    xy, score, res, size, ppm, nodes = _small_grid_points(seed, "rollei-6006", rot_deg=4.8,
                                                          dpi=1200)
    n = len(nodes)
    rng = np.random.default_rng(seed)
    arm = xy[:n] + np.array([0.3 * res.pitch_x * ppm, 0.0]) + rng.normal(0, 0.7, (n, 2))
    xy = np.vstack([xy, arm])
    score = np.concatenate([score[:n] + 0.1, score[n:], rng.uniform(0.3, 0.5, n)])
    lat = grid.find_lattice(xy, score, res, px_per_mm=ppm, rotate_deg=0.0, scale_tol=0.03)
    assert lat is not None
    assert np.sum(lat.cand < n) >= 0.9 * n  # the centres, not the arms' peaks


@pytest.mark.parametrize("seed", [
    1,   # plate, quarter frame, half turn: the format's edge runs one pitch beyond the last row
    56,  # Rollei quarter frame at 334 dpi: crosses cut by the scan's edge
    72,  # Rollei half frame, web copy: a peak on the border beyond the format's corner
    91,  # Hasselblad whole frame at 205 dpi, its top row under a black sky
    130,  # plate at 399 dpi: its top row under a black sky, peaks along the bottom edge
    131,  # aerial part: a wrong naming puts rows on the border, where no cross would show
])
def test_sweep_renders_are_named_from_their_crosses_and_the_formats_edge(seed):
    """Renders of the robustness sweep that show their rows and columns (an end row and
    column with the format's edge beyond it) and came out shifted by whole rows or columns:
    a row of correlation peaks along the format's edge (scoring like the clutter) or a
    peak on the border beyond a corner is no cross, for a naming or against it; a cross
    under a flat dark region, or nearer the scan's edge than the correlation reaches, is
    no missed cross; the format's edge decides between the namings the crosses leave.
    Every measured cross with its own row and col, nothing claimed where no cross shows."""
    from softplot.synthetic.sweep import make_case, run_case

    sc, det = run_case(make_case(seed))
    assert sc.result and not sc.ambiguous_truth
    assert sc.wrong == [] and sc.claimed == []
    assert sc.measured >= 0.9 * sc.visible


@pytest.mark.parametrize("seed", [
    273,  # Rollei quarter frame, half turn, busy colour negative: the end column's crosses
          # barely show (6 of 7 not among the candidates), the format's edge beyond it does
    512,  # plate quarter frame at 245 dpi, half turn: a row of peaks along the format's edge
          # one pitch beyond the last row, the edge itself a low-contrast step
    519,  # Rollei quarter frame over a busy scene: dark rows hide most of the format's edge
])
def test_sweep_renders_named_by_the_formats_edge_over_faint_end_crosses(seed):
    """Renders of the robustness sweep that came out named a column (or two rows) off: the
    crosses alone favour the wrong naming by up to three crosses' evidence (the end column's
    crosses missing from the candidates count as missed), while the format's edge the scan
    shows lies where only the right naming puts it. Every cross given with its own row and
    col, nothing claimed where no cross shows."""
    from softplot.synthetic.sweep import make_case, run_case

    sc, det = run_case(make_case(seed))
    assert sc.result and not sc.ambiguous_truth
    assert sc.wrong == [] and sc.claimed == []
    assert sc.measured >= 0.7 * sc.visible


@pytest.mark.parametrize("seed", [
    362,  # Hasselblad half frame over a busy colour negative: a scratch on the border beyond
          # the format's edge gives the lattice an end column of strong peaks
    345,  # Hasselblad whole frame, its bottom row under a black band: not one cross there
          # measured, and the naming is right
])
def test_a_naming_moves_off_an_end_column_of_peaks_beyond_the_formats_edge(seed):
    """A lattice whose outermost column is scene content on the film's border (none of its
    crosses holds at full resolution, though they would lie whole in the scan) is named one
    column off by the candidates; where the format's edge of the naming moved off that
    column shows, and the column the move names anew lies off the scan, the naming moves:
    every cross with its own row and col, none refused, nothing claimed. An outer row under
    a flat dark band (no format's edge where the moved naming puts it) keeps its naming."""
    from softplot.synthetic.sweep import make_case, run_case

    sc, det = run_case(make_case(seed))
    assert sc.result, sc.error
    assert not sc.ambiguous_truth
    assert sc.wrong == [] and sc.claimed == [] and sc.gross == []
    assert sc.measured >= 0.9 * sc.visible


def test_a_few_peaks_of_the_other_polarity_do_not_keep_the_reseau_from_being_fitted():
    """Sweep render 233, a busy 3 x 3 Pentax turned a quarter: the bright peaks give a
    lattice of 3 clutter peaks that scores above what the dark crosses' candidates could
    bound; a fit too small to be a reseau must neither stop the dark polarity from being
    fitted nor win over it. All 9 crosses with their own rows and columns."""
    from softplot.synthetic.sweep import make_case, run_case

    sc, det = run_case(make_case(233))
    assert sc.result and sc.wrong == [] and sc.claimed == []
    assert sc.measured == sc.visible == 9


def test_no_cross_is_measured_again_where_a_black_region_leaves_no_contrast():
    """Sweep render 15: an aerial quarter frame whose rows 2-7 lie under a region that
    exposes nothing (8 bit, the noise quantised away: a flat grey). A cross refused there
    and fitted again from its neighbours' prediction fits no contrast with a contrast to
    noise of a hundred; a cross is measured again only with a tenth of the measured crosses'
    contrast: no whole cross is claimed where none shows, and no lone bar either (a bar of
    no contrast there has a contrast to noise of 41)."""
    from softplot.synthetic.sweep import make_case, run_case

    sc, det = run_case(make_case(15))
    assert sc.result and sc.wrong == []
    assert sc.claimed == []
    assert sc.measured >= 0.98 * sc.visible
