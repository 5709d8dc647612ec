"""Photogrammetric bundle: truth recovery, self-calibration, free network datum, snooping."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats

from conftest import sweep
from softplot.orientation.bundle import BundleOptions, bundle_adjust, distortion
from softplot.orientation.bundle_init import initialize
from softplot.synthetic.testfield import make_testfield

FREE7 = ("c", "x0", "y0", "k1", "k2", "p1", "p2")


def test_distortion_derivatives_match_finite_differences():
    rng = np.random.default_rng(0)
    xb, yb = rng.uniform(-50, 50, 20), rng.uniform(-50, 50, 20)
    p = np.array([100.0, 0.1, -0.1, 3e-6, -1e-9, 2e-13, 4e-6, -3e-6, 2e-4, -1e-4])
    d, J, K = distortion(xb, yb, p)
    h = 1e-6
    dxp, _, _ = distortion(xb + h, yb, p)
    dxm, _, _ = distortion(xb - h, yb, p)
    assert np.allclose((dxp - dxm) / (2 * h), J[:, :, 0], atol=1e-9)
    dyp, _, _ = distortion(xb, yb + h, p)
    dym, _, _ = distortion(xb, yb - h, p)
    assert np.allclose((dyp - dym) / (2 * h), J[:, :, 1], atol=1e-9)
    for i in range(7):
        q = p.copy()
        q[3 + i] += 1.0
        d1, _, _ = distortion(xb, yb, q)
        assert np.allclose(d1 - d, K[:, :, i], rtol=1e-9, atol=1e-12)  # linear in k's


def test_noise_free_bundle_recovers_truth_exactly():
    net = make_testfield(n_photos=8, noise_um=0.0, control_sigma_m=0.0, seed=1)
    net.intr_true[0, 4:8] = [2e-11, 0.0, 3e-6, -2e-6]  # k2, k3, p1, p2
    # regenerate the image coordinates with the richer distortion
    net = make_testfield(
        n_photos=8, noise_um=0.0, control_sigma_m=0.0, seed=1, intrinsics=net.intr_true[0]
    )
    res = bundle_adjust(net.to_bundle_data(free=FREE7))
    assert res.converged
    err = res.intrinsics[0, :10] - net.intr_true[0]
    assert np.all(np.abs(err[:3]) < 1e-7)  # mm
    assert abs(err[3]) < 1e-12 and abs(err[6]) < 1e-9 and abs(err[7]) < 1e-9
    assert np.abs(res.X0 - net.X0_true).max() < 1e-6
    assert np.abs(res.M - net.M_true).max() < 1e-9
    assert res.rms_image_um()["xy"] < 1e-5


@pytest.mark.parametrize("seed", [0])
def test_self_calibration_on_49_point_test_field(seed):
    """Convergent + rolled photos, 2 um noise: c, x0, y0 within 1 um; k1 within 2 std."""
    net = make_testfield(n_photos=36, noise_um=2.0, seed=seed)
    res = bundle_adjust(net.to_bundle_data(free=("c", "x0", "y0", "k1")))
    err_um = (res.intrinsics[0, :3] - net.intr_true[0, :3]) * 1000.0
    assert np.all(np.abs(err_um) < 1.0), err_um
    std_um = res.intrinsics_std[0, :3] * 1000.0
    assert np.all(std_um < 0.6)  # the geometry must make 1 um a > 1.6 sigma statement
    dk1 = res.intrinsics[0, 3] - net.intr_true[0, 3]
    assert abs(dk1) < 2.0 * res.intrinsics_std[0, 3]
    # image residual RMS consistent with 2 um per coordinate
    assert 1.8 < res.rms_image_um()["x"] < 2.2
    # sigma0 inside the two-sided 99.9 % chi-square band of its redundancy
    r = res.redundancy
    lo, hi = (np.sqrt(scipy.stats.chi2.ppf(q, r) / r) for q in (0.0005, 0.9995))
    assert lo < res.sigma0 < hi
    assert not [w for w in res.warnings if "correlation" in w]


@pytest.mark.parametrize("seed", sweep(list(range(1, 13)), 2))
def test_calibration_errors_are_consistent_with_their_std(seed):
    net = make_testfield(n_photos=24, noise_um=2.0, seed=seed)
    res = bundle_adjust(net.to_bundle_data(free=("c", "x0", "y0", "k1")))
    z = (res.intrinsics[0, :4] - net.intr_true[0, :4]) / res.intrinsics_std[0, :4]
    assert np.all(np.abs(z) < 3.5), z
    ze = (res.XYZ - net.XYZ_true) / res.XYZ_std
    assert np.sqrt(np.mean(ze**2)) < 1.5
    # exterior orientation: positions and omega, phi, kappa (propagated from the increments)
    da = np.mod(res.angles - net.angles_true + np.pi, 2 * np.pi) - np.pi
    zo = np.hstack([res.X0 - net.X0_true, da]) / res.eo_std
    assert np.sqrt(np.mean(zo**2)) < 1.5


def test_weak_geometry_raises_correlation_warning():
    """Parallel, upright photos of a shallow field with loose control (UMK-like camera): the
    principal point is not separable from the exterior orientation."""
    umk = np.array([99.512, 0.0125, -0.0207, 0, 0, 0, 0, 0, 0, 0.0])
    given = np.array([99.5, 0, 0, 0, 0, 0, 0, 0, 0, 0.0])
    kw = dict(intrinsics=umk, given=given, format_mm=(166.0, 120.0), control_sigma_m=0.01)
    net = make_testfield(n_photos=6, convergent=False, rolled=False, depth_scale=0.1, seed=2, **kw)
    res = bundle_adjust(net.to_bundle_data(free=("c", "x0", "y0")))
    msgs = [w for w in res.warnings if "correlation" in w]
    assert any("x0-" in w for w in msgs) and any("y0-" in w for w in msgs), res.warnings
    best = res.correlation_eo_max[0]
    assert abs(best["x0"]["corr"]) > 0.9 and abs(best["y0"]["corr"]) > 0.9
    # convergent and rolled photos of the deep field decorrelate them: no warning
    good = bundle_adjust(
        make_testfield(n_photos=12, seed=2, **kw).to_bundle_data(free=("c", "x0", "y0"))
    )
    assert not [w for w in good.warnings if "correlation" in w], good.warnings
    assert abs(good.correlation_eo_max[0]["x0"]["corr"]) < 0.9


def test_blunder_is_flagged():
    net = make_testfield(n_photos=12, noise_um=2.0, seed=4)
    o = 100
    net.xy[o, 0] += 0.030  # 30 um blunder (15 sigma)
    res = bundle_adjust(net.to_bundle_data(free=("c", "x0", "y0", "k1")))
    assert res.flagged[o]
    w = np.nan_to_num(np.abs(res.w), nan=0).max(axis=1)
    assert int(np.argmax(w)) == o
    top = res.largest_residuals(1)[0]
    assert top["photo"] == net.photo_names[net.obs_photo[o]]
    assert top["point"] == net.point_names[net.obs_point[o]]
    # the clean data flags at most a handful (alpha0 = 0.001 per coordinate)
    clean = bundle_adjust(
        make_testfield(n_photos=12, seed=4).to_bundle_data(free=("c", "x0", "y0", "k1"))
    )
    assert clean.flagged.sum() <= 6


def test_redundancy_numbers_sum_to_redundancy():
    net = make_testfield(n_photos=8, seed=5)
    res = bundle_adjust(net.to_bundle_data(free=("c", "x0", "y0", "k1")))
    # observations' redundancy numbers plus those of the weighted control = r
    s = np.nansum(res.redundancy_numbers)
    assert s < res.redundancy
    assert s > res.redundancy - 3 * 49  # control pseudo-observations take the rest


def _free_net(seed=6, n_photos=8):
    net = make_testfield(n_photos=n_photos, noise_um=2.0, seed=seed)
    d = net.to_bundle_data(free=("c", "x0", "y0", "k1"))
    d.control_sigma[:] = np.nan  # no control: free network
    d.XYZ = net.XYZ_true + np.random.default_rng(seed).normal(0, 0.05, net.XYZ_true.shape)
    return net, d


def test_free_network_inner_constraints_and_minimum_trace():
    from softplot.orientation.bundle import similarity_null_space

    net, d = _free_net()
    approx = d.XYZ.copy()
    res = bundle_adjust(d, BundleOptions(datum="free"))
    assert res.datum == "free"
    # the datum: adjusted points fit their approximations without a residual similarity
    G, _, _ = similarity_null_space(res.XYZ, res.X0, res.M)
    g = np.einsum("pai,pa->i", G, res.XYZ - approx)
    assert np.abs(g).max() < 1e-8 * np.abs(G).max() * len(approx)
    Q = res.full_point_covariance()
    P = len(approx)
    Gm = G.reshape(3 * P, 7)
    # inner constraints: G' Q = 0
    assert np.abs(Gm.T @ Q).max() < 1e-8 * np.abs(Gm).max() * np.abs(Q).max() * 3 * P
    # its diagonal blocks are the reported point covariances
    blocks = np.stack([Q[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] for i in range(P)])
    assert np.allclose(blocks, res.XYZ_cov, rtol=1e-6, atol=1e-12)
    # minimum trace: any other datum (S-transform with other constraints) has a larger trace
    rng = np.random.default_rng(0)
    tr = np.trace(Q)
    for _ in range(3):
        sub = rng.random(P) < 0.3
        C = (G * sub[:, None, None]).reshape(3 * P, 7)
        S = np.eye(3 * P) - Gm @ np.linalg.inv(C.T @ Gm) @ C.T
        Q2 = S @ Q @ S.T
        assert np.trace(Q2) > tr
        # estimable functions (e orthogonal to the similarities) keep their precision
        e = rng.standard_normal(3 * P)
        e -= Gm @ np.linalg.solve(Gm.T @ Gm, Gm.T @ e)
        assert e @ Q2 @ e == pytest.approx(e @ Q @ e, rel=1e-6)
    # shape recovered: distances between points agree with the truth
    dist = np.linalg.norm(res.XYZ[0] - res.XYZ[40])
    true = np.linalg.norm(net.XYZ_true[0] - net.XYZ_true[40])
    assert abs(dist - true) < 0.02 * true  # scale from the (perturbed) approximations


def test_free_network_scale_from_a_distance():
    net, d = _free_net(seed=7)
    a, b = d.point_names[0], d.point_names[48]
    true = float(np.linalg.norm(net.XYZ_true[0] - net.XYZ_true[48]))
    res = bundle_adjust(d, BundleOptions(datum="free", scale_distance=(a, b, true)))
    assert np.linalg.norm(res.XYZ[0] - res.XYZ[48]) == pytest.approx(true, rel=1e-9)
    # with the true scale, every other distance is right to its precision
    Q = res.full_point_covariance()
    i, j = 5, 30
    dd = np.linalg.norm(res.XYZ[i] - res.XYZ[j]) - np.linalg.norm(net.XYZ_true[i] - net.XYZ_true[j])
    ed = np.zeros(Q.shape[0])
    ud = (res.XYZ[i] - res.XYZ[j]) / np.linalg.norm(res.XYZ[i] - res.XYZ[j])
    ed[3 * i : 3 * i + 3], ed[3 * j : 3 * j + 3] = ud, -ud
    assert abs(dd) < 4 * np.sqrt(ed @ Q @ ed)
    e = np.zeros(Q.shape[0])
    u = (res.XYZ[0] - res.XYZ[48]) / true
    e[0:3], e[3 * 48 : 3 * 48 + 3] = u, -u
    assert abs(e @ Q @ e) < 1e-12  # the fixed distance has no variance


def test_initialisation_from_control_only():
    net = make_testfield(n_photos=8, seed=8)
    d = net.to_bundle_data(free=("c", "x0", "y0", "k1"))
    d.X0[:] = np.nan
    d.angles[:] = np.nan
    d.XYZ[:] = np.nan
    initialize(d)
    res = bundle_adjust(d)
    ref = bundle_adjust(net.to_bundle_data(free=("c", "x0", "y0", "k1")))
    assert np.allclose(res.intrinsics, ref.intrinsics, rtol=0, atol=1e-8)
    assert np.abs(res.X0 - net.X0_true).max() < 0.01


def test_free_network_initialised_by_relative_orientation():
    net = make_testfield(n_photos=8, seed=9, rolled=False)
    d = net.to_bundle_data(free=())
    d.X0[:] = np.nan
    d.angles[:] = np.nan
    d.XYZ[:] = np.nan
    d.control[:] = np.nan
    d.control_sigma[:] = np.nan
    d.cameras[0].values[:10] = net.intr_true[0]
    initialize(d)
    res = bundle_adjust(d, BundleOptions(datum="free"))
    assert res.converged
    assert 0.9 < res.sigma0 < 1.1
    # shape: ratios of distances equal the truth's
    r1 = np.linalg.norm(res.XYZ[0] - res.XYZ[48]) / np.linalg.norm(res.XYZ[6] - res.XYZ[42])
    r0 = np.linalg.norm(net.XYZ_true[0] - net.XYZ_true[48]) / np.linalg.norm(
        net.XYZ_true[6] - net.XYZ_true[42]
    )
    assert r1 == pytest.approx(r0, rel=1e-2)  # shape right to its precision (~0.3 %)


def test_weighted_interior_orientation_stays_near_its_prior():
    net = make_testfield(n_photos=8, seed=10)
    d = net.to_bundle_data(free=("x0", "y0", "k1"), weighted={"c": 1e-5})
    d.cameras[0].values[0] = 45.300  # certificate c, 12 um from the truth
    res = bundle_adjust(d)
    assert abs(res.intrinsics[0, 0] - 45.300) < 3e-5
    assert res.intrinsics_std[0, 0] / res.sigma0 <= 1e-5 * (1 + 1e-9)  # cofactor <= prior
    free = bundle_adjust(net.to_bundle_data(free=("c", "x0", "y0", "k1")))
    assert abs(free.intrinsics[0, 0] - net.intr_true[0, 0]) < 0.003


def test_json_has_documented_keys():
    net = make_testfield(n_photos=6, seed=11)
    res = bundle_adjust(net.to_bundle_data(free=("c",), pixel_size_mm=0.0127))
    js = res.to_json()
    for k in (
        "sigma0",
        "redundancy",
        "rms_image_um",
        "rms_image_px",
        "cameras",
        "photos",
        "points",
        "largest_residuals",
        "warnings",
    ):
        assert k in js
    assert "std" in js["cameras"][0]["parameters"]["c"]
    assert "std" in js["photos"][0]["X0"]
    assert "std" in js["points"][0]["X"]
    assert js["rms_image_px"]["xy"] == pytest.approx(js["rms_image_um"]["xy"] / 12.7, rel=1e-9)
