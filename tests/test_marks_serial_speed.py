"""Speed-ups of the detection's serial stages that must not change a result
(softplot.marks.grid, softplot.marks.neighbours): each against the computation it replaces."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from softplot.marks import grid, neighbours


def _top_cells_pairwise(Hs, k):
    """The lattice search's cell picking as it was: each cell tested against every pick."""
    nb = Hs.shape[1]
    order = np.argsort(-Hs.ravel(), kind="stable")[: max(64 * k, 256)]
    picked = []
    for f in order:
        a, u, v = np.unravel_index(int(f), Hs.shape)
        close = False
        for a2, (u2, v2) in picked:
            du = min(abs(u - u2), nb - abs(u - u2))
            dv = min(abs(v - v2), nb - abs(v - v2))
            if abs(a - a2) <= 1 and du <= 1 and dv <= 1:
                close = True
                break
        if not close:
            picked.append((int(a), (int(u), int(v))))
            if len(picked) == k:
                break
    return picked


@pytest.mark.parametrize("seed", range(6))
def test_top_cells_pick_as_the_pairwise_test(seed):
    """The blocked neighbourhoods pick the cells (ties included: integer histograms) that
    testing every cell against every pick picks, in the same order; with few rotations the
    picks run out before ``k`` as they did."""
    rng = np.random.default_rng(seed)
    A = (3, 40, 7, 1, 25, 90)[seed]
    Hs = rng.integers(0, 6, (A, grid.PHASE_BINS, grid.PHASE_BINS)).astype(float)
    Hs[rng.integers(0, A), 3, 15] = 50.0  # a peak at the circular edge of the phase
    for k in (1, 5, 24, 200):
        want = _top_cells_pairwise(Hs, k)
        assert grid._top_cells(Hs, k) == want
    if A <= 7:  # few rotations: the picks ran out before k (that case is covered)
        assert len(want) < 200


def test_nearest_is_the_trees_query_kept_by_the_points_values():
    """The neighbours' query is cKDTree's (ties on a regular grid in the tree's order), kept
    by the values of the points: asked again it is the same result, with one point moved a
    new one, and past NEAREST_KEPT other queries the first is computed again."""
    film = np.stack(np.meshgrid(np.arange(11.0), np.arange(11.0)), -1).reshape(-1, 2) * 5.0
    q, m = film, film[1:]
    d0, j0 = cKDTree(m).query(q, k=17)
    d, j = neighbours.nearest(q, m, 17)
    assert np.array_equal(d, d0) and np.array_equal(j, j0)
    assert neighbours.nearest(q.copy(), m.copy(), 17)[1] is j  # kept: the values decide
    moved = m.copy()
    moved[40] += 0.3
    d2, j2 = neighbours.nearest(q, moved, 17)
    want = cKDTree(moved).query(q, k=17)
    assert np.array_equal(d2, want[0]) and np.array_equal(j2, want[1])
    assert not np.array_equal(d2, d)
    for i in range(neighbours.NEAREST_KEPT):
        neighbours.nearest(q[: 10 + i], m, 5)
    again = neighbours.nearest(q, m, 17)
    assert again[1] is not j and np.array_equal(again[1], j0)
    with pytest.raises(ValueError):
        d[0, 0] = 1.0  # read-only: a caller cannot change what the next one gets


def test_overview_grey_range_once_per_overview():
    """frame_evidence and seeable of one overview share its grey and 5-95 % points (computed
    once), give what they gave computing them each, and another overview gets its own."""
    from softplot.marks import coarse, lattice

    rng = np.random.default_rng(3)
    q = rng.integers(0, 200, (300, 400)).astype(np.uint8)
    q[:, :40] = 250  # a bright border: an edge for the evidence
    ov = coarse.Overview(q, 1.0 / 255.0)
    g, lo, hi = lattice._grey_range(ov)
    assert lattice._grey_range(ov)[0] is g  # kept
    sub = ov[:, :][::1, ::1]
    assert np.array_equal(g, sub)
    assert (lo, hi) == tuple(np.percentile(g[:: 300 // 256, :: 400 // 256], [5, 95]))
    corners = np.array([[[160.0, 40.0], [1500.0, 40.0], [1500.0, 1100.0], [160.0, 1100.0]]])
    ev = lattice.frame_evidence(ov, 4, 10.0, 5.0)(corners)
    lattice._GREY.clear()  # computed afresh: the same evidence
    assert np.array_equal(lattice.frame_evidence(ov, 4, 10.0, 5.0)(corners), ev)
    other = coarse.Overview(np.full((300, 400), 30, np.uint8), 1.0 / 255.0)
    g2, lo2, hi2 = lattice._grey_range(other)
    assert g2 is not g and lo2 == hi2 == float(g2[0, 0]) and lo2 != lo


@pytest.mark.parametrize("shape", [(1, 53, 53), (6, 61, 61), (20, 51, 51), (3, 5, 29)])
def test_patch_gradients_are_each_patchs_own(shape):
    """The joint scene's prior weights take the patches' gradients in one Sobel over the
    stacked patches: bit for bit each patch's own (its border reflected), not its neighbour's
    in the stack."""
    from softplot.marks import measure

    rng = np.random.default_rng(shape[0])
    B = rng.normal(0.5, 0.2, shape).astype(np.float32)
    B[:, :2] += 0.4  # an edge at every patch's top: its neighbour's bottom differs
    want = np.stack([measure._grad_magnitude(b) for b in B])
    assert np.array_equal(measure._patch_gradients(B), want)


def test_a_deferred_polarity_gives_the_lattice_of_both_scored():
    """On a render of dark crosses the bright sign's correlations bound its lattice below the
    dark sign's: it is not scored by its arms, and the lattice stage never scores it (the
    dark lattice beats its bound). The lattice is the one found with both signs scored, to
    the last bit, and the bright sign's bound, once scored, lies below what deferred it."""
    from softplot.camera import load_camera
    from softplot.io import Scan
    from softplot.marks.candidates import reseau_candidates
    from softplot.marks.lattice import fit_lattice
    from softplot.marks.overview import reseau_overview
    from softplot.marks.template import cross_shape
    from softplot.synthetic import ScanSpec, render_scan

    cam = load_camera("rollei-6006")
    img, _ = render_scan(cam, ScanSpec(dpi=600.0, rotation_deg=1.5, scene="busy"), seed=5)
    sc = Scan.from_array(img, dpi=600.0)
    ppm = 600.0 / 25.4
    ov = reseau_overview(sc, cross_shape(cam, ppm).width, ppm, "scan")
    lazy = reseau_candidates(sc, ov, cam, "auto", 1.0)
    assert set(lazy.deferred) == {1} and set(lazy.peaks) == {-1}
    upper = lazy.deferred[1][0]
    got = fit_lattice(sc, ov, lazy, cam, "auto", 0.0)
    assert 1 in lazy.deferred  # never scored: the dark lattice beat its bound
    full = reseau_candidates(sc, ov, cam, "auto", 1.0).complete()
    assert set(full.peaks) == {1, -1} and not full.deferred
    assert full.bound[1] <= upper < full.bound[-1]
    want = fit_lattice(sc, ov, full, cam, "auto", 0.0)
    assert got.sign == want.sign == -1
    assert np.array_equal(got.grid.H, want.grid.H)
    assert np.array_equal(got.grid.node, want.grid.node) and got.grid.score == want.grid.score


def test_patches_are_nan_exactly_off_the_scan():
    """The windows start uninitialised: the ones wholly inside are gathered whole, the others
    NaN where they leave the scan (also wholly outside) and the scan's grey elsewhere."""
    from softplot.io import Scan
    from softplot.marks.measure import patches

    rng = np.random.default_rng(7)
    img = rng.integers(0, 255, (90, 120)).astype(np.uint8)
    sc = Scan.from_array(img, dpi=1000.0)
    centres = np.array([[60.0, 45.0], [2.0, 3.0], [118.4, 88.6], [-40.0, 10.0], [30.0, 20.0]])
    for _ in range(3):  # reused memory must not show through
        stack, origin = patches(sc, centres, 6)
        g = sc.grey()
        for w, (x0, y0) in zip(stack, origin.astype(int), strict=True):
            ys, xs = np.mgrid[y0 : y0 + 13, x0 : x0 + 13]
            on = (xs >= 0) & (xs < 120) & (ys >= 0) & (ys < 90)
            assert np.isnan(w[~on]).all()
            assert np.array_equal(w[on], g[ys[on], xs[on]])


def _cross_grid_scan(rough=(), side=6, pitch=64, seed=0):
    """An 8-bit scan (pixel system) of ``side`` x ``side`` dark crosses (length 24, width
    1.2 px, blur 1 px) every ``pitch`` px over a flat grey with noise; the crosses ``rough``
    (row-major indices) over a strong texture (a period of 40 px). Returns the scan, the
    crosses' centres (N, 2) and their shape."""
    from softplot.io import Scan
    from softplot.marks.template import MarkShape, render

    shape = MarkShape("cross", length=24.0, width=1.2)
    rng = np.random.default_rng(seed)
    size = side * pitch
    img = 180.0 + rng.normal(0.0, 2.0, (size, size))
    half = 20
    mark = render(shape, 1.0, half=half)
    y, x = np.mgrid[0 : 2 * half + 1, 0 : 2 * half + 1]
    tex = 40.0 * np.sin(2 * np.pi * x / 40.0) * np.cos(2 * np.pi * y / 40.0)
    c = []
    for i in range(side * side):
        cx, cy = pitch // 2 + pitch * (i % side), pitch // 2 + pitch * (i // side)
        win = img[cy - half : cy + half + 1, cx - half : cx + half + 1]
        if i in rough:
            win += tex
        win -= 120.0 * mark
        c.append((cx, cy))
    sc = Scan.from_array(np.clip(img, 0, 255).astype(np.uint8), dpi=1200.0)
    return sc, np.array(c, float), shape


@pytest.mark.parametrize("rough", [(), (0,), (3,), (5,), (17,), (35,), (2, 30)])
def test_flat_scan_judges_as_all_patches_at_once_and_stops_at_the_first_rough(rough,
                                                                               monkeypatch):
    """flat_scan's verdict is that of every patch judged at once (each patch's opening and
    plane are its own); its chunks start small and grow, so on a busy scan the first rough
    patch ends the test after a few openings (a first chunk of 32 computed 32)."""
    from softplot.marks import measure

    sc, c0, shape = _cross_grid_scan(rough)
    A0 = np.broadcast_to(np.eye(2), (len(c0), 2, 2))
    s0, init_err, sign = 1.0, 0.5, -1
    stack, origin = measure.patches(sc, c0, measure._half(shape, A0, s0, init_err))
    bg, _, _ = measure.scene_background(stack, shape, s0, sign)
    away = measure._away_from_centre(origin, c0, A0, shape, s0, init_err, stack.shape)
    flat = measure.plane_scenes(stack, bg, away, 1.0 / sc.full_scale)[0]
    assert np.array_equal(~flat, np.isin(np.arange(len(c0)), rough))  # the scan as drawn
    read = []
    real = measure.patches

    def spy(scan, centres, half):
        read.append(len(centres))
        return real(scan, centres, half)

    monkeypatch.setattr(measure, "patches", spy)
    assert measure.flat_scan(sc, shape, c0, A0, s0, init_err, sign) == (not rough)
    first = min(rough, default=len(c0))
    chunks = measure._growing_chunks(len(c0))
    assert [m - k for k, m in chunks][:3] == [measure.FLAT_CHUNK_MIN, 8, 16]
    assert chunks[0][0] == 0 and chunks[-1][1] == len(c0)
    assert all(a[1] == b[0] for a, b in zip(chunks[:-1], chunks[1:], strict=True))
    # the patches read: those of the chunks up to the one holding the first rough patch
    assert sum(read) == (next(m for _, m in chunks if m > first) if rough else len(c0))
    if rough and first < measure.FLAT_CHUNK_MIN:
        assert read == [measure.FLAT_CHUNK_MIN]


def _bits(a) -> np.ndarray:
    return np.asarray(a, np.float64).reshape(-1).view(np.int64)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
@pytest.mark.parametrize("n", [1, 2, 3, 8, 13, 40, 41])
def test_median1_is_numpys_median_to_the_bit(dtype, n):
    """common.median1 (one partition) gives np.median's value in the array's dtype, ties,
    odd and even lengths; with a NaN it is NumPy's NaN."""
    from softplot.marks.common import median1

    rng = np.random.default_rng(n)
    for a in (rng.normal(0, 1, n), rng.integers(0, 4, n) * 0.1, np.full(n, 0.3)):
        a = a.astype(dtype)
        got, want = median1(a), np.median(a)
        assert got.dtype == want.dtype and np.array_equal(_bits(got), _bits(want))
    b = rng.normal(0, 1, n).astype(dtype)
    b[n // 2] = np.nan
    assert np.isnan(median1(b))


def test_median_profile_is_numpys_columnwise_median_to_the_bit():
    """geometry._median_profile (the rows' median by median_rows) is np.median over the
    profiles (axis 0), sample by sample, for an odd and an even number of profiles."""
    from softplot.marks.geometry import _median_profile

    rng = np.random.default_rng(3)
    for k in (5, 6, 21):
        profiles = [rng.normal(0, 1, 57).astype(np.float32) for _ in range(k)]
        want = np.median(np.stack(profiles), axis=0)
        got = _median_profile(profiles)
        assert got.dtype == want.dtype and np.array_equal(_bits(got), _bits(want))


def _bar_share_whole(scan, shape, c, A, s, sign):
    """measure.bar_share as it was: the bars' profiles evaluated over the whole patches."""
    from softplot.marks.lsm import patch_frame, support_mask
    from softplot.marks.measure import _bar_regression, patches
    from softplot.marks.template import aperture

    grow = float(1.0 / max(np.linalg.svd(A, compute_uv=False).min(), 1e-3))
    reach = min(shape.extent + 2.5 * s + 1.25, 0.5 * shape.width + 6.0 * s + 6.0)
    half = int(np.ceil(reach * grow + 2))
    stack, origin = patches(scan, c, half)
    u, v = patch_frame(origin, c, A, stack.shape)
    ap = tuple(x[:, None, None] for x in aperture(A.astype(np.float32)))
    bu, bv, core = shape.bars(u, v, np.float32(max(s, 0.3)), aperture=ap)
    m = (support_mask(shape, u, v, 2.5 * s + 1.25) & np.isfinite(stack)
         & (np.maximum(np.abs(u), np.abs(v)) <= reach))
    return _bar_regression(stack, m, bu, bv, core, half, sign)


@pytest.mark.parametrize("turn", [0.0, 0.3])
def test_bar_share_evaluates_the_bars_only_where_it_regresses(turn):
    """bar_share's bars evaluated at the pixels of the regression only (measure._bars_at)
    give the shares of the bars over the whole patches to the last bit, over a scene
    texture, with turned affines and a patch the scan's edge cuts; _bars_at's values are
    those of the whole patches there and 0 elsewhere."""
    from softplot.marks.lsm import patch_frame
    from softplot.marks.measure import _bars_at, bar_share
    from softplot.marks.template import aperture

    sc, c, shape = _cross_grid_scan(rough=(0, 7, 20))
    c = np.concatenate([c + [0.3, -0.2], [[3.0, 5.0]]])
    ct, st = np.cos(turn), np.sin(turn)
    A = np.broadcast_to(np.array([[ct, st], [-st, ct]]) * [[1.0], [0.97]], (len(c), 2, 2))
    for s, sign in ((1.0, -1), (0.6, -1), (1.0, 1)):
        got = bar_share(sc, shape, c, A, s, sign)
        want = _bar_share_whole(sc, shape, c, np.array(A), s, sign)
        if sign < 0:  # the crosses' polarity: most have a share
            assert np.isfinite(got).sum() > len(c) // 2
        assert np.array_equal(np.isnan(got), np.isnan(want))
        assert np.array_equal(_bits(got[np.isfinite(got)]), _bits(want[np.isfinite(want)]))
    u, v = patch_frame(np.zeros((len(c), 2)), c, np.array(A), (len(c), 31, 33))
    m = (np.abs(u) < 5) | (np.abs(v) < 2)
    ap = aperture(np.array(A, np.float32))
    whole = shape.bars(u, v, np.float32(0.8), aperture=tuple(x[:, None, None] for x in ap))
    for a, b in zip(_bars_at(shape, u, v, m, np.float32(0.8), ap), whole, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a[m], b[m]) and not a[~m].any()


def test_fine_rotations_histogrammed_at_once_are_each_cells_own():
    """grid._lattice_search histograms the fine rotations of all its cells in one call: each
    rotation's phase histogram is the one a call for that cell alone gives, to the bit."""
    rng = np.random.default_rng(5)
    d = rng.uniform(-900, 900, (700, 2))
    w = rng.uniform(0, 1, 700)
    sub = np.linspace(-0.004, 0.004, 11)
    fines = [t + sub for t in rng.uniform(-0.3, 0.3, 24)]
    every = grid._histograms(d, w, 63.7, 61.2, np.concatenate(fines))
    for i, f in enumerate(fines):
        assert np.array_equal(every[11 * i : 11 * (i + 1)], grid._histograms(d, w, 63.7, 61.2, f))



def test_compiled_phase_histograms_are_numpys_to_the_bit():
    """The lattice search's phase histograms counted in one compiled pass (point by point,
    rotation by rotation, the order NumPy's bincount adds in) are NumPy's to the bit: peaks
    anywhere, peaks on the nodes of a turned lattice (phases of exactly 0 and just below a
    whole pitch), weights of zero."""
    from softplot.marks import kernels

    if not kernels.ready():
        pytest.skip("numba unavailable")
    rng = np.random.default_rng(9)
    d = rng.uniform(-900, 900, (600, 2))
    t = np.radians(3.0)
    nodes = np.stack(np.meshgrid(np.arange(-6, 7), np.arange(-6, 7)), -1).reshape(-1, 2)
    on = nodes @ np.array([[63.7 * np.cos(t), 63.7 * np.sin(t)],
                           [-61.2 * np.sin(t), 61.2 * np.cos(t)]])
    d = np.concatenate([d, on, on - 1e-12])
    w = rng.uniform(0, 1, len(d))
    w[::7] = 0.0
    thetas = np.concatenate([[t, 0.0, -t], rng.uniform(-0.4, 0.4, 40)])
    Hs = np.zeros((len(thetas), grid.PHASE_BINS, grid.PHASE_BINS))
    grid._phase_bins(d, w, 63.7, 61.2, np.cos(thetas), np.sin(thetas), Hs)
    want = grid._phase_counts(d, w, 63.7, 61.2, thetas)
    assert np.array_equal(Hs, want)
    assert Hs[0].max() >= 0.5 * w[600:].sum()  # the turned lattice's nodes pile up
    got = grid._phase_histograms(d, w, 63.7, 61.2, thetas)
    want = want + np.roll(want, -1, 1)
    assert np.array_equal(got, want + np.roll(want, -1, 2))
