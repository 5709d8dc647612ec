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
