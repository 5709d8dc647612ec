"""Birardi 1980: projection centre by two planes, f, fiducial resection, differential."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.adjust import UndeterminedError
from softplot.errors import SoftplotError
from softplot.orientation import differential, fiducial_resection, principal_distance, two_planes
from softplot.orientation.two_planes import plane_readings

F = 152.3  # mm, the projector's principal distance
PC = np.array([100.25, 200.31, 350.0])  # instrument mm
Z1, Z2 = 100.0, 250.0
G = np.arange(-80.0, 81.0, 20.0)
GRID = np.array([(x, y) for x in G for y in G])  # precision grid plate, photo mm
FIDS = np.array([[-80.0, 0.0], [80.0, 0.0], [0.0, 80.0], [0.0, -80.0]])  # carrier marks


def _readings(xy, Z, X0=PC, ang=(0.0, 0.0, 0.0), f=F):
    return plane_readings(xy, Z, np.asarray(X0), np.asarray(ang), f)


@pytest.mark.parametrize("method", ["rigorous", "birardi"])
def test_noise_free(method):
    t = two_planes(_readings(GRID, Z1), Z1, _readings(GRID, Z2), Z2, GRID, method=method)
    np.testing.assert_allclose(t.X0, PC, rtol=1e-12)
    assert t.f == pytest.approx(F, rel=1e-12)
    n = len(GRID)
    assert t.redundancy == 2 * n - 3
    assert np.isnan(t.f_i[n // 2])  # the central cross (at the principal point) has no f_i
    np.testing.assert_allclose(np.delete(t.f_i, n // 2), F, rtol=1e-12)


def test_two_points_minimum():
    xy = GRID[[0, -1]]
    t = two_planes(_readings(xy, Z1), Z1, _readings(xy, Z2), Z2)
    np.testing.assert_allclose(t.X0, PC, rtol=1e-12)
    assert t.redundancy == 1


def test_statistics_rigorous_and_birardi():
    rng = np.random.default_rng(1)
    sig = 0.001  # 1 um readings, as Birardi's REC III means
    grid = GRID[::3]  # 27 crosses
    R1, R2 = _readings(grid, Z1), _readings(grid, Z2)
    out = {"rigorous": ([], [], []), "birardi": ([], [], [])}
    fs, fstd = [], []
    for _ in range(300):
        n1 = R1 + rng.normal(0, sig, R1.shape)
        n2 = R2 + rng.normal(0, sig, R2.shape)
        for m, (s02, err, var) in out.items():
            t = two_planes(n1, Z1, n2, Z2, grid, sigma=sig, method=m, f_weights="rigorous")
            s02.append(t.sigma0**2)
            err.append(t.X0 - PC)
            var.append(np.diag(t.covariance))
        fs.append(t.f)
        fstd.append(t.f_std)
    for m, (s02, err, var) in out.items():
        assert np.mean(s02) == pytest.approx(sig**2, rel=0.05), m
        ratio = np.var(np.array(err), axis=0) / np.mean(np.array(var), axis=0)
        np.testing.assert_allclose(ratio, 1.0, atol=0.2, err_msg=m)
        # no bias: the mean error is within 4 standard errors of the mean
        sem = np.sqrt(np.mean(var, axis=0) / len(err))
        assert np.all(np.abs(np.mean(err, axis=0)) < 4 * sem), m
    assert np.mean(fs) == pytest.approx(F, abs=4 * np.mean(fstd) / np.sqrt(300))
    assert np.std(fs) == pytest.approx(np.mean(fstd), rel=0.2)


def test_principal_distance_weights():
    R1, R2 = _readings(GRID, Z1), _readings(GRID, Z2)
    f, _, fi, p = principal_distance(R1, Z1, R2, Z2, GRID, "birardi")
    a2b2 = np.sum((R2 - R1) ** 2, axis=1)
    ok = np.isfinite(fi)
    np.testing.assert_allclose(p[ok], a2b2[ok] ** 2)
    f2, _, _, p2 = principal_distance(R1, Z1, R2, Z2, GRID, "rigorous")
    np.testing.assert_allclose(p2[ok], a2b2[ok])
    assert f == pytest.approx(F) and f2 == pytest.approx(F)
    with pytest.raises(SoftplotError, match="f weights"):
        principal_distance(R1, Z1, R2, Z2, GRID, "x")


def test_coincident_planes_named():
    R1 = _readings(GRID, Z1)
    with pytest.raises(UndeterminedError, match="Z0"):
        two_planes(R1, Z1, R1, Z1)


@pytest.mark.parametrize("ang", [(0.0, 0.0, 0.0), (0.0314, 0.0, 0.0), (0.02, -0.03, 0.05)])
def test_fiducial_resection_noise_free(ang):
    ang = np.array(ang)
    XY = _readings(FIDS, Z1, ang=ang)
    r = fiducial_resection(FIDS, XY, Z1, F)
    np.testing.assert_allclose(r.X0, PC, rtol=1e-11)
    np.testing.assert_allclose(r.angles, ang, atol=1e-11)
    assert r.redundancy == 2


def test_fiducial_resection_statistics():
    rng = np.random.default_rng(2)
    sig = 0.001
    marks = np.r_[FIDS, [[0.0, 0.0], [56.0, 56.0]]]  # 6 marks
    XY = _readings(marks, Z1, ang=(0.02, 0.01, -0.01))
    s02, err, var = [], [], []
    for _ in range(300):
        r = fiducial_resection(marks, XY + rng.normal(0, sig, XY.shape), Z1, F, sigma=sig)
        s02.append(r.sigma0**2)
        err.append(r.X0 - PC)
        var.append(np.diag(r.covariance)[:3])
    assert np.mean(s02) == pytest.approx(sig**2, rel=0.1)
    ratio = np.var(np.array(err), axis=0) / np.mean(np.array(var), axis=0)
    np.testing.assert_allclose(ratio, 1.0, atol=0.2)


def test_differential_cancels_fiducial_calibration_errors():
    rng = np.random.default_rng(3)
    # the carrier marks are "calibrated" with 10 um errors and f is known to 20 um only
    fids_cal = FIDS + rng.normal(0, 0.010, FIDS.shape)
    f_cal = F + 0.02
    shift = np.array([0.05, -0.03, 0.01])
    ang_model = np.array([0.0314, -0.0157, 0.0])  # 2 and 1 gon
    # (a) two planes on the grid, (b) fiducials at the same epoch, (c) fiducials in the model
    a = two_planes(_readings(GRID, Z1), Z1, _readings(GRID, Z2), Z2, GRID)
    b = fiducial_resection(fids_cal, _readings(FIDS, Z1), Z1, f_cal)
    c = fiducial_resection(fids_cal, _readings(FIDS, Z1, PC + shift, ang_model), Z1, f_cal)
    d = differential(a, b, c)
    truth = PC + shift
    direct = np.abs(c.X0 - truth).max()
    assert direct > 0.01  # the resection alone repeats the calibration errors
    # what remains is second order (tilt x calibration error)
    assert np.abs(d.X0 - truth).max() < 0.1 * direct
    np.testing.assert_allclose(d.delta, c.X0 - b.X0)
    np.testing.assert_allclose(
        d.covariance, a.covariance + b.covariance[:3, :3] + c.covariance[:3, :3]
    )


def test_bad_inputs():
    with pytest.raises(SoftplotError, match=r"\(n,2\)"):
        two_planes(np.zeros((3, 3)), Z1, np.zeros((3, 2)), Z2)
    with pytest.raises(SoftplotError, match=">= 2 points"):
        two_planes(np.zeros((1, 2)), Z1, np.zeros((1, 2)), Z2)
    with pytest.raises(SoftplotError, match="method"):
        two_planes(np.zeros((3, 2)), Z1, np.ones((3, 2)), Z2, method="x")
    with pytest.raises(SoftplotError, match=">= 3 marks"):
        fiducial_resection(FIDS[:2], FIDS[:2], Z1, F)
