"""Space resection: exact recovery, precision statistics, weighted control, degeneracy."""

from __future__ import annotations

import numpy as np
import pytest

from orientation_helpers import C, aerial_points, photo
from softplot.adjust import UndeterminedError
from softplot.errors import SoftplotError
from softplot.geometry.rotation import rotation_matrix
from softplot.orientation import resect
from softplot.orientation.resection import (
    opencv_to_photogrammetric,
    p3p,
    photogrammetric_to_opencv,
)

UTM = (512000.0, 4987000.0, 300.0)


def _case(seed, n, kappa=2.4, offset=UTM):
    rng = np.random.default_rng(seed)
    X = aerial_points(rng, n, offset=offset)
    X0 = np.array([30.0, -20.0, 1500.0]) + np.asarray(offset)
    ang = np.array([0.04, -0.03, kappa])
    return rng, X, X0, ang, photo(X, X0, ang)


@pytest.mark.parametrize("n", [3, 4, 5, 8, 25])
@pytest.mark.parametrize("kappa", [0.1, 2.4, -1.7])
def test_noise_free_recovery(n, kappa):
    _, X, X0, ang, xy = _case(n, n, kappa)
    r = resect(xy, X, C)
    np.testing.assert_allclose(r.X0, X0, rtol=1e-9, atol=1e-9 * 1500)
    np.testing.assert_allclose(r.angles, ang, atol=1e-9)
    assert r.redundancy == 2 * n - 6
    if n > 3:
        assert not r.ambiguous


def test_oblique_terrestrial_photo():
    rng = np.random.default_rng(3)
    X = np.c_[rng.uniform(-20, 20, 10), rng.uniform(40, 60, 10), rng.uniform(0, 15, 10)]
    X0 = np.array([2.0, 0.0, 1.6])
    ang = np.array([np.pi / 2 + 0.05, 0.1, -0.02])  # looking horizontally along +Y
    xy = photo(X, X0, ang, 100.0, 0.1, -0.2)
    r = resect(xy, X, 100.0, 0.1, -0.2)
    np.testing.assert_allclose(r.X0, X0, atol=1e-9)
    np.testing.assert_allclose(rotation_matrix(*r.angles), rotation_matrix(*ang), atol=1e-10)


def test_p3p_contains_truth():
    rng = np.random.default_rng(9)
    for _ in range(20):
        X = aerial_points(rng, 3)
        X0 = np.array([rng.uniform(-100, 100), rng.uniform(-100, 100), 1200.0])
        ang = rng.uniform(-0.1, 0.1, 3) + [0, 0, rng.uniform(-3, 3)]
        sols = p3p(photo(X, X0, ang), X, C)
        assert 1 <= len(sols) <= 4
        err = min(np.abs(s[1] - X0).max() for s in sols)
        assert err < 1e-6


def test_opencv_conversion_round_trip():
    M = rotation_matrix(0.1, -0.2, 0.3)
    X0 = np.array([1.0, 2.0, 3.0])
    R, t = photogrammetric_to_opencv(M, X0)
    M2, X02 = opencv_to_photogrammetric(R, t)
    np.testing.assert_allclose(M2, M, atol=1e-15)
    np.testing.assert_allclose(X02, X0, atol=1e-14)
    # a point in front: OpenCV z > 0, photogrammetric z < 0; pixel y flips
    P = np.array([5.0, 7.0, -100.0])
    xc = R @ P + t
    u = M @ (P - X0)
    assert xc[2] > 0 > u[2]
    np.testing.assert_allclose(100 * xc[:2] / xc[2], [-100 * u[0] / u[2], 100 * u[1] / u[2]])


def test_noise_statistics_sigma0_and_covariance():
    sig = 0.004
    rng, X, X0, ang, xy = _case(11, 12)
    s02, d, cov_rep, chi = [], [], [], []
    for _ in range(1000):
        r = resect(xy + rng.normal(0, sig, xy.shape), X, C, sigma_xy=sig)
        s02.append(r.sigma0**2)
        e = r.params - np.r_[X0, ang]
        d.append(e)
        cov_rep.append(np.diag(r.covariance))
        Qp = r.adjustment.cofactor[:6, :6] * sig**2  # a priori covariance
        chi.append(e @ np.linalg.solve(Qp, e))
    assert np.mean(s02) == pytest.approx(sig**2, rel=0.04)
    ratio = np.var(np.array(d), axis=0) / np.mean(np.array(cov_rep), axis=0)
    np.testing.assert_allclose(ratio, 1.0, atol=0.15)
    assert np.mean(chi) == pytest.approx(6.0, rel=0.06)  # chi2(6) with the full covariance


def test_weighted_control_moves_with_its_sigma():
    rng, X, X0, ang, xy = _case(5, 8, offset=(0, 0, 0))
    Xbad = X.copy()
    Xbad[0] += [0.5, -0.4, 0.3]  # a control point 0.5 m off
    s = np.full((8, 3), np.nan)
    s[0] = 1000.0  # very weak control point: one photo fixes it across its ray only
    r = resect(xy, Xbad, C, sigma_xy=0.002, sigma_XYZ=s)
    np.testing.assert_allclose(r.X0, X0, atol=1e-6)
    np.testing.assert_allclose(r.angles, ang, atol=1e-9)
    assert r.adjustment.names[6:9] == ("X_0", "Y_0", "Z_0")
    assert r.redundancy == 2 * 8 - 6
    # the adjusted control point lies on its ray; the (equal-sigma) correction is orthogonal
    np.testing.assert_allclose(photo(r.control[:1], X0, ang), xy[:1], atol=1e-9)
    ray = (X[0] - X0) / np.linalg.norm(X[0] - X0)
    assert abs((r.control[0] - Xbad[0]) @ ray) < 1e-6
    # a strong control point behaves like fixed control
    s[0] = 1e-4
    strong = resect(xy, Xbad, C, sigma_xy=0.002, sigma_XYZ=s)
    fixed = resect(xy, Xbad, C, sigma_xy=0.002)
    np.testing.assert_allclose(strong.X0, fixed.X0, atol=2e-3)
    assert not np.allclose(strong.X0, X0, atol=1e-3)


def test_blunder_flagged():
    rng, X, X0, ang, xy = _case(21, 15)
    xy = xy + rng.normal(0, 0.003, xy.shape)
    xy[6, 1] += 0.06  # 20 sigma
    r = resect(xy, X, C, sigma_xy=0.003)
    assert r.flagged[6]
    w = np.abs(r.standardized)
    assert np.unravel_index(np.nanargmax(w), w.shape)[0] == 6


def test_collinear_control_named_error():
    X = np.c_[np.linspace(0, 300, 6), np.linspace(0, 90, 6), np.zeros(6)]
    xy = photo(X, [150.0, 20.0, 900.0], [0.01, 0.02, 0.3])
    with pytest.raises(UndeterminedError, match="not determined: .*omega") as e:
        resect(xy, X, C)
    assert {"omega", "phi"} & set(e.value.names)


@pytest.mark.parametrize(
    "args, msg",
    [
        ((np.zeros((2, 2)), np.zeros((2, 3)), C), ">= 3 control points"),
        ((np.zeros((4, 2)), np.zeros((3, 3)), C), "control must be"),
        ((np.zeros((4, 3)), np.zeros((4, 3)), C), r"\(N,2\)"),
        ((np.full((4, 2), np.nan), np.zeros((4, 3)), C), "finite"),
        ((np.zeros((4, 2)), np.zeros((4, 3)), -1.0), "principal distance"),
    ],
)
def test_bad_inputs(args, msg):
    with pytest.raises(SoftplotError, match=msg):
        resect(*args)
