"""Plane transforms: exact recovery, precision (covariance vs Monte Carlo), inverses, errors."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.errors import SoftplotError
from softplot.geometry import KINDS, MIN_POINTS, fit_transform, transform_points
from softplot.geometry.transforms import N_PARAMS, from_params

# natural parameters mapping scan pixels (0..5000) to film mm: 2400 dpi-like scale, small
# rotation, a y flip, and higher-order terms of the size film deformation would give
TRUE = {
    "similarity": [0.0105, 0.0003, -26.0, -27.0],
    "affine": [0.0105, 0.0001, -26.0, 0.0002, -0.0104, 27.0],
    "projective": [0.0105, 0.0001, -26.0, 0.0002, -0.0104, 27.0, 1e-7, -2e-7],
    "bilinear": [-26.0, 0.0105, 0.0001, 1e-9, 27.0, 0.0002, -0.0104, -2e-9],
    "poly2": [-26.0, 0.0105, 0.0001, 1e-9, 2e-9, -1e-9, 27.0, 0.0002, -0.0104, -2e-9, 1e-9, 3e-9],
    "poly3": [
        -26.0, 0.0105, 0.0001, 1e-9, 2e-9, -1e-9, 1e-13, 2e-13, -1e-13, 3e-13,
        27.0, 0.0002, -0.0104, -2e-9, 1e-9, 3e-9, 1e-13, 2e-13, -1e-13, 3e-13,
    ],
}


def _src(n=40, seed=1):
    return np.random.default_rng(seed).uniform(0, 5000, (n, 2))


@pytest.mark.parametrize("kind", KINDS)
def test_exact_parameters_recovered(kind):
    src = _src()
    p = np.array(TRUE[kind])
    dst = transform_points(kind, p, src)
    t = fit_transform(kind, src, dst)
    assert t.params.shape == (N_PARAMS[kind],)
    np.testing.assert_allclose(t.params, p, rtol=1e-8, atol=1e-18)
    assert t.sigma0 < 1e-9
    assert np.abs(t.residuals).max() < 1e-9
    assert t.redundancy == 2 * 40 - N_PARAMS[kind]
    # forward reproduces the natural model elsewhere too
    q = _src(200, seed=5)
    np.testing.assert_allclose(t.forward(q), transform_points(kind, p, q), atol=1e-9)


@pytest.mark.parametrize("kind", KINDS)
def test_inverse_round_trip(kind):
    src = _src()
    dst = transform_points(kind, TRUE[kind], src)
    t = fit_transform(kind, src, dst)
    q = _src(5000, seed=7)
    back = t.inverse(t.forward(q))
    assert np.abs(back - q).max() < 1e-7  # px


def test_bilinear_inverse_closed_form_under_90_degree_rotation():
    # x and y swap roles: the quadratic must still pick the right root
    p = [10.0, 1e-6, 0.5, 2e-5, -3.0, -0.5, 1e-6, -1e-5]
    src = _src(30)
    t = fit_transform("bilinear", src, transform_points("bilinear", p, src))
    q = _src(1000, seed=3)
    assert np.abs(t.inverse(t.forward(q)) - q).max() < 1e-7


@pytest.mark.parametrize("kind", KINDS)
def test_minimum_point_count(kind):
    need = MIN_POINTS[kind]
    src = _src(need, seed=11)
    dst = transform_points(kind, TRUE[kind], src)
    t = fit_transform(kind, src, dst)  # exactly determined
    assert t.redundancy in (0, 1)
    np.testing.assert_allclose(t.forward(src), dst, atol=1e-8)
    msg = rf"{kind} transform needs at least {need} points, got {need - 1}"
    with pytest.raises(SoftplotError, match=msg):
        fit_transform(kind, src[:-1], dst[:-1])


def test_exactly_determined_has_nan_sigma0_but_a_cofactor():
    src = _src(4)
    t = fit_transform("projective", src, transform_points("projective", TRUE["projective"], src))
    assert t.redundancy == 0
    assert np.isnan(t.sigma0)
    assert np.all(np.isnan(t.covariance))
    assert np.all(np.isfinite(t.cofactor))


@pytest.mark.parametrize("kind", ["affine", "projective", "poly2"])
def test_degenerate_configuration(kind):
    x = np.linspace(0, 100, 20)
    src = np.column_stack([x, 2 * x + 1])  # collinear
    with pytest.raises(SoftplotError, match="degenerate"):
        fit_transform(kind, src, src * 0.01)


def test_bad_input():
    with pytest.raises(SoftplotError, match="unknown transform"):
        fit_transform("spline", _src(5), _src(5))
    with pytest.raises(SoftplotError, match="finite"):
        s = _src(5)
        s[2, 0] = np.nan
        fit_transform("affine", s, _src(5))
    with pytest.raises(SoftplotError, match="5 source points but 4"):
        fit_transform("affine", _src(5), _src(4))
    with pytest.raises(SoftplotError, match="weights"):
        fit_transform("affine", _src(5), _src(5), weights=[1, 1, -1, 1, 1])


@pytest.mark.parametrize("kind", KINDS)
def test_covariance_matches_monte_carlo(kind):
    rng = np.random.default_rng(42)
    src = _src(30, seed=2)
    dst = transform_points(kind, TRUE[kind], src)
    sigma = 0.003  # mm
    t = fit_transform(kind, src, dst)
    pred = sigma**2 * t.cofactor
    runs = np.array(
        [fit_transform(kind, src, dst + rng.normal(0, sigma, dst.shape)).params for _ in range(600)]
    )
    var = runs.var(axis=0, ddof=1)
    ratio = var / np.diag(pred)
    # 599 degrees of freedom: the ratio's standard deviation is about 0.058
    assert np.all((ratio > 0.75) & (ratio < 1.25)), ratio
    # correlations too (the off-diagonal structure), on the strongest pairs
    C = np.cov(runs.T)
    d = np.sqrt(np.diag(pred))
    rho_pred = pred / np.outer(d, d)
    rho_mc = C / np.outer(np.sqrt(np.diag(C)), np.sqrt(np.diag(C)))
    assert np.abs(rho_pred - rho_mc).max() < 0.15


def test_sigma0_and_weights():
    rng = np.random.default_rng(3)
    src = _src(400, seed=4)
    dst = transform_points("affine", TRUE["affine"], src)
    sig = np.where(np.arange(400) % 2 == 0, 0.001, 0.004)
    noisy = dst + rng.normal(0, 1, dst.shape) * sig[:, None]
    t = fit_transform("affine", src, noisy, weights=(0.001 / sig) ** 2)
    # weights relative to a unit-weight sigma of 1 um: sigma0 estimates it
    assert abs(t.sigma0 - 0.001) < 0.0001
    assert np.allclose(t.covariance, t.sigma0**2 * t.cofactor)
    tu = fit_transform("affine", src, noisy)
    assert np.trace(t.covariance) < np.trace(tu.covariance)  # weighting helps


@pytest.mark.parametrize("kind", KINDS)
def test_point_jacobian_vs_finite_differences(kind):
    src = _src()
    t = fit_transform(kind, src, transform_points(kind, TRUE[kind], src))
    q = _src(20, seed=9)
    J = t.jacobian(q)
    h = 1e-3
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        num = (t.forward(q + e) - t.forward(q - e)) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], num, rtol=1e-6, atol=1e-12)


@pytest.mark.parametrize("kind", KINDS)
def test_from_params_evaluates_like_the_fit(kind):
    src = _src()
    p = TRUE[kind]
    t = from_params(kind, p, src_scale_hint=src)
    np.testing.assert_allclose(t.forward(src), transform_points(kind, p, src), atol=1e-9)
    np.testing.assert_allclose(t.params, p)


def test_matrix_kinds():
    src = _src()
    t = fit_transform("similarity", src, transform_points("similarity", TRUE["similarity"], src))
    M = t.matrix()
    h = np.column_stack([src, np.ones(len(src))]) @ M.T
    np.testing.assert_allclose(h[:, :2] / h[:, 2:], t.forward(src), atol=1e-10)
    with pytest.raises(SoftplotError, match="no 3x3 matrix"):
        fit_transform("poly2", src, transform_points("poly2", TRUE["poly2"], src)).matrix()
