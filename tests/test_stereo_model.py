"""Stereo model against a synthetic aerial pair with exact truth."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from conftest import sweep
from softplot.errors import SoftplotError
from softplot.geometry.collinearity import project
from softplot.stereo.model import OrientedPhoto, StereoModel, invert_correction
from softplot.synthetic.stereo import aerial_pair


def _model(t, corrections=False):
    photos = []
    for k in range(2):
        f2p, p2f = t.corrections(k) if corrections else (None, None)
        photos.append(OrientedPhoto(t.X0[k], t.angles[k], t.c[k], t.x0[k], t.y0[k], f2p, p2f))
    return StereoModel(*photos)


SEEDS = sweep(list(range(12)), 4)


@pytest.mark.parametrize("seed", SEEDS)
def test_single_point_removes_y_parallax_and_recovers_truth(seed):
    t = aerial_pair(seed=seed)
    m = _model(t)
    P = t.sample_points(200, seed=seed)
    xy1, xy2 = t.photo(0, P), t.photo(1, P)
    r = m.single_point(xy2, xy1[:, 0])
    # the y1 computed is the true one, and the object point is the true one
    assert np.max(np.abs(r.xy1[:, 1] - xy1[:, 1])) < 1e-9
    assert np.max(np.abs(r.XYZ - P)) < 1e-6
    # independent check of the y-parallax: re-project the object point into both photos
    # with the collinearity equations; the image points must be reproduced
    back1 = project(r.XYZ, t.X0[0], t.M(0), t.c[0], t.x0[0], t.y0[0])
    back2 = project(r.XYZ, t.X0[1], t.M(1), t.c[1], t.x0[1], t.y0[1])
    assert np.max(np.abs(back1 - r.xy1)) < 1e-9
    assert np.max(np.abs(back2 - xy2)) < 1e-9
    # coplanarity with the fundamental matrix, in mm (normalised epipolar line distance)
    lines = m.epipolar_lines_left(xy2)
    dist = np.abs(np.einsum("ij,ij->i", lines, np.c_[r.xy1, np.ones(len(P))]))
    assert dist.max() < 1e-9


@pytest.mark.parametrize("seed", SEEDS)
def test_single_point_off_terrain_x_parallax_moves_along_ray(seed):
    """Any handwheel x1 gives a point on the right ray with zero y-parallax."""
    t = aerial_pair(seed=seed)
    m = _model(t)
    P = t.sample_points(50, seed=seed + 100)
    xy2 = t.photo(1, P)
    x1 = t.photo(0, P)[:, 0] + np.linspace(-3, 3, 50)
    r = m.single_point(xy2, x1)
    assert np.max(np.abs(m.y_parallax(*m.project(r.XYZ)))) < 1e-9
    back2 = t.photo(1, r.XYZ)
    assert np.max(np.abs(back2 - xy2)) < 1e-9
    assert np.max(r.gap) < 1e-6


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("H", [230.0, 300.0, 360.0])
def test_contour_vertices_on_height_with_true_planimetry(seed, H):
    t = aerial_pair(seed=seed)
    m = _model(t)
    C = t.contour_truth(H, 90)
    r = m.contour(t.photo(1, C), H)
    assert np.max(np.abs(r.XYZ[:, 2] - H)) < 1e-6
    assert np.max(np.hypot(*(r.XYZ[:, :2] - C[:, :2]).T)) < 1e-6
    # the left point is the truth's, so the mark sits on the terrain
    assert np.max(np.abs(r.xy1 - t.photo(0, C))) < 1e-9
    assert np.max(np.abs(r.py)) < 1e-9
    # and every vertex lies on the terrain at H
    assert np.max(np.abs(t.terrain(r.XYZ[:, 0], r.XYZ[:, 1]) - H)) < 1e-6


def test_contour_at_other_height_misses_terrain():
    """A wrong contour height puts the mark off the terrain (the test can fail)."""
    t = aerial_pair(seed=3)
    m = _model(t)
    C = t.contour_truth(300.0, 20)
    r = m.contour(t.photo(1, C), 301.0)
    assert np.min(np.abs(r.xy1 - t.photo(0, C)).max(axis=1)) > 1e-3


def test_free_mode_truth_and_residual_parallax():
    t = aerial_pair(seed=5)
    m = _model(t)
    P = t.sample_points(100, seed=9)
    xy1, xy2 = t.photo(0, P), t.photo(1, P)
    r = m.free(xy1, xy2)
    assert np.max(np.abs(r.XYZ - P)) < 1e-6
    assert np.max(np.abs(r.py)) < 1e-9
    assert r.std.shape == (100, 3) and np.all(r.std > 0)
    # a known y error of the left point shows up as the y-parallax
    dy = np.linspace(-0.05, 0.05, 100)
    r2 = m.free(xy1 + np.c_[np.zeros(100), dy], xy2)
    assert np.max(np.abs(r2.py - dy)) < 1e-9
    assert np.all(r2.gap[np.abs(dy) > 0.01] > 1e-3)


def test_drive_to_and_projection():
    t = aerial_pair(seed=7)
    m = _model(t)
    P = t.sample_points(40, seed=1)
    r = m.drive_to(P)
    assert np.max(np.abs(r.xy1 - t.photo(0, P))) < 1e-12
    assert np.max(np.abs(r.xy2 - t.photo(1, P))) < 1e-12
    assert np.max(np.abs(r.py)) < 1e-9


def test_fundamental_matrix_and_epipolar_lines_both_ways():
    t = aerial_pair(seed=2)
    m = _model(t)
    P = t.sample_points(60)
    xy1, xy2 = t.photo(0, P), t.photo(1, P)
    F = m.fundamental()
    h1, h2 = np.c_[xy1, np.ones(60)], np.c_[xy2, np.ones(60)]
    rel = np.abs(np.einsum("ni,ij,nj->n", h1, F, h2)) / np.abs(F).max()
    assert rel.max() < 1e-9
    lr = m.epipolar_lines_right(xy1)
    assert np.max(np.abs(np.einsum("ij,ij->i", lr, h2))) < 1e-9
    # a point off the line is at its distance
    off = np.einsum("ij,ij->i", m.epipolar_lines_left(xy2), h1 + [0, 0.1, 0])
    assert np.allclose(np.abs(off), 0.1 * np.abs(m.epipolar_lines_left(xy2)[:, 1]), atol=1e-9)


def test_fast_scalar_path_matches_vectorised():
    t = aerial_pair(seed=4)
    m = _model(t)
    f = m.fast()
    P = t.sample_points(30, seed=4)
    xy1, xy2 = t.photo(0, P), t.photo(1, P)
    rs = m.single_point(xy2, xy1[:, 0])
    rc = m.contour(xy2, P[:, 2])
    for i in range(30):
        y1, X, Y, Z = f.single(float(xy2[i, 0]), float(xy2[i, 1]), float(xy1[i, 0]))
        assert abs(y1 - rs.xy1[i, 1]) < 1e-11
        assert np.max(np.abs(np.array([X, Y, Z]) - rs.XYZ[i])) < 1e-8
        x1c, y1c, Xc, Yc = f.contour(float(xy2[i, 0]), float(xy2[i, 1]), float(P[i, 2]))
        assert np.max(np.abs(np.array([x1c, y1c]) - rc.xy1[i])) < 1e-11
        assert np.max(np.abs(np.array([Xc, Yc]) - rc.XYZ[i, :2])) < 1e-8


def test_film_corrections_round_trip():
    t = aerial_pair(seed=6, deform=True)
    m = _model(t, corrections=True)
    P = t.sample_points(20)
    film = t.film(0, P)
    photo = m.left.film_to_photo(film)
    assert np.max(np.abs(photo - t.photo(0, P))) < 1e-12
    assert np.max(np.abs(m.left.photo_to_film(photo) - film)) < 1e-12
    # without the explicit inverse the fixed-point inverse is used
    f2p = t.corrections(0)[0]
    inv = invert_correction(f2p, photo)
    assert np.max(np.abs(inv - film)) < 1e-10


def test_bad_models_raise_one_line_errors():
    with pytest.raises(SoftplotError, match="coincide"):
        StereoModel(
            OrientedPhoto([0, 0, 10], [0, 0, 0], 50), OrientedPhoto([0, 0, 10], [0, 0, 0], 50)
        )
    with pytest.raises(SoftplotError, match="principal distance"):
        OrientedPhoto([0, 0, 10], [0, 0, 0], -5)
    with pytest.raises(SoftplotError, match="not finite"):
        OrientedPhoto([0, np.nan, 10], [0, 0, 0], 50)
    m = StereoModel(
        OrientedPhoto([0, 0, 10], [0, 0, 0], 50), OrientedPhoto([5, 0, 10], [0, 0, 0], 50)
    )
    with pytest.raises(SoftplotError, match="behind"):
        m.contour([[1.0, 2.0]], 20.0)
    with pytest.raises(SoftplotError, match="parallel"):
        # photos looking sideways (omega = 90 deg): the central ray is horizontal
        side = StereoModel(
            OrientedPhoto([0, 0, 10], [np.pi / 2, 0, 0], 50),
            OrientedPhoto([5, 0, 10], [np.pi / 2, 0, 0], 50),
        )
        side.contour([[0.0, 0.0]], 0.0)
    r = m.contour([[1.0, 2.0]], 0.0)
    assert np.allclose(r.XYZ[0, 2], 0.0)


@settings(max_examples=60, deadline=None)
@given(
    angles=st.lists(st.floats(-0.35, 0.35), min_size=6, max_size=6),
    base=st.floats(50.0, 800.0),
    by=st.floats(-50.0, 50.0),
    bz=st.floats(-50.0, 50.0),
    c=st.floats(30.0, 300.0),
    seed=st.integers(0, 2**16),
)
def test_single_point_and_contour_any_geometry(angles, base, by, bz, c, seed):
    """Random tilted/convergent pairs: y-parallax removed and contour height exact."""
    L = OrientedPhoto([0.0, 0.0, 1500.0], angles[:3], c, 0.01, -0.02)
    R = OrientedPhoto([base, by, 1500.0 + bz], angles[3:], c, -0.01, 0.02)
    m = StereoModel(L, R)
    rng = np.random.default_rng(seed)
    P = np.c_[
        rng.uniform(-200, base + 200, 20), rng.uniform(-300, 300, 20), rng.uniform(0, 300, 20)
    ]
    xy1, xy2 = m.project(P)
    r = m.single_point(xy2, xy1[:, 0])
    scale = 1 + np.abs(xy1).max()
    assert np.max(np.abs(r.xy1[:, 1] - xy1[:, 1])) < 1e-9 * scale
    assert np.max(np.abs(m.y_parallax(*m.project(r.XYZ)))) < 1e-9 * scale
    rc = m.contour(xy2, P[:, 2])
    assert np.max(np.abs(rc.XYZ[:, 2] - P[:, 2])) < 1e-6
    assert np.max(np.abs(rc.XYZ - P)) < 1e-6
