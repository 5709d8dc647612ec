"""Normalised (epipolar) images: zero y-parallax by construction, resampled once."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from matching_scenes import make_scene, true_session
from softplot.cli import cli


@pytest.fixture(scope="session")
def scene(tmp_path_factory):
    return make_scene(str(tmp_path_factory.getbasetemp() / "matching-scene"), 600.0)


@pytest.fixture(scope="session")
def epi(scene, tmp_path_factory):
    base = tmp_path_factory.getbasetemp()
    sess = true_session(scene, base / "matching-session")
    out = base / "matching-epipolar"
    r = CliRunner().invoke(cli, ["epipolar", str(sess), "--out", str(out)])
    assert r.exit_code == 0, r.output
    return sess, out


def test_epipolar_rows_carry_no_y_parallax(scene, epi):
    import tifffile

    from softplot.matching.epipolar import load_epipolar
    from softplot.matching.lsm import match_patches

    _, out = epi
    geo, meta = load_epipolar(out)
    L = tifffile.imread(out / "left.tif").astype(np.float32) / 255
    R = tifffile.imread(out / "right.tif").astype(np.float32) / 255
    # true terrain points seen by both photos -> exact normalised pixels through the truth
    P = scene.pair.sample_points(400, seed=3)
    ok = scene.terrain[0].visible(P) & scene.terrain[1].visible(P)
    # away from the reseau crosses (they are on the film, not on the ground)
    crosses = scene.camera.reseau.film()
    for k in range(2):
        film = scene.io.photo_to_film(scene.pair.photo(k, P))
        d = np.min(np.hypot(*(film[:, None, :] - crosses[None]).transpose(2, 0, 1)), axis=1)
        ok &= d > 1.0
    P = P[ok]
    n = []
    for k in range(2):
        ph = scene.pair.photo(k, P)
        n.append(geo.to_pixel(k, geo.from_photo(k, ph, scene.pair.M(k), scene.pair.c[k])))
    # geometry: the same row in both images (the orientation is exact)
    assert np.max(np.abs(n[0][:, 1] - n[1][:, 1])) < 0.05
    # resampling: least-squares matching of the normalised images finds the true positions
    inside = np.all((n[0] > 30) & (n[0] < np.array(L.shape[::-1]) - 30), axis=1) & np.all(
        (n[1] > 30) & (n[1] < np.array(R.shape[::-1]) - 30), axis=1)
    left_px = np.rint(n[0][inside])
    truth = n[1][inside] + (left_px - n[0][inside])  # locally a shift
    pm = match_patches(L, R, left_px, truth + 0.4, half=13)
    good = pm.ok & (pm.corr > 0.8)
    assert good.sum() > 100
    err = pm.xy[good] - truth[good]
    # y-parallax: no bias, matching noise only (a few patches on steep relief are worse)
    assert abs(np.mean(err[:, 1])) < 0.02
    assert np.median(np.abs(err[:, 1])) < 0.06
    assert np.percentile(np.abs(err[:, 1]), 90) < 0.15
    assert np.median(np.abs(err[:, 0])) < 0.1


def test_epipolar_maps_are_kept_and_nothing_overwritten(epi):
    import tifffile

    sess, out = epi
    meta = json.loads((out / "epipolar.json").read_text())
    g = meta["geometry"]
    for side, w in (("left", g["cols"][0]), ("right", g["cols"][1])):
        m = np.load(out / f"{side}.map.npz")
        assert m["mapx"].shape == (g["rows"], w) and m["mapx"].dtype == np.float32
        assert tifffile.imread(out / f"{side}.tif").shape[:2] == (g["rows"], w)
    before = (out / "left.tif").read_bytes()
    r = CliRunner().invoke(cli, ["epipolar", str(sess), "--out", str(out)],
                           standalone_mode=False)
    assert "refusing to overwrite" in str(r.exception)
    assert (out / "left.tif").read_bytes() == before


def test_tiled_resampling_equals_one_remap(scene, tmp_path):
    from softplot.cli.epipolar import open_session
    from softplot.matching.epipolar import resample_pair

    sess = true_session(scene, tmp_path / "s")
    s, maps, scans = open_session(sess)
    imgs = [sc.data for sc in scans]
    _, one, _ = resample_pair(s.model, maps, imgs, 0.1, keep_maps=False, tile_rows=100000)
    _, tiled, _ = resample_pair(s.model, maps, imgs, 0.1, keep_maps=False, tile_rows=37)
    for a, b in zip(one, tiled, strict=True):
        assert np.abs(a.astype(int) - b.astype(int)).max() <= 1


def test_not_a_session(tmp_path):
    r = CliRunner().invoke(cli, ["epipolar", str(tmp_path), "--out", str(tmp_path / "o")],
                           standalone_mode=False)
    assert "not a plotting session" in str(r.exception)
    assert not (tmp_path / "o").exists()
