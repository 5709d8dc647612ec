"""Relative orientation (coplanarity, Gauss-Helmert): exact, statistics, y-parallax, blunders."""

from __future__ import annotations

import numpy as np
import pytest

from orientation_helpers import stereo_pair
from softplot.adjust import UndeterminedError
from softplot.errors import SoftplotError
from softplot.geometry.collinearity import project
from softplot.geometry.rotation import angles_from_matrix, rotation_matrix
from softplot.orientation import relative_orientation
from softplot.orientation.relative import PARAMS

BX = 100.0


def _truth_dependent(s):
    M1 = rotation_matrix(*s["a1"])
    M2 = rotation_matrix(*s["a2"])
    b = M1 @ (s["C2"] - s["C1"])
    scale = BX / b[0]
    X = scale * (s["X"] - s["C1"]) @ M1.T  # object -> left photo frame, scaled
    return b * scale, np.array(angles_from_matrix(M2 @ M1.T)), X


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dependent_noise_free(seed):
    s = stereo_pair(np.random.default_rng(seed))
    b, a2, X = _truth_dependent(s)
    r = relative_orientation(s["xy1"], s["xy2"], s["c"], bx=BX)
    np.testing.assert_allclose(r.base, b, rtol=1e-9, atol=1e-9 * BX)
    np.testing.assert_allclose(r.angles2, a2, atol=1e-9)
    np.testing.assert_allclose(r.angles1, 0.0)
    np.testing.assert_allclose(r.points.XYZ, X, rtol=1e-9, atol=1e-9 * BX)
    assert np.abs(r.py).max() < 1e-9
    assert r.redundancy == len(X) - 5


@pytest.mark.parametrize("n", [6, 7, 9])
@pytest.mark.parametrize("seed", [4, 5, 6])
def test_few_points_noise_free(n, seed):
    # LMedS cannot choose among the five-point roots with few points; every root is ranked
    s = stereo_pair(np.random.default_rng(seed), n=n)
    b, a2, _ = _truth_dependent(s)
    r = relative_orientation(s["xy1"], s["xy2"], s["c"], bx=BX)
    np.testing.assert_allclose(r.base, b, rtol=1e-8, atol=1e-8 * BX)
    np.testing.assert_allclose(r.angles2, a2, atol=1e-8)


@pytest.mark.parametrize("seed", [0, 3])
def test_independent_noise_free_is_a_rotation_of_dependent(seed):
    s = stereo_pair(np.random.default_rng(seed))
    dep = relative_orientation(s["xy1"], s["xy2"], s["c"], bx=BX)
    ind = relative_orientation(s["xy1"], s["xy2"], s["c"], bx=BX, mode="independent")
    np.testing.assert_allclose(ind.base, [BX, 0, 0], rtol=1e-12)
    assert ind.value("omega1") == 0.0
    M1 = rotation_matrix(*ind.angles1)
    # same model up to the rotation M1 and the scale |b_dep| / bx
    k = BX / np.linalg.norm(dep.base)
    np.testing.assert_allclose(ind.points.XYZ @ M1.T, k * dep.points.XYZ, atol=1e-8)
    # the rays of both photos pass exactly through the model points
    for X0, ang, xy in ((np.zeros(3), ind.angles1, s["xy1"]), (ind.base, ind.angles2, s["xy2"])):
        np.testing.assert_allclose(
            project(ind.points.XYZ, X0, rotation_matrix(*ang), s["c"]), xy, atol=1e-9
        )


def test_sigma0_and_covariance_statistics():
    rng = np.random.default_rng(7)
    s = stereo_pair(rng, n=30)
    sig = 0.004
    exact = relative_orientation(s["xy1"], s["xy2"], s["c"], bx=BX)
    truth = exact.params
    free = [PARAMS.index(p) for p in exact.free]
    s02, err, var, chi = [], [], [], []
    for _ in range(600):
        # the essential-matrix start is tested above; start at the truth to save time
        r = relative_orientation(
            s["xy1"] + rng.normal(0, sig, (30, 2)),
            s["xy2"] + rng.normal(0, sig, (30, 2)),
            s["c"],
            bx=BX,
            sigma=sig,
            start=truth,
        )
        s02.append(r.sigma0**2)
        e = (r.params - truth)[free]
        err.append(e)
        var.append(np.diag(r.covariance))
        chi.append(e @ np.linalg.solve(r.adjustment.cofactor[np.ix_(free, free)] * sig**2, e))
    assert np.mean(s02) == pytest.approx(sig**2, rel=0.05)
    ratio = np.var(np.array(err), axis=0) / np.mean(np.array(var), axis=0)
    np.testing.assert_allclose(ratio, 1.0, atol=0.2)
    assert np.mean(chi) == pytest.approx(5.0, rel=0.08)


def test_dependent_and_independent_same_fit_with_noise():
    rng = np.random.default_rng(8)
    s = stereo_pair(rng)
    xy1 = s["xy1"] + rng.normal(0, 0.005, s["xy1"].shape)
    xy2 = s["xy2"] + rng.normal(0, 0.005, s["xy2"].shape)
    dep = relative_orientation(xy1, xy2, s["c"], bx=BX)
    ind = relative_orientation(xy1, xy2, s["c"], bx=BX, mode="independent")
    assert ind.sigma0 == pytest.approx(dep.sigma0, rel=1e-7)
    np.testing.assert_allclose(ind.py, dep.py, atol=2e-5)
    np.testing.assert_allclose(ind.residuals, dep.residuals, atol=1e-8)
    assert 0.5 * 0.005 < dep.sigma0 < 1.5 * 0.005


def test_y_parallax_blunder_flagged():
    rng = np.random.default_rng(9)
    s = stereo_pair(rng, n=25)
    xy1 = s["xy1"] + rng.normal(0, 0.003, s["xy1"].shape)
    xy2 = s["xy2"] + rng.normal(0, 0.003, s["xy2"].shape)
    xy2[12, 1] += 0.06
    names = [f"p{i}" for i in range(25)]
    r = relative_orientation(xy1, xy2, s["c"], bx=BX, sigma=0.003, names=names)
    assert r.flagged[12]
    assert int(np.argmax(np.abs(r.py))) == 12
    assert r.flagged.sum() <= 2


def test_too_few_points_named():
    s = stereo_pair(np.random.default_rng(1), n=4)
    with pytest.raises(UndeterminedError, match="not determined: by, bz, omega2, phi2, kappa2"):
        relative_orientation(s["xy1"], s["xy2"], s["c"], bx=BX)


def test_bad_inputs():
    s = stereo_pair(np.random.default_rng(1), n=8)
    with pytest.raises(SoftplotError, match="both be"):
        relative_orientation(s["xy1"], s["xy2"][:5], s["c"])
    with pytest.raises(SoftplotError, match="unknown mode"):
        relative_orientation(s["xy1"], s["xy2"], s["c"], mode="x")
    with pytest.raises(SoftplotError, match="bx"):
        relative_orientation(s["xy1"], s["xy2"], s["c"], bx=0.0)
