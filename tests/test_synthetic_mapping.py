"""The synthetic scan's truth mapping: round trips, Jacobians, amplitudes, scanner geometry."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from softplot.synthetic import ScanSpec, TruthMapping, render_scan
from softplot.synthetic.mapping import Deformation, Scanner


def _mapping(deform_um=60.0, shrink=400.0, dpi=1200.0, rot=3.0, aniso=700.0, seed=5):
    d = Deformation.random((56.0, 56.0), deform_um, shrink, np.random.default_rng(seed))
    return TruthMapping(d, Scanner(dpi, rot, aniso, 1325.3, 1310.8))


def _grid(half=30.0, n=41):
    g = np.linspace(-half, half, n)
    x, y = np.meshgrid(g, g)
    return np.column_stack([x.ravel(), y.ravel()])


@pytest.mark.parametrize("deform_um,rot", [(0.0, 0.0), (60.0, 3.0), (100.0, -9.5), (250.0, 90.0)])
def test_round_trip_film_pixel_film(deform_um, rot):
    m = _mapping(deform_um=deform_um, rot=rot)
    film = _grid()
    back = m.pixel_to_film(m.film_to_pixel(film))
    assert np.max(np.abs(back - film)) < 1e-9  # mm
    px = m.film_to_pixel(film) + 0.37
    again = m.film_to_pixel(m.pixel_to_film(px))
    assert np.max(np.abs(again - px)) < 1e-7  # px (1e-9 mm is ~5e-8 px at 1200 dpi)


def test_shapes_are_kept():
    m = _mapping()
    pts = np.zeros((3, 4, 2))
    assert m.film_to_pixel(pts).shape == (3, 4, 2)
    assert m.pixel_to_film(pts).shape == (3, 4, 2)
    assert m.film_to_pixel([1.0, 2.0]).shape == (2,)


def test_jacobian_matches_finite_differences():
    m = _mapping(deform_um=80.0)
    film = _grid(25.0, 7)
    jac = m.jacobian(film)
    h = 1e-5
    for k in range(2):
        step = np.zeros(2)
        step[k] = h
        num = (m.film_to_pixel(film + step) - m.film_to_pixel(film - step)) / (2 * h)
        assert np.max(np.abs(jac[:, :, k] - num)) < 1e-5  # px per mm (~47 px/mm)


@pytest.mark.parametrize("amp", [5.0, 40.0, 100.0])
def test_deformation_amplitude_is_what_was_asked(amp):
    d = Deformation.random((56.0, 41.5), amp, 0.0, np.random.default_rng(int(amp)))
    # an independent, finer grid over the same format
    gx, gy = np.meshgrid(np.linspace(-28, 28, 561), np.linspace(-20.75, 20.75, 416))
    u = np.column_stack([gx.ravel(), gy.ravel()])
    disp = d.forward(u) - u
    peak_um = np.max(np.hypot(disp[:, 0], disp[:, 1])) * 1000
    assert amp * 0.999 <= peak_um <= amp * 1.01
    # smooth, not affine: an affine fit leaves a good part of it in
    a = np.column_stack([u, np.ones(len(u))])
    coef, *_ = np.linalg.lstsq(a, disp, rcond=None)
    rest = disp - a @ coef
    assert np.max(np.hypot(rest[:, 0], rest[:, 1])) * 1000 > 0.15 * amp


def test_shrinkage_and_no_field():
    d = Deformation.random((56.0, 56.0), 0.0, 1000.0, np.random.default_rng(1))
    u = _grid(28.0, 5)
    assert np.allclose(d.forward(u), u * (1 - 1e-3), atol=1e-15)


def test_scanner_scale_rotation_anisotropy():
    dpi, rot, aniso = 1000.0, 7.0, 2000.0
    m = TruthMapping(Deformation(), Scanner(dpi, rot, aniso, 100.0, 200.0))
    o, ex, ey = m.film_to_pixel(np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]]))
    assert np.allclose(o, [100.0, 200.0])
    s = dpi / 25.4
    vx, vy = ex - o, ey - o
    assert math.hypot(*vx) == pytest.approx(10 * s * math.hypot(
        (1 + 1e-3) * math.cos(math.radians(rot)), (1 - 1e-3) * math.sin(math.radians(rot))))
    # film +x turns counter-clockwise on screen: pixel y (down) decreases
    th = math.radians(rot)
    expect = math.degrees(math.atan2((1 - 1e-3) * math.sin(th), (1 + 1e-3) * math.cos(th)))
    assert math.degrees(math.atan2(-vx[1], vx[0])) == pytest.approx(expect, abs=1e-9)
    assert abs(expect - rot) < 0.02
    # film +y points up on screen (pixel y decreases)
    assert vy[1] < 0
    # without rotation the x/y scale ratio is the anisotropy
    m0 = TruthMapping(Deformation(), Scanner(dpi, 0.0, aniso, 0.0, 0.0))
    p = m0.film_to_pixel(np.array([[10.0, 10.0]]))[0]
    assert p[0] / -p[1] == pytest.approx((1 + 1e-3) / (1 - 1e-3), rel=1e-12)


def test_truth_json_round_trip_is_exact(tmp_path):
    spec = ScanSpec(dpi=300, deform_um=70, shrink_ppm=300, rotation_deg=4, anisotropy_ppm=500,
                    noise_sigma=0, scene="none", crop_mm=(2.0, 1.0, 0.5, 0.0),
                    offset_px=(3.2, -1.1))
    img, truth = render_scan("hasselblad-mk70", spec, seed=11)
    path = tmp_path / "t.json"
    path.write_text(json.dumps(truth))
    m1 = TruthMapping.from_truth(truth)
    m2 = TruthMapping.from_truth(path)
    film = _grid(27.0, 9)
    assert np.array_equal(m1.film_to_pixel(film), m2.film_to_pixel(film))
    marks = truth["marks"]
    xy = np.array([[k["x"], k["y"]] for k in marks])
    fxy = np.array([[k["film_x"], k["film_y"]] for k in marks])
    assert np.max(np.abs(m2.film_to_pixel(fxy) - xy)) < 1e-9
    assert truth["width"] == img.shape[1] and truth["height"] == img.shape[0]


def test_from_truth_bad_input(tmp_path):
    from softplot.errors import SoftplotError

    with pytest.raises(SoftplotError):
        TruthMapping.from_truth({"marks": []})
    with pytest.raises(SoftplotError):
        TruthMapping.from_truth(tmp_path / "missing.json")
    with pytest.raises(SoftplotError):
        TruthMapping.from_truth({"mapping": {"scanner": {"dpi": 1}}})
