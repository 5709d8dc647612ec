"""Absolute orientation (7-parameter similarity): exact, statistics, weights, degeneracy."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.adjust import UndeterminedError
from softplot.errors import SoftplotError
from softplot.orientation import absolute_orientation
from softplot.orientation.absolute import kabsch, transform

TRUTH = np.array([2.5, 0.03, -0.02, 1.9, 512300.0, 4987100.0, 240.0])


def _model(rng, n=8):
    return np.c_[rng.uniform(-100, 300, n), rng.uniform(-150, 150, n), rng.uniform(-600, -540, n)]


def test_noise_free_recovery():
    m = _model(np.random.default_rng(0))
    obj = transform(TRUTH, m)
    r = absolute_orientation(m, obj)
    np.testing.assert_allclose(r.params, TRUTH, rtol=1e-10, atol=1e-10)
    assert r.redundancy == 3 * 8 - 7
    np.testing.assert_allclose(r.apply(m), obj, atol=1e-7)


def test_kabsch_umeyama_closed_form():
    rng = np.random.default_rng(1)
    m = _model(rng)
    s, R, t = kabsch(m, transform(TRUTH, m), with_scale=True)
    assert s == pytest.approx(TRUTH[0], rel=1e-12)
    np.testing.assert_allclose(t, TRUTH[4:], rtol=1e-12, atol=1e-8)


def test_height_only_and_plan_only_control():
    m = _model(np.random.default_rng(2), 6)
    obj = transform(TRUTH, m)
    obj[3, :2] = np.nan  # height-only point
    obj[4, 2] = np.nan  # plan-only point
    r = absolute_orientation(m, obj)
    np.testing.assert_allclose(r.params, TRUTH, rtol=1e-9, atol=1e-9)
    assert r.redundancy == 18 - 3 - 7
    assert np.isnan(r.residuals[3, 0]) and np.isfinite(r.residuals[3, 2])


def test_statistics_and_weights():
    rng = np.random.default_rng(3)
    m = _model(rng, 10)
    obj = transform(TRUTH, m)
    sig = np.tile([0.05, 0.05, 0.1], (10, 1))
    s02, err, var, chi = [], [], [], []
    for _ in range(1500):
        r = absolute_orientation(m, obj + rng.normal(0, sig), sig)
        s02.append(r.sigma0**2)
        e = r.params - TRUTH
        err.append(e)
        var.append(np.diag(r.covariance))
        chi.append(e @ np.linalg.solve(r.adjustment.cofactor, e))
    assert np.mean(s02) == pytest.approx(1.0, rel=0.04)  # sigma0 is a ratio here (prior 1)
    ratio = np.var(np.array(err), axis=0) / np.mean(np.array(var), axis=0)
    np.testing.assert_allclose(ratio, 1.0, atol=0.15)
    assert np.mean(chi) == pytest.approx(7.0, rel=0.05)


def test_blunder_flagged():
    rng = np.random.default_rng(4)
    m = _model(rng, 12)
    obj = transform(TRUTH, m) + rng.normal(0, 0.02, (12, 3))
    obj[5, 2] += 0.4
    r = absolute_orientation(m, obj, 0.02, names=[f"P{i}" for i in range(12)])
    assert r.flagged[5]
    assert np.unravel_index(np.nanargmax(np.abs(r.standardized)), (12, 3)) == (5, 2)


def test_collinear_control_named_error():
    t = np.linspace(0, 1, 5)[:, None]
    m = t * [100.0, 50.0, 10.0]
    with pytest.raises(UndeterminedError, match="not determined: .*(omega|phi|kappa)"):
        absolute_orientation(m, transform(TRUTH, m))


def test_bad_inputs():
    with pytest.raises(SoftplotError, match=r"\(N,3\)"):
        absolute_orientation(np.zeros((4, 3)), np.zeros((4, 2)))
    with pytest.raises(SoftplotError, match=">= 7"):
        absolute_orientation(np.zeros((2, 3)), np.zeros((2, 3)))
