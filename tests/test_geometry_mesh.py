"""Mesh models: exactness at the crosses, round trips, location, outside points, merging."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.camera import load_camera
from softplot.errors import SoftplotError
from softplot.geometry import MESH_KINDS, MeshModel, default_mesh_kind, fit_transform
from softplot.synthetic import Deformation, Scanner, TruthMapping


def _setup(camera="rollei-6006", deform_um=40.0, seed=0, dpi=2400, rot=0.7):
    cam = load_camera(camera)
    R = cam.reseau
    film = R.film().reshape(R.rows, R.cols, 2)
    rng = np.random.default_rng(seed)
    w, h = cam.format_mm
    s = dpi / 25.4
    tm = TruthMapping(
        Deformation.random(cam.format_mm, deform_um, 80.0, rng),
        Scanner(dpi, rot, 400.0, w / 2 * s + 60, h / 2 * s + 40),
    )
    return cam, film, tm.film_to_pixel(film), tm


def _format_points(cam, n=20000, seed=1, margin=0.0):
    w, h = cam.format_mm
    rng = np.random.default_rng(seed)
    return rng.uniform([-w / 2 - margin, -h / 2 - margin], [w / 2 + margin, h / 2 + margin], (n, 2))


@pytest.mark.parametrize("kind", MESH_KINDS)
@pytest.mark.parametrize("camera", ["rollei-6006", "pentax-645", "hasselblad-mk70"])
def test_exact_at_crosses_and_round_trip(kind, camera):
    cam, film, px, tm = _setup(camera)
    m = MeshModel(film, px, kind)
    f, flags = m.pixel_to_film(px.reshape(-1, 2))
    assert np.abs(f - film.reshape(-1, 2)).max() < 1e-9  # mm
    assert np.all(flags == 0)
    # points all over the format and 5 mm beyond (outside the reseau): round trips close
    q = _format_points(cam, margin=5.0)
    p, fl1 = m.film_to_pixel(q)
    back, fl2 = m.pixel_to_film(p)
    assert np.abs(back - q).max() <= 1e-6  # mm
    np.testing.assert_array_equal(fl1, fl2)
    pp, _ = m.film_to_pixel(m.pixel_to_film(p)[0])
    assert np.abs(pp - p).max() < 1e-6  # px


@pytest.mark.parametrize("kind", MESH_KINDS)
def test_single_point_path_equals_vectorised(kind):
    cam, film, px, tm = _setup()
    m = MeshModel(film, px, kind)
    q = tm.film_to_pixel(_format_points(cam, 500, margin=3.0))
    vec, flags = m.pixel_to_film(q)
    one = np.array([m.pixel_to_film_point(x, y) for x, y in q])
    np.testing.assert_allclose(one[:, :2], vec, atol=1e-12)
    np.testing.assert_array_equal(one[:, 2].astype(int), flags)
    f = vec
    vp, _ = m.film_to_pixel(f)
    onep = np.array([m.film_to_pixel_point(x, y)[:2] for x, y in f])
    np.testing.assert_allclose(onep, vp, atol=1e-9)


def test_homography_mesh_is_the_per_quad_homography():
    cam, film, px, tm = _setup()
    m = MeshModel(film, px, "mesh-homography")
    assert m.n_cells == 100
    rng = np.random.default_rng(5)
    for r, c in [(0, 0), (4, 7), (9, 9), (3, 0)]:
        corners_f = film[[r, r, r + 1, r + 1], [c, c + 1, c + 1, c]]
        corners_p = px[[r, r, r + 1, r + 1], [c, c + 1, c + 1, c]]
        H = fit_transform("projective", corners_p, corners_f)
        # points strictly inside the quad (bilinear combination of its corners)
        s, t = rng.uniform(0.02, 0.98, (2, 200))
        P = (
            corners_p[0] * ((1 - s) * (1 - t))[:, None]
            + corners_p[1] * (s * (1 - t))[:, None]
            + corners_p[2] * (s * t)[:, None]
            + corners_p[3] * ((1 - s) * t)[:, None]
        )
        np.testing.assert_allclose(m.pixel_to_film(P)[0], H.forward(P), atol=1e-9)
        assert np.all(m.cells_of_pixel(P) == r * 10 + c)


def test_pentax_eight_triangles_meet_in_the_centre():
    cam, film, px, tm = _setup("pentax-645")
    m = MeshModel(film, px)  # camera default
    assert m.kind == "mesh-affine" == default_mesh_kind(3, 3)
    assert m.n_cells == 8
    # union jack: quads (0,0) and (1,1) take TL-BR, (0,1) and (1,0) take TR-BL
    np.testing.assert_array_equal(m.backslash, [True, False, False, True])
    # every triangle is one affine: check the triangle TL, TR, BR of quad (0,0)
    tri_p = px[[0, 0, 1], [0, 1, 1]]
    tri_f = film[[0, 0, 1], [0, 1, 1]]
    A = fit_transform("affine", tri_p, tri_f)
    w = np.random.default_rng(1).dirichlet([1, 1, 1], 300)
    P = w @ tri_p
    np.testing.assert_allclose(m.pixel_to_film(P)[0], A.forward(P), atol=1e-9)


def test_default_mesh_kinds():
    assert default_mesh_kind(3, 3) == "mesh-affine"
    assert default_mesh_kind(11, 11) == "mesh-homography"
    assert default_mesh_kind(5, 5) == "mesh-homography"


@pytest.mark.parametrize("kind", MESH_KINDS)
def test_outside_points_flagged_and_use_the_nearest_border_mesh(kind):
    cam, film, px, tm = _setup()
    m = MeshModel(film, px, kind)
    # film points 1.5 mm left of the reseau's left column, between rows 4 and 5
    y = np.linspace(film[4, 0, 1] - 0.5, film[5, 0, 1] + 0.5, 7)[1:-1]
    q = np.column_stack([np.full_like(y, film[4, 0, 0] - 1.5), y])
    p = tm.film_to_pixel(q)
    f, flags = m.pixel_to_film(p)
    assert np.all(flags == 1)
    assert np.all(m.cells_of_pixel(p) == 4 * 10 + 0)  # quad (4, 0)
    # the extrapolation stays close to the truth (smooth deformation)
    assert np.abs(f - q).max() < 0.005
    if kind == "mesh-homography":
        corners_p = px[[4, 4, 5, 5], [0, 1, 1, 0]]
        corners_f = film[[4, 4, 5, 5], [0, 1, 1, 0]]
        H = fit_transform("projective", corners_p, corners_f)
        np.testing.assert_allclose(f, H.forward(p), atol=1e-9)
    inside = tm.film_to_pixel(film[5:7, 3:5].reshape(-1, 2) * 0.5 + film[4, 4] * 0.5)
    assert np.all(m.pixel_to_film(inside)[1] == 0)


@pytest.mark.parametrize("kind", MESH_KINDS)
@pytest.mark.parametrize(
    "missing",
    [[(5, 5)], [(0, 0)], [(0, 5), (0, 6)], [(10, 10), (9, 9), (5, 2)], "checkerboard"],
    ids=["interior", "corner", "edge-pair", "three", "checkerboard"],
)
def test_missing_crosses_merge_meshes(kind, missing):
    cam, film, px, tm = _setup()
    pm = px.copy()
    if missing == "checkerboard":
        r, c = np.mgrid[0:11, 0:11]
        pm[(r + c) % 2 == 1] = np.nan
        n_missing = 60
    else:
        for r, c in missing:
            pm[r, c] = np.nan
        n_missing = len(missing)
    m = MeshModel(film, pm, kind)
    assert len(m.filled) == n_missing
    assert "merged around missing" in m.describe()
    # the measured crosses are still exact, the round trip still closes
    ok = np.all(np.isfinite(pm), axis=2)
    f, _ = m.pixel_to_film(px[ok])
    assert np.abs(f - film[ok]).max() < 1e-9
    q = _format_points(cam, 5000, margin=2.0)
    back = m.pixel_to_film(m.film_to_pixel(q)[0])[0]
    assert np.abs(back - q).max() <= 1e-6
    # and the correction stays accurate where crosses are missing (smooth 40 um field)
    p = tm.film_to_pixel(q)
    err = np.hypot(*(m.pixel_to_film(p)[0] - q).T) * 1000
    assert np.sqrt(np.mean(err**2)) < (4.0 if missing == "checkerboard" else 2.5)


def test_too_few_crosses_names_method_and_counts():
    cam, film, px, tm = _setup()
    pm = np.full_like(px, np.nan)
    pm[0, :3] = px[0, :3]
    msg = r"mesh-homography needs at least 4 measured reseau crosses, got 3 of 121"
    with pytest.raises(SoftplotError, match=msg):
        MeshModel(film, pm, "mesh-homography")


def test_folded_grid_refused():
    cam, film, px, tm = _setup()
    bad = px.copy()
    bad[5, 5], bad[5, 6] = px[5, 6].copy(), px[5, 5].copy()  # two crosses swapped
    with pytest.raises(SoftplotError, match="folded"):
        MeshModel(film, bad, "mesh-homography")


def test_bad_shapes_and_kind():
    cam, film, px, tm = _setup()
    with pytest.raises(SoftplotError, match="unknown mesh kind"):
        MeshModel(film, px, "mesh-spline")
    with pytest.raises(SoftplotError, match="rows, cols, 2"):
        MeshModel(film.reshape(-1, 2), px.reshape(-1, 2))
    with pytest.raises(SoftplotError, match="at least 2 x 2"):
        MeshModel(film[:1], px[:1])


def test_nan_points_give_nan():
    cam, film, px, tm = _setup()
    m = MeshModel(film, px)
    q = np.array([[100.0, 200.0], [np.nan, 3.0], [2500.0, 2500.0]])
    f, _ = m.pixel_to_film(q)
    assert np.all(np.isfinite(f[[0, 2]])) and np.all(np.isnan(f[1]))


def test_homography_mesh_edge_slip_is_small():
    """Two homographies that share an edge agree at its ends only: measure the slip."""
    cam, film, px, tm = _setup()
    m = MeshModel(film, px, "mesh-homography")
    H = m.film_cell_homographies()
    slip = []
    for r in range(10):
        for c in range(9):  # vertical edge between quads (r, c) and (r, c+1)
            a, b = film[r, c + 1], film[r + 1, c + 1]
            t = np.linspace(0, 1, 11)[:, None]
            e = np.column_stack([a + t * (b - a), np.ones(11)])
            p1 = e @ H[r * 10 + c].T
            p2 = e @ H[r * 10 + c + 1].T
            slip.append(np.abs(p1[:, :2] / p1[:, 2:] - p2[:, :2] / p2[:, 2:]).max())
    # in pixels at 2400 dpi (0.05 px = 0.5 um; measured 0.018 px for this 40 um field)
    assert max(slip) < 0.05


def test_calibrated_reseau_coordinates_are_used():
    """A certificate with calibrated cross positions (a few um off the nominal grid): the mesh
    takes the calibrated film coordinates, not the nominal ones."""
    from dataclasses import replace

    cam = load_camera("rollei-6006")
    R = cam.reseau
    rng = np.random.default_rng(4)
    cal = R.nominal_film().reshape(R.rows, R.cols, 2) + rng.normal(0, 0.004, (R.rows, R.cols, 2))
    cam = cam.with_(reseau=replace(R, calibrated=cal))
    film = cam.reseau.film().reshape(R.rows, R.cols, 2)
    np.testing.assert_allclose(film, cal)
    w, h = cam.format_mm
    tm = TruthMapping(Deformation.random(cam.format_mm, 40.0, 50.0, rng),
                      Scanner(2400.0, 1.0, 0.0, 2700.0, 2650.0))
    px = tm.film_to_pixel(film)
    for kind in MESH_KINDS:
        m = MeshModel(film, px, kind)
        assert np.abs(m.pixel_to_film(px.reshape(-1, 2))[0] - film.reshape(-1, 2)).max() < 1e-9
        q = _format_points(cam, 5000)
        e = np.hypot(*(m.pixel_to_film(tm.film_to_pixel(q))[0] - q).T) * 1000
        assert np.sqrt(np.mean(e**2)) < 2.0
        # the nominal grid instead would leave the calibration's 4 um scatter in
        mn = MeshModel(R.nominal_film().reshape(R.rows, R.cols, 2), px, kind)
        en = np.hypot(*(mn.pixel_to_film(tm.film_to_pixel(q))[0] - q).T) * 1000
        assert np.sqrt(np.mean(en**2)) > 2 * np.sqrt(np.mean(e**2))
