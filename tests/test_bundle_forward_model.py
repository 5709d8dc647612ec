"""The forward lens model: exact Jacobians, and an unbiased sigma0 (Monte Carlo)."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.geometry.rotation import rotation_matrix
from softplot.orientation.bundle import BundleOptions, _Model, _State, bundle_adjust
from softplot.synthetic.network import film_from_object
from softplot.synthetic.testfield import make_testfield

FREE = ("c", "x0", "y0", "k1", "k2", "p1", "p2")
#: a strongly distorting wide-angle camera: k1 r^2 = 7 % at the format corner
STRONG = np.array([45.312, 0.0125, -0.0207, 1.5e-5, -1.5e-9, 0.0, 2e-6, -1.5e-6, 0, 0, 0])
SIGMA = 0.002  # mm


def _data(net, model, intr=STRONG, free=FREE):
    d = net.to_bundle_data(free=free)
    d.cameras[0].model = model
    d.cameras[0].values[:] = intr
    d.X0[:], d.angles[:], d.XYZ[:] = net.X0_true, net.angles_true, net.XYZ_true
    d.sigma_xy[:] = SIGMA
    return d


def _predict(d, intr):
    """Image points of the model with the data's values (residual at measured = 0)."""
    d.xy[:] = 0.0
    m = _Model(d, np.ones((len(d.point_names), 3), bool))
    M = rotation_matrix(d.angles[:, 0], d.angles[:, 1], d.angles[:, 2])
    return m.unwhiten(m.evaluate(_State(d.X0, M, np.atleast_2d(intr), d.XYZ), False).r)


@pytest.mark.parametrize("model", ["forward", "inverse"])
def test_jacobians_match_finite_differences(model):
    net = make_testfield(n_photos=4, seed=1)
    intr = np.array([45.3, 0.02, -0.01, 8e-6, -1e-9, 2e-13, 3e-6, -2e-6, 1e-4, -2e-4, 3e-3])
    d = _data(
        net, model, intr, free=("c", "x0", "y0", "k1", "k2", "k3", "p1", "p2", "b1", "b2", "a")
    )
    rng = np.random.default_rng(0)
    d.xy += rng.normal(0, 0.01, d.xy.shape)
    d.cov_xy = 0.3 * SIGMA**2 * np.ones(d.obs_photo.size)
    d.__post_init__()
    model_ = _Model(d, np.ones((len(d.point_names), 3), bool))
    M = rotation_matrix(d.angles[:, 0], d.angles[:, 1], d.angles[:, 2])
    st = _State(d.X0.copy(), M, intr[None].copy(), d.XYZ.copy())
    ev = model_.evaluate(st, True)
    n = model_.n_cam
    cols = model_.structure.obs_cols
    for j in range(n):
        # columns: 4 photos x 6, then c, x0, y0, k1, k2, k3, p1, p2, b1, b2, a
        h = {24: 1e-6, 27: 1e-10, 28: 1e-14, 29: 1e-18, 30: 1e-9, 31: 1e-9}.get(j, 1e-7)
        e = np.zeros(n)
        e[j] = h
        rp = model_.evaluate(model_.retract(st, e, np.zeros_like(st.XYZ)), False).r
        rm = model_.evaluate(model_.retract(st, -e, np.zeros_like(st.XYZ)), False).r
        num = (rp - rm) / (2 * h)
        ana = np.zeros_like(num)
        o, k = np.nonzero(cols == j)
        ana[o] = ev.Jc[o, :, k]
        scale = np.abs(num).max() + 1e-12
        assert np.abs(num - ana).max() < 2e-5 * scale, (j, np.abs(num - ana).max(), scale)
    for a in range(3):
        e = np.zeros_like(st.XYZ)
        e[:, a] = 1e-6
        rp = model_.evaluate(model_.retract(st, np.zeros(n), e), False).r
        rm = model_.evaluate(model_.retract(st, np.zeros(n), -e), False).r
        num = (rp - rm) / 2e-6
        assert np.abs(num - ev.Jp[:, :, a]).max() < 2e-5 * np.abs(num).max()


def test_forward_model_monte_carlo_sigma0_and_spread():
    """Strong distortion, noise in the measured image: with the forward model the mean
    sigma0 is within 1 % of 1 and every interior parameter's empirical spread within 10 %
    of its reported standard deviation (500 trials); the inverse model biases sigma0."""
    net = make_testfield(n_photos=10, noise_um=0, control_sigma_m=0.0, seed=0)
    xy_true = _predict(_data(net, "forward"), STRONG)
    rng = np.random.default_rng(1)
    idx = [0, 1, 2, 3, 4, 6, 7]  # c, x0, y0, k1, k2, p1, p2
    s0, err, std = [], [], []
    for _ in range(500):
        d = _data(net, "forward")
        d.xy[:] = xy_true + rng.normal(0, SIGMA, xy_true.shape)
        res = bundle_adjust(d, BundleOptions())
        s0.append(res.sigma0)
        err.append(res.intrinsics[0, idx] - STRONG[idx])
        std.append(res.intrinsics_std[0, idx])
    assert abs(np.mean(s0) - 1.0) < 0.01, np.mean(s0)
    ratio = np.std(err, axis=0) / np.mean(std, axis=0)
    assert np.all(np.abs(ratio - 1.0) < 0.10), ratio
    assert np.all(np.abs(np.mean(err, axis=0)) < 4 * np.mean(std, axis=0) / np.sqrt(500))
    # the inverse model on measurements it describes exactly (noise added in the measured
    # image): its residual carries the noise through I - d(dx)/dx, sigma0 is biased (here
    # low: this k1 shrinks the noise; a barrel lens inflates it)
    xy_inv = np.empty_like(xy_true)
    for f in range(len(net.photo_names)):
        o = net.obs_photo == f
        xy_inv[o], _ = film_from_object(
            net.XYZ_true[net.obs_point[o]], net.X0_true[f], net.M_true[f], STRONG[:10]
        )
    s0_inv = []
    for _ in range(100):
        d = _data(net, "inverse")
        d.xy[:] = xy_inv + rng.normal(0, SIGMA, xy_inv.shape)
        s0_inv.append(bundle_adjust(d, BundleOptions()).sigma0)
    assert abs(np.mean(s0_inv) - 1.0) > 0.01, np.mean(s0_inv)


def test_forward_is_the_default_for_self_calibration(tmp_path):
    """No ``lens`` in cameras.toml: forward once a distortion parameter is freed (also by
    --free), inverse for a fixed lens; an explicit ``lens`` is kept."""
    from softplot.cli._bundle_common import apply_free
    from softplot.orientation.bundle_io import read_project, write_project

    net = make_testfield(n_photos=4, seed=0)
    write_project(tmp_path / "p", net.to_bundle_data(free=("c",)))
    toml = tmp_path / "p" / "cameras.toml"
    explicit = toml.read_text()
    assert 'lens = "inverse"' in explicit
    toml.write_text(explicit.replace('lens = "inverse"\n', ""))
    d = read_project(tmp_path / "p")
    assert d.cameras[0].model == "inverse"  # only c free: the lens is known
    apply_free(d, ("c", "x0", "y0", "k1"))
    assert d.cameras[0].model == "forward"
    toml.write_text(explicit.replace('free = ["c"]', 'free = ["c", "k1"]'))
    e = read_project(tmp_path / "p")
    apply_free(e, ("c", "k1"))
    assert e.cameras[0].model == "inverse"  # as the file says


def test_mixed_lens_models_in_one_block():
    """Two physical cameras, one forward and one inverse: each photo's residuals and
    Jacobians are those of its own camera's model."""
    import dataclasses

    net = make_testfield(n_photos=6, seed=3)
    d = _data(net, "forward", STRONG)
    d.xy += np.random.default_rng(0).normal(0, 0.01, d.xy.shape)
    inv = dataclasses.replace(d.cameras[0], name="inv", model="inverse")
    d.cameras.append(inv)
    d.photo_camera[1::2] = 1
    M = rotation_matrix(d.angles[:, 0], d.angles[:, 1], d.angles[:, 2])
    P = len(d.point_names)
    intr = np.array([STRONG, STRONG])
    ev = _Model(d, np.ones((P, 3), bool)).evaluate(_State(d.X0, M, intr, d.XYZ), True)
    for cam, model in ((0, "forward"), (1, "inverse")):
        e = dataclasses.replace(
            d,
            cameras=[dataclasses.replace(d.cameras[0], model=model)],
            photo_camera=np.zeros(len(d.photo_names), int),
        )
        one = _Model(e, np.ones((P, 3), bool)).evaluate(_State(d.X0, M, STRONG[None], d.XYZ), True)
        o = d.photo_camera[d.obs_photo] == cam
        np.testing.assert_allclose(ev.r[o], one.r[o], rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(ev.Jp[o], one.Jp[o], rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(ev.Jc[o], one.Jc[o], rtol=1e-13, atol=1e-9)
