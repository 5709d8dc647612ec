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
    d, j = neighbours._nearest(q, m, 17)
    assert np.array_equal(d, d0) and np.array_equal(j, j0)
    assert neighbours._nearest(q.copy(), m.copy(), 17)[1] is j  # kept: the values decide
    moved = m.copy()
    moved[40] += 0.3
    d2, j2 = neighbours._nearest(q, moved, 17)
    want = cKDTree(moved).query(q, k=17)
    assert np.array_equal(d2, want[0]) and np.array_equal(j2, want[1])
    assert not np.array_equal(d2, d)
    for i in range(neighbours.NEAREST_KEPT):
        neighbours._nearest(q[: 10 + i], m, 5)
    again = neighbours._nearest(q, m, 17)
    assert again[1] is not j and np.array_equal(again[1], j0)
    with pytest.raises(ValueError):
        d[0, 0] = 1.0  # read-only: a caller cannot change what the next one gets
