"""Start from what surveyors have: minimal control, approximate points, fixed-pose rigs."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.errors import SoftplotError
from softplot.orientation.bundle import bundle_adjust
from softplot.orientation.bundle_init import initialize
from softplot.orientation.bundle_io import read_project, write_project
from softplot.synthetic.block import make_block
from softplot.synthetic.testfield import make_testfield


def _three_control(net, idx):
    """Keep full control on the points ``idx`` only (no check points)."""
    keep = np.zeros(len(net.point_names), bool)
    keep[idx] = True
    net.control[~keep] = np.nan
    net.control_sigma[~keep] = np.nan
    net.control_sigma[keep] = 0.0
    net.control[keep] = net.XYZ_true[keep]
    net.check[:] = False


def _reference(net, free):
    """The same adjustment started from the true values."""
    d = net.to_bundle_data(free=free)
    d.X0[:], d.angles[:] = net.X0_true, net.angles_true
    d.XYZ[:] = net.XYZ_true
    return bundle_adjust(d)


def _far_apart(XYZ):
    """Three well-spread points: two extremes along X and the one farthest from their line."""
    a, b = int(np.argmin(XYZ[:, 0] + XYZ[:, 1])), int(np.argmax(XYZ[:, 0] - XYZ[:, 1]))
    e = (XYZ[b] - XYZ[a]) / np.linalg.norm(XYZ[b] - XYZ[a])
    r = XYZ - XYZ[a]
    dist = np.linalg.norm(r - np.outer(r @ e, e), axis=1)
    return [a, b, int(np.argmax(dist))]


@pytest.mark.parametrize("kind", ["block", "testfield"])
def test_three_control_points_and_no_orientations(kind):
    if kind == "block":
        net = make_block(n_strips=2, photos_per_strip=6, seed=1)
        free = ()
    else:
        net = make_testfield(n_photos=12, seed=3)
        free = ("c", "x0", "y0", "k1")
    _three_control(net, _far_apart(net.XYZ_true))
    d = net.to_bundle_data(free=free)
    d.X0[:] = np.nan
    d.angles[:] = np.nan
    d.XYZ[:] = np.nan
    initialize(d)
    res = bundle_adjust(d)
    ref = _reference(net, free)
    assert res.converged and res.datum == "control"
    assert np.abs(res.X0 - ref.X0).max() < 1e-5
    assert np.abs(res.XYZ - ref.XYZ).max() < 1e-5
    assert res.sigma0 == pytest.approx(ref.sigma0, rel=1e-6)


def test_two_control_points_are_not_enough():
    net = make_block(n_strips=1, photos_per_strip=5, seed=2)
    _three_control(net, _far_apart(net.XYZ_true)[:2])
    d = net.to_bundle_data(free=())
    d.X0[:] = np.nan
    d.angles[:] = np.nan
    with pytest.raises(SoftplotError, match="fewer than 4 known points"):
        initialize(d)


def test_approximate_object_coordinates_from_points_csv(tmp_path):
    """No control, no orientations: the project's points.csv approximations start and
    define the (inner-constraint) datum."""
    net = make_testfield(n_photos=8, seed=4)
    net.control[:] = np.nan
    net.control_sigma[:] = np.nan
    d = net.to_bundle_data(free=())
    d.cameras[0].values[:10] = net.intr_true[0]
    d.X0[:] = np.nan
    d.angles[:] = np.nan
    rng = np.random.default_rng(0)
    approx = net.XYZ_true + rng.normal(0, 0.05, net.XYZ_true.shape)
    d.XYZ[:] = approx
    write_project(tmp_path / "p", d)
    assert (tmp_path / "p" / "points.csv").is_file()
    e = read_project(tmp_path / "p")
    approx = approx[[d.point_names.index(n) for n in e.point_names]]
    np.testing.assert_array_equal(e.XYZ, approx)
    initialize(e)
    res = bundle_adjust(e)
    assert res.converged and res.datum == "free"
    # inner constraints over the approximations: no mean shift, no rotation or scale
    assert np.abs((res.XYZ - approx).mean(axis=0)).max() < 1e-9
    assert 0.8 < res.sigma0 < 1.2


def test_fixed_exterior_orientation_without_control():
    """A fixed-pose rig: the photos' orientations held, no control - points intersected."""
    net = make_testfield(n_photos=16, seed=5, noise_um=2.0)
    net.control[:] = np.nan
    net.control_sigma[:] = np.nan
    d = net.to_bundle_data(free=())
    d.cameras[0].values[:10] = net.intr_true[0]
    d.X0[:], d.angles[:] = net.X0_true, net.angles_true
    d.photo_fixed[:] = True
    d.XYZ[:] = np.nan
    initialize(d)
    res = bundle_adjust(d)
    assert res.datum == "fixed-eo"
    assert res.n_unknowns == 3 * len(d.point_names)
    assert np.all(res.eo_std == 0)
    z = (res.XYZ - net.XYZ_true) / res.XYZ_std
    assert 0.6 < np.mean(z**2) < 1.5  # 147 coordinates
