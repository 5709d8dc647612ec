"""Rotation matrices and collinearity: convention, derivatives vs finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.errors import SoftplotError
from softplot.geometry.collinearity import (
    JACOBIAN_COLUMNS,
    camera_coordinates,
    image_rays,
    project,
    project_jacobian,
)
from softplot.geometry.rotation import (
    angles_from_matrix,
    from_radians,
    gon2rad,
    rad2gon,
    rotation_derivatives,
    rotation_matrix,
    to_radians,
)


def _elementary(o, p, k):
    so, co, sp, cp, sk, ck = np.sin(o), np.cos(o), np.sin(p), np.cos(p), np.sin(k), np.cos(k)
    Mo = np.array([[1, 0, 0], [0, co, so], [0, -so, co]])
    Mp = np.array([[cp, 0, -sp], [0, 1, 0], [sp, 0, cp]])
    Mk = np.array([[ck, sk, 0], [-sk, ck, 0], [0, 0, 1]])
    return Mk @ Mp @ Mo


def test_matrix_is_mk_mp_mo_and_orthonormal():
    rng = np.random.default_rng(1)
    ang = rng.uniform(-3, 3, size=(50, 3))
    M = rotation_matrix(ang[:, 0], ang[:, 1], ang[:, 2])
    assert M.shape == (50, 3, 3)
    for a, m in zip(ang, M, strict=True):
        np.testing.assert_allclose(m, _elementary(*a), atol=1e-15)
    eye = np.broadcast_to(np.eye(3), M.shape)
    np.testing.assert_allclose(M @ np.swapaxes(M, 1, 2), eye, atol=1e-14)
    np.testing.assert_allclose(np.linalg.det(M), 1.0, atol=1e-14)


def test_known_elements():
    o, p, k = 0.1, -0.2, 0.3
    M = rotation_matrix(o, p, k)
    assert M[2, 0] == pytest.approx(np.sin(p))
    assert M[2, 1] == pytest.approx(-np.sin(o) * np.cos(p))
    assert M[2, 2] == pytest.approx(np.cos(o) * np.cos(p))
    assert M[0, 0] == pytest.approx(np.cos(p) * np.cos(k))
    assert M[1, 0] == pytest.approx(-np.cos(p) * np.sin(k))


def test_angles_round_trip():
    rng = np.random.default_rng(2)
    o = rng.uniform(-np.pi + 1e-3, np.pi - 1e-3, 200)
    p = rng.uniform(-np.pi / 2 + 1e-3, np.pi / 2 - 1e-3, 200)
    k = rng.uniform(-np.pi + 1e-3, np.pi - 1e-3, 200)
    oo, pp, kk = angles_from_matrix(rotation_matrix(o, p, k))
    np.testing.assert_allclose(np.c_[oo, pp, kk], np.c_[o, p, k], atol=1e-12)


@pytest.mark.parametrize("phi", [np.pi / 2, -np.pi / 2])
def test_gimbal_lock_gives_same_matrix(phi):
    M = rotation_matrix(0.3, phi, 0.2)
    o, p, k = angles_from_matrix(M)
    np.testing.assert_allclose(rotation_matrix(o, p, k), M, atol=1e-9)


def test_rotation_derivatives_fd():
    rng = np.random.default_rng(3)
    h = 1e-6
    for _ in range(20):
        a = rng.uniform(-2, 2, 3)
        dM = rotation_derivatives(*a)
        for i in range(3):
            e = np.zeros(3)
            e[i] = h
            fd = (rotation_matrix(*(a + e)) - rotation_matrix(*(a - e))) / (2 * h)
            np.testing.assert_allclose(dM[i], fd, atol=1e-9)


def test_units():
    assert float(gon2rad(400.0)) == pytest.approx(2 * np.pi)
    assert float(rad2gon(np.pi / 2)) == pytest.approx(100.0)
    assert float(to_radians(90.0, "deg")) == pytest.approx(np.pi / 2)
    assert float(from_radians(np.pi, "gon")) == pytest.approx(200.0)
    with pytest.raises(SoftplotError, match="angle unit"):
        to_radians(1.0, "mil")


def _scene(rng, n=30):
    XYZ = np.c_[rng.uniform(-500, 500, n), rng.uniform(-500, 500, n), rng.uniform(-50, 80, n)]
    X0 = np.array([30.0, -20.0, 1500.0])
    ang = np.array([0.05, -0.03, 0.7])
    return XYZ, X0, ang


def test_project_vertical_photo_by_hand():
    # vertical photo, kappa 0: x = c*dX/H, y = c*dY/H
    XYZ = np.array([[100.0, 50.0, 0.0]])
    xy = project(XYZ, [0, 0, 1000.0], np.eye(3), 150.0, x0=0.01, y0=-0.02)
    np.testing.assert_allclose(xy, [[15.01, 7.48]], atol=1e-12)
    assert camera_coordinates(XYZ, [0, 0, 1000.0], np.eye(3))[0, 2] < 0


def test_project_jacobian_fd():
    rng = np.random.default_rng(4)
    XYZ, X0, ang = _scene(rng)
    c, x0, y0 = 152.3, 0.02, -0.015
    xy, J = project_jacobian(XYZ, X0, ang, c, x0, y0)
    np.testing.assert_allclose(xy, project(XYZ, X0, rotation_matrix(*ang), c, x0, y0), atol=1e-12)
    assert J.shape == (30, 2, len(JACOBIAN_COLUMNS))
    steps = [1e-3, 1e-3, 1e-3, 1e-7, 1e-7, 1e-7, 1e-3, 1e-3, 1e-3, 1e-5, 1e-6, 1e-6]

    for j, h in enumerate(steps):
        if 6 <= j <= 8:  # object point: one point at a time
            e = np.zeros(3)
            e[j - 6] = h
            fd = (
                project(XYZ + e, X0, rotation_matrix(*ang), c, x0, y0)
                - project(XYZ - e, X0, rotation_matrix(*ang), c, x0, y0)
            ) / (2 * h)
        else:
            p = np.r_[X0, ang, 0, 0, 0, c, x0, y0]
            e = np.zeros(12)
            e[j] = h

            def g(q):
                return project(XYZ, q[0:3], rotation_matrix(*q[3:6]), q[9], q[10], q[11])

            fd = (g(p + e) - g(p - e)) / (2 * h)
        name = JACOBIAN_COLUMNS[j]
        np.testing.assert_allclose(J[:, :, j], fd, rtol=1e-6, atol=1e-8, err_msg=name)


def test_project_jacobian_per_point_orientation():
    rng = np.random.default_rng(5)
    XYZ, X0, ang = _scene(rng, 10)
    X0n = X0 + rng.normal(0, 10, (10, 3))
    angn = ang + rng.normal(0, 0.05, (10, 3))
    cn = 150 + rng.normal(0, 1, 10)
    xy, J = project_jacobian(XYZ, X0n, angn, cn)
    for i in range(10):
        xi, Ji = project_jacobian(XYZ[i : i + 1], X0n[i], angn[i], cn[i])
        np.testing.assert_allclose(xy[i], xi[0], atol=1e-12)
        np.testing.assert_allclose(J[i], Ji[0], atol=1e-12)


def test_image_rays_hit_points():
    rng = np.random.default_rng(6)
    XYZ, X0, ang = _scene(rng)
    M = rotation_matrix(*ang)
    xy = project(XYZ, X0, M, 150.0, 0.01, 0.02)
    r = image_rays(xy, M, 150.0, 0.01, 0.02)
    d = XYZ - X0
    np.testing.assert_allclose(r, d / np.linalg.norm(d, axis=1, keepdims=True), atol=1e-12)


def test_bad_shape():
    with pytest.raises(SoftplotError, match=r"\(N,3\)"):
        project(np.zeros((4, 2)), [0, 0, 0], np.eye(3), 150.0)
