"""Dense surface and automatic contours against the exact synthetic surface; no-data."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial import cKDTree

from matching_scenes import make_scene, true_session
from softplot.cli import cli

GSD = 1.5
#: building and blank area of the no-data scene (object m)
BOX = (118.0, 148.0, 55.0, 85.0, 232.0)
BLANK = (10.0, 60.0, -130.0, -80.0)


@pytest.fixture(scope="session")
def scene(tmp_path_factory):
    return make_scene(str(tmp_path_factory.getbasetemp() / "matching-scene"), 600.0)


@pytest.fixture(scope="session")
def dsm_run(scene, tmp_path_factory):
    base = tmp_path_factory.getbasetemp()
    sess = true_session(scene, base / "matching-session")
    out = base / "dsm-out"
    r = CliRunner().invoke(cli, ["dsm", str(sess), "--gsd", str(GSD), "--out",
                                 str(out / "dsm.tif"), "--contours", "5", "--dxf",
                                 str(out / "contours.dxf")])
    assert r.exit_code == 0, r.output
    from softplot.matching.dsm import read_geotiff

    return sess, out, read_geotiff(out / "dsm.tif")


def _height_precision(scene, Zmean):
    """Height precision implied by B/H and 0.2 scan px matching, m."""
    p = scene.pair
    H = p.X0[:, 2].mean() - Zmean
    B = np.linalg.norm(p.X0[1] - p.X0[0])
    return H / B * H / p.c[0] * 0.2 * 25.4 / scene.dpi


def _overlap_cells(scene, dsm, margin_mm=1.0):
    """Cells seen by both photos: inside both scans and both formats (the textured area of
    the film), away from the format's edge and from the reseau crosses by ``margin_mm``."""
    X, Y = dsm.centres()
    Zt = scene.terrain[0].surface(X, Y)
    P = np.c_[X.ravel(), Y.ravel(), Zt.ravel()]
    keep = scene.terrain[0].visible(P) & scene.terrain[1].visible(P)
    tree = cKDTree(scene.camera.reseau.film())
    half = 0.5 * np.asarray(scene.camera.format_mm) - margin_mm
    for k in range(2):
        film = scene.io.photo_to_film(scene.pair.photo(k, P))
        px = scene.mapping[k].film_to_pixel(film)
        keep &= np.all((px > 30) & (px < 1350), axis=1)
        keep &= np.all(np.abs(film) < half, axis=1)
        keep &= tree.query(film)[0] > margin_mm
    return keep.reshape(X.shape), Zt


def test_dsm_heights_within_the_precision(scene, dsm_run):
    _, _, dsm = dsm_run
    valid = np.isfinite(dsm.Z)
    X, Y = dsm.centres()
    Zt = scene.terrain[0].surface(X, Y)
    err = (dsm.Z - Zt)[valid]
    tol = 1.5 * _height_precision(scene, float(np.mean(Zt[valid])))
    assert valid.sum() > 5000
    assert np.sqrt(np.mean(err**2)) < tol, (np.sqrt(np.mean(err**2)), tol)
    # the precision band is there and positive where there is a height
    assert np.all(np.isfinite(dsm.sigma[valid])) and np.all(dsm.sigma[valid] > 0)
    assert np.all(np.isnan(dsm.sigma[~valid]))


def test_dsm_covers_the_textured_overlap(scene, dsm_run):
    _, _, dsm = dsm_run
    cells, _ = _overlap_cells(scene, dsm)
    assert cells.sum() > 20000
    share = float(np.isfinite(dsm.Z)[cells].mean())
    assert share >= 0.90, share


def test_dsm_precision_describes_the_error(scene, dsm_run):
    """The stated per-cell standard deviation is the actual error's: err / sigma has an
    RMS near 1 over the valid cells (neither optimistic nor pessimistic by 1.5 x)."""
    _, _, dsm = dsm_run
    valid = np.isfinite(dsm.Z)
    X, Y = dsm.centres()
    ne = ((dsm.Z - scene.terrain[0].surface(X, Y)) / dsm.sigma)[valid]
    rms = float(np.sqrt(np.mean(ne**2)))
    assert 0.67 <= rms <= 1.5, rms
    # and not by a few large errors alone: the share within 2 sigma as for a normal law
    assert 0.85 <= float(np.mean(np.abs(ne) < 2.0)) <= 0.995


def test_contours_follow_the_true_surface(scene, dsm_run):
    import ezdxf

    _, out, dsm = dsm_run
    doc = ezdxf.readfile(out / "contours.dxf")
    lines = [e for e in doc.modelspace() if e.dxf.layer == "CONTOUR"]
    assert len(lines) > 5
    gj = json.loads((out / "contours.geojson").read_text())
    assert len(gj["features"]) == len(lines)
    V = np.vstack([np.asarray(f["geometry"]["coordinates"], float).reshape(-1, 3)
                   for f in gj["features"]])
    dz = scene.terrain[0].surface(V[:, 0], V[:, 1]) - V[:, 2]
    X, Y = dsm.centres()
    Zt = scene.terrain[0].surface(X, Y)
    tol = 1.5 * _height_precision(scene, float(np.nanmean(np.where(np.isfinite(dsm.Z), Zt,
                                                                   np.nan))))
    assert np.sqrt(np.mean(dz**2)) < tol, (np.sqrt(np.mean(dz**2)), tol)


def test_geotiff_tags_and_sidecar(dsm_run):
    import tifffile

    _, out, dsm = dsm_run
    with tifffile.TiffFile(out / "dsm.tif") as tf:
        page = tf.pages[0] if len(tf.pages) else None
        tags = page.tags
        assert tags[33550].value[:2] == (GSD, GSD)
        tie = tags[33922].value
        assert tags[42113].value == "-9999"
        assert 34735 in tags
        a = tf.asarray()
    assert a.dtype == np.float32 and a.shape[0] == 2
    side = json.loads((out / "dsm.json").read_text())
    for k in ("x0", "y0", "gsd", "nodata"):
        assert k in side
    assert side["x0"] == pytest.approx(tie[3] + GSD / 2)
    assert side["y0"] == pytest.approx(tie[4] - GSD / 2)


def test_occlusion_and_blank_area_are_no_data(tmp_path_factory):
    base = tmp_path_factory.getbasetemp()
    sc = make_scene(str(base / "matching-scene-box"), 400.0, box=BOX, blank=BLANK)
    sess = true_session(sc, base / "matching-session-box")
    from softplot.cli.epipolar import open_session
    from softplot.matching.dsm import dense_surface

    s, maps, scans = open_session(sess)
    dsm = dense_surface(s.model, maps, [x.data for x in scans], GSD)
    X, Y = dsm.centres()
    valid = np.isfinite(dsm.Z)
    Zt = sc.terrain[0].surface(X, Y)
    # occluded: the whole cell (centre and corners) hidden from one photo
    hidden = np.zeros(X.shape, bool)
    for dx, dy in ((0, 0), (-1, -1), (-1, 1), (1, -1), (1, 1)):
        Xs, Ys = X + 0.5 * GSD * dx, Y + 0.5 * GSD * dy
        P = np.c_[Xs.ravel(), Ys.ravel(), sc.terrain[0].surface(Xs, Ys).ravel()]
        h = ~(sc.terrain[0].visible(P) & sc.terrain[1].visible(P))
        hidden = hidden | h.reshape(X.shape) if (dx, dy) == (0, 0) else hidden & h.reshape(
            X.shape)
    x0, x1, y0, y1, _ = BOX
    near_box = (X > x0 - 20) & (X < x1 + 20) & (Y > y0 - 20) & (Y < y1 + 20)
    occl = hidden & near_box
    assert occl.sum() > 20
    assert valid[occl].mean() < 0.02, valid[occl].mean()
    # the blank area (shrunk by the matching window's reach): no data
    m = 3.0
    inner = ((X > BLANK[0] + m) & (X < BLANK[1] - m) & (Y > BLANK[2] + m) & (Y < BLANK[3] - m))
    assert inner.sum() > 100
    assert valid[inner].mean() < 0.02, valid[inner].mean()
    # where there are heights near the building they are right (not invented)
    ok = valid & near_box
    err = np.abs(dsm.Z - Zt)[ok]
    assert np.median(err) < 0.3
