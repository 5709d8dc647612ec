"""A measurement is tied to what it measured: a detection applied to another scan or with
another camera is refused in one line naming both; ``--force`` applies it with a warning."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import tifffile

from softplot.camera import load_camera
from softplot.cli import main
from softplot.io import fingerprint

SCALE = 20.0


def _run(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in argv])
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


@pytest.fixture()
def files(tmp_path):
    rng = np.random.default_rng(0)
    left, right = tmp_path / "LEFT.tif", tmp_path / "RIGHT.tif"
    for p in (left, right):
        tifffile.imwrite(p, rng.integers(0, 255, (1200, 1200), dtype=np.uint8))
    cam = load_camera("rollei-6006")
    marks = [
        {"kind": "reseau", "name": n, "row": int(r), "col": int(c),
         "x": 600.0 + SCALE * x, "y": 600.0 - SCALE * y, "status": "measured"}
        for n, (r, c), (x, y) in zip(cam.reseau.names(), cam.reseau.row_col(),
                                     cam.reseau.film(), strict=True)
    ]

    def det(name, scan, camera="rollei-6006", record=True):
        d = {"image": scan.name, "camera": camera, "width": 1200, "height": 1200,
             "marks": marks}
        if record:
            d["scan"] = fingerprint(scan)
        p = tmp_path / name
        p.write_text(json.dumps(d))
        return p

    pts = tmp_path / "in.csv"
    with pts.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["name", "x", "y"])
        w.writerow(["a", 700.0, 500.0])
    return {"left": left, "right": right, "det": det, "pts": pts, "dir": tmp_path}


def _correct(scan, det, out, capsys, *extra, camera="rollei-6006"):
    return _run(["correct", scan, "-c", camera, "-d", det, "--points", det.parent / "in.csv",
                 "--out", out, "-m", "affine", *extra], capsys)


def test_detection_of_another_scan_is_refused_naming_both(files, capsys):
    d = files["dir"]
    right_det = files["det"]("RIGHT.detection.json", files["right"])
    code, out, err = _correct(files["left"], right_det, d / "o.csv", capsys)
    assert code == 2 and not (d / "o.csv").exists()
    msg = err.strip().splitlines()
    assert len(msg) == 1 and "LEFT.tif" in msg[0] and "RIGHT.tif" in msg[0]
    assert "--force" in msg[0]
    # its own scan: fine
    code, out, err = _correct(files["right"], right_det, d / "o.csv", capsys)
    assert code == 0, err
    assert "warning" not in out + err
    # --force: applied, with a warning in the output
    code, out, err = _correct(files["left"], right_det, d / "f.csv", capsys, "--force")
    assert code == 0, err
    assert "warning" in out and "RIGHT.tif" in out and (d / "f.csv").exists()


def test_detection_without_fingerprint_checked_by_name(files, capsys):
    d = files["dir"]
    old = files["det"]("old.json", files["right"], record=False)
    code, _, err = _correct(files["left"], old, d / "o.csv", capsys)
    assert code == 2 and "RIGHT.tif" in err and "LEFT.tif" in err


def test_detection_of_another_camera_is_refused_naming_both(files, capsys):
    d = files["dir"]
    det = files["det"]("pentax.json", files["left"], camera="pentax-645")
    code, _, err = _correct(files["left"], det, d / "o.csv", capsys)
    assert code == 2 and "pentax-645" in err and "rollei-6006" in err
    assert not (d / "o.csv").exists()
    # a detection alone (no scan): the camera is still checked
    code, _, err = _run(["correct", det, "-c", "rollei-6006", "--points", files["pts"],
                         "--out", d / "o.csv", "-m", "affine"], capsys)
    assert code == 2 and "pentax-645" in err
    code, out, err = _correct(files["left"], det, d / "o.csv", capsys, "--force")
    assert code == 0 and "warning" in out and "pentax-645" in out


def test_detect_records_the_scan_fingerprint(tmp_path, capsys):
    from softplot.synthetic import ScanSpec, write_scan

    img, _ = write_scan(tmp_path, "pentax-645", ScanSpec(dpi=300.0, scene="none"), seed=1,
                        stem="s")
    js = tmp_path / "s.det.json"
    code, _, err = _run(["detect", img, "--camera", "pentax-645", "--json", js], capsys)
    assert code == 0, err
    doc = json.loads(js.read_text())
    assert doc["scan"] == fingerprint(img) and doc["camera"] == "pentax-645"
    other = tmp_path / "other.tif"
    other.write_bytes(img.read_bytes()[:-1] + bytes([img.read_bytes()[-1] ^ 1]))
    code, _, err = _run(["correct", other, "-c", "pentax-645", "-d", js, "--points",
                         _pts(tmp_path), "--out", tmp_path / "o.csv"], capsys)
    assert code == 2 and "sha256" in err and "s.tif" in err


def _pts(d):
    p = d / "p.csv"
    p.write_text("name,x,y\na,100,100\n")
    return p
