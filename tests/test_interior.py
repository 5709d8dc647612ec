"""Interior orientation: film <-> photo with principal point, radial table and Brown terms."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.camera import Distortion, load_camera
from softplot.orientation.interior import InteriorOrientation


def _brown_camera():
    cam = load_camera("rollei-6006")
    return cam.with_(
        x0=0.12,
        y0=-0.07,
        distortion=Distortion(
            model="brown", k1=-2e-5, k2=3e-9, k3=-1e-12, p1=2e-6, p2=-1.5e-6, b1=1e-5, b2=-2e-5
        ),
    )


def _table_camera():
    cam = load_camera("zeiss-rmk-a-15-23")
    table = Distortion(
        model="radial-table",
        radius_mm=(0.0, 20.0, 40.0, 60.0, 80.0, 100.0, 120.0, 140.0, 160.0),
        delta_r_um=(0.0, 0.5, 1.0, 1.5, 1.5, 1.0, 0.0, -1.5, -3.0),
    )
    return cam.with_(x0=0.01, y0=-0.02, distortion=table)


def _grid(half, n=41):
    g = np.linspace(-half, half, n)
    x, y = np.meshgrid(g, g)
    return np.column_stack([x.ravel(), y.ravel()])


def test_brown_sign_convention_by_hand():
    cam = _brown_camera()
    io = InteriorOrientation(cam)
    x, y = 20.0, -13.0
    xb, yb = x - cam.x0, y - cam.y0
    d = cam.distortion
    r2 = xb * xb + yb * yb
    F = d.k1 * r2 + d.k2 * r2**2 + d.k3 * r2**3
    dx = xb * F + d.p1 * (r2 + 2 * xb * xb) + 2 * d.p2 * xb * yb + d.b1 * xb + d.b2 * yb
    dy = yb * F + 2 * d.p1 * xb * yb + d.p2 * (r2 + 2 * yb * yb)
    np.testing.assert_allclose(io.film_to_photo([[x, y]])[0], [xb - dx, yb - dy], atol=1e-14)
    assert io.film_to_photo_point(x, y) == pytest.approx((xb - dx, yb - dy), abs=1e-14)


def test_radial_table_sign_and_values_at_tabulated_radii():
    cam = _table_camera()
    io = InteriorOrientation(cam)
    d = cam.distortion
    for r, dr in zip(d.radius_mm, d.delta_r_um, strict=True):
        # a point at radius r from the principal point, at 30 degrees
        xb, yb = r * np.cos(np.pi / 6), r * np.sin(np.pi / 6)
        p = io.film_to_photo([[xb + cam.x0, yb + cam.y0]])[0]
        # photo = reduced - delta, delta along the radius with length delta_r
        expect = np.array([xb, yb]) * (1 - dr * 1e-3 / r) if r > 0 else np.zeros(2)
        np.testing.assert_allclose(p, expect, atol=1e-12)


def test_radial_table_interpolation_is_monotone_between_tabulated_values():
    io = InteriorOrientation(_table_camera())
    d = io.camera.distortion
    r = np.asarray(d.radius_mm)
    v = np.asarray(d.delta_r_um) * 1e-3
    for i in range(len(r) - 1):
        rr = np.linspace(r[i], r[i + 1], 50)
        dr = io.delta_r(rr)
        lo, hi = min(v[i], v[i + 1]), max(v[i], v[i + 1])
        assert np.all(dr >= lo - 1e-15) and np.all(dr <= hi + 1e-15)  # no overshoot
    # smooth: C1 at the breakpoints
    h = 1e-7
    inner = r[1:-1]
    left = (io.delta_r(inner) - io.delta_r(inner - h)) / h
    right = (io.delta_r(inner + h) - io.delta_r(inner)) / h
    assert np.abs(left - right).max() < 1e-5


def test_radial_table_extrapolates_linearly_and_adds_the_origin():
    cam = load_camera("hasselblad-mk70").with_(
        distortion=Distortion(model="radial-table", radius_mm=(5.0, 10.0, 20.0),
                              delta_r_um=(1.0, 2.0, 1.0))
    )
    io = InteriorOrientation(cam)
    assert io.delta_r(0.0) == pytest.approx(0.0, abs=1e-15)
    assert io.delta_r(5.0) == pytest.approx(1e-3)
    r = np.array([20.0, 25.0, 30.0, 40.0])
    d = io.delta_r(r)
    slopes = np.diff(d) / np.diff(r)
    np.testing.assert_allclose(slopes, slopes[0], rtol=1e-9)


@pytest.mark.parametrize("make", [_brown_camera, _table_camera], ids=["brown", "table"])
def test_round_trip_and_single_point(make):
    cam = make()
    io = InteriorOrientation(cam)
    half = max(cam.format_mm) / 2 * 1.3  # beyond the format corners too
    f = _grid(half)
    p = io.film_to_photo(f)
    back = io.photo_to_film(p)
    assert np.abs(back - f).max() < 1e-11  # mm
    one = np.array([io.film_to_photo_point(x, y) for x, y in f[::37]])
    np.testing.assert_allclose(one, p[::37], atol=1e-13)
    onef = np.array([io.photo_to_film_point(x, y) for x, y in p[::97]])
    np.testing.assert_allclose(onef, f[::97], atol=1e-11)


@pytest.mark.parametrize("make", [_brown_camera, _table_camera], ids=["brown", "table"])
def test_distortion_jacobian_vs_finite_differences(make):
    io = InteriorOrientation(make())
    q = _grid(30.0, 9) + 0.123
    J = io.distortion_jacobian(q[:, 0], q[:, 1])
    h = 1e-5
    for j in range(2):
        e = np.zeros(2)
        e[j] = h
        a = np.array(io.distortion(*(q + e).T))
        b = np.array(io.distortion(*(q - e).T))
        np.testing.assert_allclose(J[:, :, j], ((a - b) / (2 * h)).T, atol=1e-9)


def test_no_distortion_is_the_principal_point_only():
    cam = load_camera("pentax-645").with_(x0=0.3, y0=-0.2)
    io = InteriorOrientation(cam)
    f = _grid(20.0, 5)
    np.testing.assert_allclose(io.film_to_photo(f), f - [0.3, -0.2], atol=1e-15)
    np.testing.assert_allclose(io.photo_to_film(io.film_to_photo(f)), f, atol=1e-14)


def test_radial_only_brown_fast_branch_matches_general_formula():
    cam = load_camera("rollei-6006").with_(distortion=Distortion(model="brown", k1=-2e-5))
    io = InteriorOrientation(cam)
    f = _grid(28.0, 11)
    dx, dy = io.distortion(f[:, 0] - cam.x0, f[:, 1] - cam.y0)
    np.testing.assert_allclose(
        io.film_to_photo(f), np.column_stack([f[:, 0] - dx, f[:, 1] - dy]), atol=1e-14
    )
