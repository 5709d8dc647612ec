"""Automatic tie points (softplot match) against exact synthetic truth, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from matching_scenes import make_scene, true_right
from matching_scenes import run_cli as run


@pytest.fixture(scope="session")
def scene(tmp_path_factory):
    return make_scene(str(tmp_path_factory.getbasetemp() / "matching-scene"), 600.0)


@pytest.fixture(scope="session")
def ties(scene):
    from softplot.cli.match import load_pair
    from softplot.matching.ties import match_pair

    _, scans, maps = load_pair(*scene.scans, scene.camera.name, *scene.detections)
    return match_pair(scans[0], scans[1], maps[0], maps[1]), maps


def test_ties_within_a_tenth_of_a_pixel(ties, scene):
    res, _ = ties
    assert res.n >= 100
    truth, seen = true_right(scene, res.left_px)
    assert seen.all()
    err = res.right_px - truth
    rms = float(np.sqrt(np.mean(np.sum(err**2, axis=1))))
    assert rms < 0.1, rms
    # the stated precision is realistic (LSM's own estimate, within a factor 2)
    z = err / res.std_px
    assert 0.5 < float(np.sqrt(np.mean(z**2))) < 2.0
    # well distributed: ties in all six Gruber areas
    assert min(res.gruber) >= 3, res.gruber
    assert res.rms_px < 0.15


def test_relative_orientation_equals_truth_within_its_std(ties, scene):
    from softplot.orientation.relative import relative_orientation

    res, maps = ties
    truth, _ = true_right(scene, res.left_px)
    p1 = maps[0].pixel_to_photo(res.left_px)
    p2 = maps[1].pixel_to_photo(truth)
    ref = relative_orientation(p1, p2, scene.camera.c, bx=1.0, sigma=0.001)
    std = res.ro.std
    for k in ("by", "bz", "omega2", "phi2", "kappa2"):
        d = res.ro.value(k) - ref.value(k)
        assert abs(d) < 3.0 * std[k], (k, d, std[k])


def test_match_cli_writes_pixel_csvs(scene, tmp_path):
    out = tmp_path / "ties"
    code, text = run(["match", str(scene.scans[0]), str(scene.scans[1]), "--camera",
                      "rollei-6006", "--detection-left", str(scene.detections[0]),
                      "--detection-right", str(scene.detections[1]), "--out", str(out)])
    assert code == 0, text
    from softplot.correction import read_points_csv

    nl, xl = read_points_csv(out / "left.csv")
    nr, xr = read_points_csv(out / "right.csv")
    assert nl == nr and len(nl) >= 100
    meta = json.loads((out / "match.json").read_text())
    assert meta["n"] == len(nl) and meta["rms_px"] < 0.15 and 0.3 < meta["sigma0"] < 3
    # the ties feed softplot correct as they are
    code, text = run(["correct", str(scene.scans[0]), "--camera", "rollei-6006",
                      "--detection", str(scene.detections[0]), "--points",
                      str(out / "left.csv"), "--out", str(tmp_path / "left-photo.csv"),
                      "--to", "photo"])
    assert code == 0, text
    # a second run refuses to overwrite
    before = (out / "left.csv").read_bytes()
    code, text = run(["match", str(scene.scans[0]), str(scene.scans[1]), "--camera",
                      "rollei-6006", "--out", str(out)])
    assert code == 2 and "refusing to overwrite" in text and text.count("\n") <= 1
    assert (out / "left.csv").read_bytes() == before


def _unchanged(folder):
    return {p.name: p.read_bytes() for p in folder.iterdir()}


@pytest.fixture
def old_out(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine\n")
    return out


def test_pair_that_does_not_overlap(scene, tmp_path, old_out):
    from softplot.synthetic import ScanSpec, write_scan

    other, _ = write_scan(tmp_path, "rollei-6006", ScanSpec(dpi=600, scene="texture"), seed=9,
                          stem="other")
    before = _unchanged(old_out)
    code, text = run(["match", str(scene.scans[0]), str(other), "--camera", "rollei-6006",
                      "--detection-left", str(scene.detections[0]), "--out", str(old_out)])
    assert code == 2
    assert "overlap" in text or "too few ties" in text
    assert text.strip().count("\n") == 0
    assert _unchanged(old_out) == before


def test_wrong_camera(scene, old_out):
    before = _unchanged(old_out)
    code, text = run(["match", str(scene.scans[0]), str(scene.scans[1]), "--camera",
                      "hasselblad-mk70", "--out", str(old_out)])
    assert code == 2 and "hasselblad-mk70" in text and text.strip().count("\n") == 0
    assert _unchanged(old_out) == before


def test_too_few_ties(scene, old_out):
    before = _unchanged(old_out)
    code, text = run(["match", str(scene.scans[0]), str(scene.scans[1]), "--camera",
                      "rollei-6006", "--detection-left", str(scene.detections[0]),
                      "--detection-right", str(scene.detections[1]), "--max-ties", "4",
                      "--out", str(old_out)])
    assert code == 2 and "too few ties" in text and "6" in text
    assert _unchanged(old_out) == before


def test_relor_auto_sets_up_the_model(scene, tmp_path):
    out = tmp_path / "ro.json"
    code, text = run(["relor", "--auto", str(scene.scans[0]), str(scene.scans[1]), "--camera",
                      "rollei-6006", "--ties", str(tmp_path / "ties"), "--json", str(out)])
    assert code == 0, text
    data = json.loads(out.read_text())
    assert len(data["points"]) >= 100
    # the same model as from the truth pixels of the same left points
    from softplot.cli.match import load_pair
    from softplot.correction import read_points_csv
    from softplot.orientation.relative import relative_orientation

    names, left_px = read_points_csv(tmp_path / "ties" / "left.csv")
    truth, _ = true_right(scene, left_px)
    _, _, maps = load_pair(*scene.scans, "rollei-6006", *scene.detections)
    ref = relative_orientation(maps[0].pixel_to_photo(left_px), maps[1].pixel_to_photo(truth),
                               scene.camera.c, bx=100.0, sigma=0.001)
    assert abs(data["by"] - ref.value("by")) < 3 * data["std"]["by"]
    assert abs(data["bz"] - ref.value("bz")) < 3 * data["std"]["bz"]


def test_relor_needs_points_or_auto():
    code, text = run(["relor", "--camera", "rollei-6006"])
    assert code == 2 and "--auto" in text
