"""BAL problems: reader, a small real subset, the full Ladybug problem (cost target only)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from softplot.adjust.bal import read_bal, solve_bal
from softplot.adjust.sparse_bundle import LMOptions
from softplot.errors import SoftplotError

LADYBUG = Path("/work/shared/data/bal/problem-49-7776-pre.txt")
needs_data = pytest.mark.skipif(not LADYBUG.is_file(), reason="BAL data not available")


@needs_data
def test_reader_counts_and_initial_cost():
    p = read_bal(LADYBUG)
    assert (p.n_cameras, p.n_points, p.n_observations) == (49, 7776, 31843)
    from softplot.adjust.bal import BALModel

    cost = BALModel(p).evaluate((p.cameras, p.points), False).cost
    assert cost == pytest.approx(8.5091e5, rel=1e-4)  # the README's starting cost


@needs_data
def test_small_subset_converges():
    p = read_bal(LADYBUG).subset(range(8))
    r = solve_bal(p)
    assert r.converged
    assert r.final_cost < 0.05 * r.initial_cost
    assert r.rms_px < 2.0


@needs_data
def test_full_ladybug_reaches_the_ceres_cost():
    """From the given start to a final cost <= 1.34e4 (Ceres: 1.3308e4; timing: benchmark)."""
    r = solve_bal(read_bal(LADYBUG), LMOptions())
    assert r.final_cost <= 1.34e4
    assert r.iterations <= 60


@pytest.mark.parametrize(
    "text,msg",
    [
        ("", "missing header"),
        ("1 1 x", "three integers"),
        ("1 1 1\n0 0 1.0 2.0\n", "expected"),
        ("1 1 1\n0 5 1 2\n" + "0 " * 9 + "0 0 0", "out of range"),
    ],
)
def test_reader_errors(tmp_path, text, msg):
    f = tmp_path / "b.txt"
    f.write_text(text)
    with pytest.raises(SoftplotError, match=msg):
        read_bal(f)


def test_subset_renumbers():
    from test_bundle_engine import synthetic_bal

    p, _ = synthetic_bal(n_cam=4, n_pts=20)
    s = p.subset([1, 2])
    assert s.n_cameras == 2 and set(np.unique(s.cam_index)) == {0, 1}
    assert s.points.shape[0] == np.unique(s.point_index).size
