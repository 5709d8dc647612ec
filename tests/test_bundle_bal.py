"""BAL problems: reader, a small real problem shipped with the tests (tests/data/bal/, what
the first 8 cameras of the Ladybug problem see), the full Ladybug problem as an optional input
(the shared data folder beside the repository; cost target only)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from softplot.adjust.bal import read_bal, solve_bal
from softplot.adjust.sparse_bundle import LMOptions
from softplot.errors import SoftplotError

#: shipped: cameras 0-7 of the Ladybug problem (tools/make_bal_subset.py; tests/data/bal/README.md)
SMALL = Path(__file__).parent / "data" / "bal" / "ladybug-8.txt"
#: optional: the whole Ladybug problem, in the shared data folder beside the repository
LADYBUG = Path(__file__).resolve().parents[2] / "shared/data/bal/problem-49-7776-pre.txt"
needs_data = pytest.mark.skipif(not LADYBUG.is_file(), reason="the full Ladybug problem (optional "
                                "benchmark input) is not beside the repository")


def _cost_by_the_readme(p) -> float:
    """The BAL cost computed independently of softplot's model, as the BAL README states it:
    P = R X + t (Rodrigues R), p = -P/P.z, r = 1 + k1 |p|^2 + k2 |p|^4, predicted = f r p."""
    import cv2

    total = 0.0
    for k in range(p.n_cameras):
        sel = p.cam_index == k
        cam = p.cameras[k]
        R, _ = cv2.Rodrigues(cam[:3].reshape(3, 1))
        P = p.points[p.point_index[sel]] @ R.T + cam[3:6]
        q = -P[:, :2] / P[:, 2:3]
        n2 = (q**2).sum(1, keepdims=True)
        pred = cam[6] * (1 + cam[7] * n2 + cam[8] * n2**2) * q
        total += 0.5 * float(((pred - p.xy[sel]) ** 2).sum())
    return total


def test_shipped_problem_reads_with_the_readme_cost():
    p = read_bal(SMALL)
    assert (p.n_cameras, p.n_points, p.n_observations) == (8, 2581, 6480)
    from softplot.adjust.bal import BALModel

    cost = BALModel(p).evaluate((p.cameras, p.points), False).cost
    assert cost == pytest.approx(_cost_by_the_readme(p), rel=1e-10)


@needs_data
def test_reader_counts_and_initial_cost():
    p = read_bal(LADYBUG)
    assert (p.n_cameras, p.n_points, p.n_observations) == (49, 7776, 31843)
    from softplot.adjust.bal import BALModel

    cost = BALModel(p).evaluate((p.cameras, p.points), False).cost
    assert cost == pytest.approx(8.5091e5, rel=1e-4)  # the README's starting cost
    assert cost == pytest.approx(_cost_by_the_readme(p), rel=1e-10)


def test_small_problem_converges():
    p = read_bal(SMALL)
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
