"""Aerial blocks: synthetic generator, bundle block and independent-model triangulation."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.orientation.block import consecutive_models, independent_models
from softplot.orientation.bundle import bundle_adjust
from softplot.orientation.bundle_init import initialize
from softplot.synthetic.block import make_block


def test_block_generator_overlaps_control_and_check_points():
    net = make_block(n_strips=5, photos_per_strip=21, seed=0)
    assert net.info["n_models"] == 100
    B, S = net.info["base"], 230.0 * 1520.0 / net.intr_true[0, 0]
    assert B == pytest.approx(0.4 * S)  # 60 % forward overlap
    assert net.info["strip_spacing"] == pytest.approx(0.7 * S)  # 30 % side overlap
    rays = np.bincount(net.obs_point)
    assert rays.min() >= 2 and rays.max() >= 5  # triple overlap in strips, side overlap
    ctl = np.isfinite(net.control_sigma[:, 0])
    P = net.XYZ_true
    lo, hi = P.min(axis=0), P.max(axis=0)
    edge = np.minimum(np.abs(P[:, :2] - lo[:2]), np.abs(P[:, :2] - hi[:2])).min(axis=1)
    assert np.all(edge[ctl] < B / 2 + 1e-9)  # control at the block edges
    assert np.all(edge[net.check] > B / 2)  # check points inside
    assert net.check.sum() == 20 and not np.any(ctl & net.check)
    # every image point inside the 230 mm format
    assert np.abs(net.xy_true).max() < 115.0


def test_noise_free_block_is_recovered_by_bundle_and_independent_models():
    net = make_block(n_strips=2, photos_per_strip=6, noise_um=0.0, control_sigma_m=0.0, seed=1)
    d = net.to_bundle_data(free=())
    im = independent_models(d, pc_tie="xyz")
    ok = np.all(np.isfinite(im.XYZ), axis=1)
    assert ok.sum() > 0.8 * len(ok)
    assert np.abs(im.XYZ[ok] - net.XYZ_true[ok]).max() < 1e-4
    pc = np.isfinite(im.projection_centres[:, 0])
    assert np.abs(im.projection_centres[pc] - net.X0_true[pc]).max() < 1e-4
    imz = independent_models(d, pc_tie="z")
    assert np.abs(imz.XYZ[ok] - net.XYZ_true[ok]).max() < 1e-4
    initialize(d)
    b = bundle_adjust(d)
    assert np.abs(b.XYZ - net.XYZ_true).max() < 1e-5
    assert b.check_rms()["Z"] < 1e-5


@pytest.mark.parametrize("tie", ["xyz", "z"])
def test_independent_models_with_noise(tie):
    net = make_block(n_strips=3, photos_per_strip=8, noise_um=3.0, seed=2)
    d = net.to_bundle_data(free=())
    im = independent_models(d, pc_tie=tie)
    assert im.converged
    assert len(im.models) == 21 == len(consecutive_models(d))
    # scale 1:10000, 3 um -> 3 cm in the image plane; heights weaker (base/height 0.6)
    # (projection centres tied in Z only: fewer conditions, heights drift more between the
    # edge control, as Birardi accepts for analogue plotters)
    assert im.check["X"] < 0.15 and im.check["Y"] < 0.15
    assert im.check["Z"] < (0.5 if tie == "xyz" else 1.0)
    assert 0.01 < im.sigma0 < 0.2  # metres
    # Z-only ties keep fewer conditions
    assert im.redundancy > 0
    # the pooled model-point sigma0 is the RMS of the model discrepancies (isotropic weights:
    # heights are weaker than planimetry, so the point std is only a pooled figure)
    ok = np.all(np.isfinite(im.XYZ), axis=1)
    rms = np.sqrt(np.mean((im.XYZ[ok] - net.XYZ_true[ok]) ** 2))
    if tie == "xyz":  # with Z-only ties the block bends in height beyond the model sigma0
        assert rms < 5 * im.sigma0


def test_bundle_block_with_self_calibration_and_check_points():
    net = make_block(n_strips=3, photos_per_strip=8, noise_um=3.0, seed=3)
    net.intr_given[0, :3] = [152.0, 0.0, 0.0]
    d = net.to_bundle_data(free=("c", "x0", "y0"))
    initialize(d)
    b = bundle_adjust(d)
    assert b.converged and 0.85 < b.sigma0 < 1.15
    chk = b.check_rms()
    assert chk["n"] == 20
    # check-point errors consistent with the predicted standard deviations
    e = b.check_point_errors()
    sd = b.XYZ_std[d.check]
    assert np.sqrt(np.mean((e / sd) ** 2)) < 2.0
    assert chk["X"] < 0.1 and chk["Y"] < 0.1 and chk["Z"] < 0.3
    err = np.abs(b.intrinsics[0, :3] - net.intr_true[0, :3])
    assert np.all(err < 4 * b.intrinsics_std[0, :3])


def test_block_initialised_without_any_exterior_orientation():
    """Resection at the edge control, intersection, resection ... along the strips."""
    net = make_block(n_strips=3, photos_per_strip=10, seed=4)
    d = net.to_bundle_data(free=())
    d.X0[:] = np.nan
    d.angles[:] = np.nan
    initialize(d)
    assert np.abs(d.X0 - net.X0_true).max() < 20.0  # metres, at 1520 m flying height
    b = bundle_adjust(d)
    assert b.converged and 0.85 < b.sigma0 < 1.15
    assert np.abs(b.X0 - net.X0_true).max() < 1.0
