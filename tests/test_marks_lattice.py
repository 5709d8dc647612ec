"""The lattice stage: a scan that shows a consistent part of the reseau gives a lattice
(never "no regular pattern" or "found only N on a lattice"), and the grid's scale and
rotation are judged where its crosses are."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.camera import load_camera
from softplot.marks import grid


@pytest.mark.parametrize("seed", range(6))
def test_a_corner_block_of_a_large_reseau_keeps_its_scale(seed):
    """A 3 x 5 block at the corner of the 23 x 47 aerial reseau, peaks a few pixels off
    (an overview's error): the projective model through them extrapolates its perspective
    to the grid's far-away centre; the scale is checked where the crosses are."""
    res = load_camera("aerial-23x47").reseau
    film, rc = res.film(), res.row_col()
    ppm = 2583 / 25.4
    sel = np.where((rc[:, 1] <= 2) & (rc[:, 0] >= 18))[0]
    th = np.radians(-2.4)
    A = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]) @ np.diag([ppm, -ppm])
    rng = np.random.default_rng(seed)
    pix = film[sel] @ A.T + [-film[sel][:, 0].min() * ppm + 600,
                             film[sel][:, 1].max() * ppm + 500]
    pix += rng.normal(0.0, 5.0, pix.shape)
    g = grid.fit_grid(pix, np.full(len(pix), 0.75), res, (4400, 5600), px_per_mm=ppm,
                      rotate_deg=0.0, scale_tol=0.03)
    assert g is not None
    assert len(g.node) == len(sel)
    assert abs(g.px_per_mm / ppm - 1.0) < 0.01
    assert abs(g.rotation_deg + 2.4) < 0.5
    # the block's shape: 3 columns by 5 rows, every cross once
    r, c = np.divmod(g.node, res.cols)
    assert (np.ptp(c), np.ptp(r)) == (2, 4)
    assert len(set(g.node.tolist())) == len(sel)


def _box(img, x0, y0, x1, y1, v):
    img[y0:y1, x0:x1] = v


def test_arm_evidence_tells_a_cross_from_corners_edges_blobs_and_block_corners():
    """The coarse stage's arm test: a faint cross shows its arms; a bright block's corner, a
    step edge, a blot larger than the arms and the corner of JPEG-like 8 x 8 blocks (all
    stronger than the cross) show none; a single bar (a one-armed cross) shows at half
    weight."""
    import cv2

    from softplot.marks.candidates import arm_evidence

    img = np.full((160, 320), 0.4, np.float32)
    cv2.line(img, (20, 30), (60, 30), 0.5, 1)  # a faint bright cross at (40, 30)
    cv2.line(img, (40, 10), (40, 50), 0.5, 1)
    _box(img, 100, 30, 160, 80, 0.9)  # a bright block: corner at (100, 30)
    _box(img, 200, 0, 320, 60, 0.8)  # a step edge at x = 200, through (200, 30)
    cv2.circle(img, (260, 110), 12, 0.9, -1)  # a blot larger than the arms
    rng = np.random.default_rng(1)
    for by in range(88, 152, 8):  # 8 x 8 blocks of random levels: a corner at (40, 120)
        for bx in range(8, 72, 8):
            _box(img, bx, by, bx + 8, by + 8, rng.uniform(0.2, 0.8))
    cv2.line(img, (120, 130), (170, 130), 0.5, 1)  # one bar, centre (145, 130)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    pts = np.array([[40, 30], [100, 30], [200, 30], [260, 110], [40, 120], [145, 130]],
                   float)
    ev = arm_evidence(img, pts, +1, arm_half=8.0, width=1.0, s=0.7)
    cross, corner, edge, blob, block, bar = ev
    assert cross > 0.05
    assert max(corner, edge, blob, block) < 0.25 * cross
    assert 0.25 * cross < bar < 0.75 * cross
    # dark crosses: the sign turns the evidence round
    assert arm_evidence(1.0 - img, pts[:1], -1, 8.0, 1.0, 0.7)[0] == pytest.approx(cross)


def test_arm_evidence_read_in_chunks_is_the_same(monkeypatch):
    """Points read a chunk at a time (a bounded working set) give each point the evidence
    it has read alone or among all, to the precision of the bilinear reads (OpenCV's remap
    interpolates at 1/32 px, on float32 coordinates of the stacked windows); points outside
    the image stay -inf."""
    from softplot.marks import candidates

    rng = np.random.default_rng(3)
    img = rng.uniform(0.3, 0.6, (90, 120)).astype(np.float32)
    pts = np.column_stack([rng.uniform(-5, 125, 50), rng.uniform(-5, 95, 50)])
    whole = candidates.arm_evidence(img, pts, +1, 8.0, 1.0, 0.7)
    monkeypatch.setattr(candidates, "ARM_CHUNK", 7)
    chunked = candidates.arm_evidence(img, pts, +1, 8.0, 1.0, 0.7)
    alone = np.array([candidates.arm_evidence(img, p[None], +1, 8.0, 1.0, 0.7)[0]
                      for p in pts])
    inside = (pts[:, 0] >= 0) & (pts[:, 0] < 120) & (pts[:, 1] >= 0) & (pts[:, 1] < 90)
    assert np.isfinite(whole).sum() == inside.sum() > 30
    fin = np.isfinite(whole)
    assert np.array_equal(fin, np.isfinite(chunked)) and np.array_equal(fin, np.isfinite(alone))
    assert np.abs(whole[fin] - chunked[fin]).max() < 1e-4
    assert np.abs(whole[fin] - alone[fin]).max() < 1e-4


@pytest.mark.parametrize("seed", [10, 37])
def test_a_3x3_reseau_over_a_busy_scene_is_not_refused(seed):
    """Pentax 645 (3 x 3 crosses) over a busy scene, half-turned: faint crosses correlate no
    better than the scene's corners and edges, and more of those than a lattice takes
    used to crowd the crosses out ("found only 5 on a lattice"). Every visible cross is
    measured with its right row and column."""
    from softplot.synthetic.sweep import make_case, run_case

    case = make_case(seed)
    assert case.camera == "pentax-645" and "busy" in case.conditions
    sc, det = run_case(case)
    assert sc.result, sc.error
    assert not sc.wrong and not sc.claimed
    assert sc.measured == sc.visible >= 8


@pytest.mark.parametrize("camera,scene,seed,dpi", [
    ("rollei-6006", "texture", 1, 300),
    ("rollei-6006", "busy", 1, 300),
    ("hasselblad-mk70", "texture", 1, 300),
    ("pentax-645", "busy", 1, 300),
])
def test_a_photograph_without_a_reseau_is_refused(camera, scene, seed, dpi):
    """A plain photograph (the scene, no crosses; its texture may fall on the reseau's
    lattice at many nodes by chance): refused in one line, never given a grid, however the
    candidates are scored."""
    from softplot.io import Scan
    from softplot.marks import DetectionError, detect
    from softplot.synthetic import ScanSpec, render_scan

    img, _ = render_scan(camera, ScanSpec(dpi=dpi, scene=scene), seed, marks=False)
    with pytest.raises(DetectionError, match="no reseau found") as exc:
        detect(Scan.from_array(img, dpi=dpi), camera)
    assert "\n" not in str(exc.value)


def test_a_format_edge_half_hidden_by_dark_rows_still_names_the_grid():
    """The film's left edge (at x = 40 overview px) shows over 42 % of its length; a band of
    flat dark rows, as dark as the border, hides the rest. The naming that puts the format's
    left edge there must outscore the one a pitch further left (its left edge outside the
    scan, its other edges on the same steps): the median step along the whole edge is the
    dark band's (none), so the edge is read where the film inside it could show."""
    from softplot.marks.lattice import frame_evidence

    rng = np.random.default_rng(3)
    H, W = 300, 400
    g = np.full((H, W), 0.05, np.float32)  # unexposed border (a positive: dark)
    g[30:271, 40:] = 0.6 + 0.1 * rng.standard_normal((241, W - 40))  # film, textured
    g[80:221, :] = 0.05  # dark rows over the film's middle, left edge included
    g += 0.01 * rng.standard_normal(g.shape).astype(np.float32)
    xs = np.arange(80, 400, 40.0)
    found = np.array([(x, y) for x in xs for y in (50.0, 250.0)])  # crosses on the film
    truth = np.array([[40, 30], [500, 30], [500, 270], [40, 270]], float)
    left = truth - [40.0, 0.0]  # a pitch (4 mm at 10 px/mm) further left
    ev = frame_evidence(g, 1, 10.0, 4.0)(np.stack([truth, left]), found)
    # the true left edge's step (0.55 over a grey range of about 0.6) less FRAME_STEP, over 4
    assert ev[0] > ev[1] + 0.1
