"""Serial stages split over the process's threads (softplot.runtime.thread_map): the lattice
search's hypotheses refined a few at a time, the mark geometry's profiles sampled and
fitted in parts. Each must give what the one-by-one computation gives, to the bit."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from softplot import runtime
from softplot.camera import load_camera
from softplot.io import Scan
from softplot.marks import detect, geometry, grid, kernels
from softplot.synthetic import ScanSpec, render_scan

CAM = "rollei-6006"


@pytest.fixture
def two_threads():
    runtime.set_threads(2)
    yield
    runtime.set_threads(None)


def _find_lattice_one_by_one(xy, score, reseau, px_per_mm, rotate_deg=0.0,
                             max_rotation_deg=20.0, scale_tol=None, by_count=False):
    """:func:`softplot.marks.grid.find_lattice` as it was: each hypothesis refined in turn,
    the ones too weak for the best lattice so far skipped."""
    px, py = reseau.pitch_x, reseau.pitch_y
    lx, ly = px * px_per_mm, py * px_per_mm
    square = abs(lx - ly) < 0.08 * min(lx, ly)
    best, best_key = None, None
    for theta, p0, n_cell in grid._lattice_search(xy, score, lx, ly, rotate_deg,
                                                  max_rotation_deg, square):
        if best_key is not None and 1.5 * n_cell + 3 < best_key[0]:
            continue
        got = grid._lattice_at(xy, np.ones_like(score) if by_count else score, theta, p0, lx,
                               ly, min(px, py), scale_tol)
        if got is None:
            continue
        p0, Bc, idx, cand, (n_agree, med) = got
        turn = np.degrees(np.arctan2(Bc[1, 0], Bc[0, 0])) - rotate_deg
        key = (n_agree, -round(abs((turn + 180.0) % 360.0 - 180.0) / 5.0), -med)
        if best_key is None or key > best_key:
            best = (p0, Bc, idx, cand)
            best_key = key
    return best


def _peaks(seed, n_clutter):
    """Candidate peaks (pixel system) of a 7 x 7 part of a 5 mm reseau at 40 px/mm, turned
    2 degrees, with ``n_clutter`` clutter peaks scoring as high (scores in [0, 1])."""
    rng = np.random.default_rng(seed)
    c, s = np.cos(np.radians(2.0)), np.sin(np.radians(2.0))
    ij = np.stack(np.meshgrid(np.arange(7.0), np.arange(7.0)), -1).reshape(-1, 2) * 200.0
    nodes = ij @ np.array([[c, s], [-s, c]]) + [300.0, 250.0] + rng.normal(0, 0.7, ij.shape)
    keep = rng.random(len(nodes)) > 0.15
    clutter = rng.uniform(0, 1700, (n_clutter, 2))
    xy = np.concatenate([nodes[keep], clutter])
    score = np.concatenate([rng.uniform(0.4, 1.0, keep.sum()), rng.uniform(0, 1.0, n_clutter)])
    return xy, score


@pytest.mark.parametrize("seed", range(4))
def test_lattice_hypotheses_refined_on_two_threads_pick_the_one_by_one_lattice(two_threads,
                                                                                seed):
    """Over clutter that scores as high as the crosses (many hypotheses refined, some ruled
    out by an earlier one of their batch), by scores and by count: the same lattice, to the
    bit, as refining the hypotheses one by one."""
    reseau = load_camera(CAM).reseau
    xy, score = _peaks(seed, (40, 150, 400, 900)[seed])
    for by_count in (False, True):
        want = _find_lattice_one_by_one(xy, score, reseau, 40.0, scale_tol=0.05,
                                        by_count=by_count)
        got = grid.find_lattice(xy, score, reseau, 40.0, scale_tol=0.05, by_count=by_count)
        assert want is not None and got is not None
        p0, Bc, idx, cand = want
        assert np.array_equal(got.p0, p0) and np.array_equal(got.B, Bc)
        assert np.array_equal(got.idx, idx) and np.array_equal(got.cand, cand)


def test_a_hypothesis_its_batch_rules_out_is_dropped(two_threads, monkeypatch):
    """Hypotheses refined side by side are still taken in their order: one that the lattice
    of an earlier one of its batch rules out (too few peaks in its cell to gather as many)
    is dropped, however many peaks its own lattice gathers, as the one-by-one search never
    refines it; a later strong one still wins."""
    reseau = load_camera(CAM).reseau
    # (theta, p0, peaks in the cell) and what each lattice gathers
    hyps = [(0.0, np.zeros(2), 100), (0.01, np.zeros(2), 10), (0.02, np.zeros(2), 20),
            (0.03, np.zeros(2), 90), (0.04, np.zeros(2), 5)]
    agree = {0.0: 50.0, 0.01: 80.0, 0.02: 40.0, 0.03: 60.0, 0.04: 99.0}
    refined = []

    def lattice_at(xy, score, theta, p0, lx, ly, pmin, scale_tol, max_shear=None):
        refined.append(theta)
        B = np.array([[lx, 0.0], [0.0, ly]]) * (1.0 + theta)
        return p0, B, np.zeros((1, 2), int), np.array([int(theta * 100)]), (agree[theta], 1.0)

    monkeypatch.setattr(grid, "_lattice_search", lambda *a, **k: hyps)
    monkeypatch.setattr(grid, "_lattice_at", lattice_at)
    xy, score = np.zeros((5, 2)), np.ones(5)
    want = _find_lattice_one_by_one(xy, score, reseau, 40.0)
    assert refined == [0.0, 0.03]  # the others ruled out one by one
    refined.clear()
    got = grid.find_lattice(xy, score, reseau, 40.0)
    assert set(refined) >= {0.0, 0.01} and 0.04 not in refined  # 0.01 refined beside 0.0
    assert np.array_equal(got.cand, want[3]) and got.cand.tolist() == [3]
    assert np.array_equal(got.B, want[1])


def test_split_profile_fits_are_the_whole_batchs(two_threads):
    """The compiled box fits of a batch split in two halves on the threads are each
    problem's fit in one batch (each problem is fitted alone), to the bit."""
    if not kernels.ready():
        pytest.skip("numba unavailable")
    rng = np.random.default_rng(3)
    u = np.arange(-30.0, 30.01, 0.5)
    K = 21
    a1, a2 = -rng.uniform(12, 18, K), rng.uniform(12, 18, K)
    s = rng.uniform(0.8, 1.6, K)
    from scipy.special import ndtr

    data = (0.1 + 0.6 * (ndtr((u - a1[:, None]) / s[:, None]) - ndtr((u - a2[:, None])
                                                                      / s[:, None]))
            + rng.normal(0, 0.02, (K, len(u))))
    p0 = np.column_stack([np.full(K, 0.1), np.full(K, 0.5), a1 + 1, a2 - 1, np.ones(K),
                          np.zeros(K)])
    args = (geometry._ALONG, u, data, p0, -np.inf, np.inf)
    assert K >= geometry.LM_SPLIT
    got = geometry._lm_compiled(*args, h=0.5)
    runtime.set_threads(1)
    want = geometry._lm_compiled(*args, h=0.5)
    assert np.isfinite(want).all() and np.array_equal(got, want, equal_nan=True)


def test_geometry_on_two_threads_is_the_one_threads(two_threads, monkeypatch):
    """The mark geometry of a busy render (the call detection makes), its crosses' profiles
    sampled on two threads, is the one-thread geometry to the bit."""
    from softplot.marks import marksize

    img, truth = render_scan(CAM, ScanSpec(dpi=600.0, rotation_deg=1.5, scene="busy"), 5)
    calls = []

    def keep(*args, **kw):
        calls.append((args, kw))
        return geometry.estimate_geometry(*args, **kw)

    monkeypatch.setattr(marksize, "estimate_geometry", keep)
    detect(Scan.from_array(img, dpi=truth["dpi"]), load_camera(CAM))
    args, kw = calls[0]
    got = geometry.estimate_geometry(*args, **kw)
    runtime.set_threads(1)
    want = geometry.estimate_geometry(*args, **kw)
    assert got.source == want.source == "scan" and got.n >= 10
    assert repr(got) == repr(want)


def test_width_trials_on_two_threads_are_the_one_threads(two_threads, monkeypatch):
    """The line widths (or arms) the profiles leave in doubt are tried side by side on the
    threads: each trial's fits are its own, so the width chosen and every trial's score are
    those of trying them one after the other."""
    from softplot.marks import marksize

    img, truth = render_scan(CAM, ScanSpec(dpi=600.0, rotation_deg=1.5, scene="busy"), 2)
    calls, scores = [], []

    def keep(*args, **kw):
        calls.append((args, kw))
        return marksize.choose_width(*args, **kw)

    def trial(*args, **kw):
        scores.append(trial_score(*args, **kw))
        return scores[-1]

    trial_score = marksize._trial_score
    monkeypatch.setattr(importlib.import_module("softplot.marks.detect"), "choose_width", keep)
    detect(Scan.from_array(img, dpi=truth["dpi"]), load_camera(CAM))
    args, kw = calls[0]
    monkeypatch.setattr(marksize, "_trial_score", trial)
    got = marksize.choose_width(*args, **kw)
    two = sorted(scores)
    scores.clear()
    runtime.set_threads(1)
    want = marksize.choose_width(*args, **kw)
    assert len(scores) >= 2 and sorted(scores) == two  # several trials, the same scores
    assert repr(got) == repr(want)
