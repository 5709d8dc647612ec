"""Space intersection: exact, precision per point, degenerate rays, vectorised interface."""

from __future__ import annotations

import numpy as np
import pytest

from orientation_helpers import C, photo
from softplot.adjust import UndeterminedError
from softplot.errors import SoftplotError
from softplot.orientation import intersect, intersect_pair

PHOTOS_X0 = np.array([[0.0, 0.0, 1500.0], [600.0, 10.0, 1510.0], [1200.0, -5.0, 1495.0]])
PHOTOS_ANG = np.array([[0.01, -0.02, 0.03], [-0.02, 0.01, -0.04], [0.0, 0.03, 0.02]])


def _obs(X, photos=(0, 1, 2)):
    xy, pt, ph = [], [], []
    for f in photos:
        xy.append(photo(X, PHOTOS_X0[f], PHOTOS_ANG[f]))
        pt.append(np.arange(len(X)))
        ph.append(np.full(len(X), f))
    return np.vstack(xy), np.concatenate(pt), np.concatenate(ph)


def _points(rng, n):
    return np.c_[rng.uniform(400, 800, n), rng.uniform(-400, 400, n), rng.uniform(-30, 80, n)]


@pytest.mark.parametrize("photos", [(0, 1), (1, 2), (0, 1, 2)])
def test_noise_free(photos):
    X = _points(np.random.default_rng(1), 50)
    xy, pt, ph = _obs(X, photos)
    r = intersect(xy, pt, ph, PHOTOS_X0, PHOTOS_ANG, C)
    np.testing.assert_allclose(r.XYZ, X, rtol=1e-9, atol=1e-9 * 1500)
    assert np.all(r.redundancy == 2 * len(photos) - 3)
    assert np.all(r.n_rays == len(photos))
    assert r.rms.max() < 1e-9


def test_precision_statistics_vectorised():
    # 3000 independent points in one call: sigma0 and covariance against the empirical errors
    rng = np.random.default_rng(2)
    sig = 0.005
    X = _points(rng, 3000)
    xy, pt, ph = _obs(X)
    r = intersect(xy + rng.normal(0, sig, xy.shape), pt, ph, PHOTOS_X0, PHOTOS_ANG, C, sigma=sig)
    assert r.sigma0_pooled == pytest.approx(sig, rel=0.03)
    e = r.XYZ - X
    chi = np.einsum("pi,pij,pj->p", e, np.linalg.inv(r.cofactor * sig**2), e)
    assert np.mean(chi) == pytest.approx(3.0, rel=0.05)
    ratio = np.mean(e**2, axis=0) / np.mean(np.einsum("pii->pi", r.covariance), axis=0)
    np.testing.assert_allclose(ratio, 1.0, atol=0.1)
    assert np.nanmean(r.sigma0**2) == pytest.approx(sig**2, rel=0.05)
    # Z is the weak coordinate of a vertical pair
    assert np.all(r.std[:, 2] > r.std[:, 0])


def test_covariance_modes():
    rng = np.random.default_rng(3)
    X = _points(rng, 20)
    xy, pt, ph = _obs(X)
    xy = xy + rng.normal(0, 0.004, xy.shape)
    a = intersect(xy, pt, ph, PHOTOS_X0, PHOTOS_ANG, C, sigma=0.004, covariance="prior")
    np.testing.assert_allclose(a.covariance, a.cofactor * 0.004**2)
    b = intersect(xy, pt, ph, PHOTOS_X0, PHOTOS_ANG, C, sigma=0.004, covariance="point")
    np.testing.assert_allclose(b.covariance[0], b.cofactor[0] * b.sigma0[0] ** 2)


def test_pair_wrapper_and_blunder():
    rng = np.random.default_rng(4)
    X = _points(rng, 10)
    xy1 = photo(X, PHOTOS_X0[0], PHOTOS_ANG[0])
    xy2 = photo(X, PHOTOS_X0[1], PHOTOS_ANG[1])
    r = intersect_pair(xy1, xy2, PHOTOS_X0[0], PHOTOS_ANG[0], PHOTOS_X0[1], PHOTOS_ANG[1], C)
    np.testing.assert_allclose(r.XYZ, X, atol=1e-8)
    # a y-parallax blunder in a two-ray point is detectable (x-parallax is not: it is depth)
    X = _points(rng, 5)
    xy, pt, ph = _obs(X)
    xy = xy + rng.normal(0, 0.003, xy.shape)
    xy[7, 1] += 0.05
    r = intersect(xy, pt, ph, PHOTOS_X0, PHOTOS_ANG, C, sigma=0.003)
    assert r.flagged[pt[7]]
    assert r.flagged.sum() == 1


def test_single_ray_and_parallel_rays_named():
    X = _points(np.random.default_rng(5), 3)
    xy, pt, ph = _obs(X, (0, 1))
    keep = ~((pt == 1) & (ph == 1))
    with pytest.raises(UndeterminedError, match="point.*B.*not determined") as e:
        intersect(
            xy[keep], pt[keep], ph[keep], PHOTOS_X0, PHOTOS_ANG, C, point_names=["A", "B", "C"]
        )
    assert e.value.names == ("X_B", "Y_B", "Z_B")
    # two photos from the same centre: parallel (identical) rays
    X0 = np.array([PHOTOS_X0[0], PHOTOS_X0[0]])
    ang = np.array([PHOTOS_ANG[0], PHOTOS_ANG[0] + [0, 0, 0.1]])
    xy = np.r_[photo(X, X0[0], ang[0]), photo(X, X0[1], ang[1])]
    with pytest.raises(UndeterminedError, match="not determined"):
        intersect(xy, np.r_[0:3, 0:3], np.r_[[0] * 3, [1] * 3], X0, ang, C)


def test_bad_inputs():
    with pytest.raises(SoftplotError, match="indices"):
        intersect(np.zeros((4, 2)), [0, 0, 1], [0, 1, 0, 1], PHOTOS_X0, PHOTOS_ANG, C)
    with pytest.raises(SoftplotError, match="photo index"):
        intersect(np.zeros((2, 2)), [0, 0], [0, 5], PHOTOS_X0, PHOTOS_ANG, C)
    with pytest.raises(SoftplotError, match="covariance mode"):
        intersect(np.zeros((2, 2)), [0, 0], [0, 1], PHOTOS_X0, PHOTOS_ANG, C, covariance="x")
