"""``softplot correct``: points, photo coordinates, resampling, comparison, bad input."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from softplot.camera import load_camera
from softplot.cli import main
from softplot.orientation.interior import InteriorOrientation
from softplot.synthetic import ScanSpec, TruthMapping, write_scan

DPI = 800.0


def _run(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in argv])
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


@pytest.fixture(scope="module")
def scan(tmp_path_factory):
    d = tmp_path_factory.mktemp("correct")
    spec = ScanSpec(dpi=DPI, scene="none", deform_um=40.0, rotation_deg=1.2, noise_sigma=0.01,
                    blur_sigma_px=0.8, cover=("R3C4",), offset_px=(30.0, -20.0))
    img, truth_path = write_scan(d, "rollei-6006", spec, seed=3, stem="roll")
    truth = json.loads(truth_path.read_text())
    det = {
        "image": img.name,
        "camera": "rollei-6006",
        "width": truth["width"],
        "height": truth["height"],
        "marks": [
            {
                "kind": m["kind"], "name": m["name"], "row": m["row"], "col": m["col"],
                "x": m["x"] if m["visible"] else None, "y": m["y"] if m["visible"] else None,
                "status": "measured" if m["visible"] else "missing",
            }
            for m in truth["marks"]
        ],
    }
    det_path = d / "roll.det.json"
    det_path.write_text(json.dumps(det))
    tm = TruthMapping.from_truth(truth)
    return {"dir": d, "img": img, "truth": truth, "det": det_path, "tm": tm}


def _points_file(path, tm, film, extra=()):
    px = tm.film_to_pixel(film)
    with path.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["name", "x", "y", "comment"])
        for i, (x, y) in enumerate(px):
            w.writerow([f"p{i}", repr(float(x)), repr(float(y)), "c"])
        for row in extra:
            w.writerow(row)
    return path


def _read_out(path):
    rows = list(csv.DictReader(path.open()))
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    return [r["name"] for r in rows], xy, [r["flag"] for r in rows]


def test_points_to_film_with_detection(scan, tmp_path, capsys):
    film = np.random.default_rng(0).uniform(-27, 27, (300, 2))
    inp = _points_file(tmp_path / "in.csv", scan["tm"], film, extra=[["far", "-500", "40", ""]])
    out = tmp_path / "out.csv"
    code, so, se = _run(["correct", scan["img"], "--camera", "rollei-6006", "--detection",
                         scan["det"], "--points", inp, "--out", out], capsys)
    assert code == 0, se
    assert "mesh-homography" in so and "merged around missing R3C4" in so
    names, xy, flags = _read_out(out)
    assert names[:2] == ["p0", "p1"] and names[-1] == "far"
    assert flags[-1] == "outside-image"
    err = np.hypot(*(xy[:-1] - film).T) * 1000
    assert np.sqrt(np.mean(err**2)) < 2.0  # um
    inside = np.all(np.abs(film) < 24.9, axis=1)
    assert all(f == "ok" for f, i in zip(flags[:-1], inside, strict=True) if i)
    assert {"ok", "outside-reseau", "outside-image"} >= set(flags)
    assert "outside-reseau" in flags


def test_points_to_photo_and_other_spellings(scan, tmp_path, capsys):
    film = np.random.default_rng(1).uniform(-24, 24, (50, 2))
    inp = _points_file(tmp_path / "in.csv", scan["tm"], film)
    out_f, out_p = tmp_path / "film.csv", tmp_path / "photo.csv"
    code, _, se = _run(["correct", "--camera", "rollei-6006", scan["img"], "-d", scan["det"],
                        "--points", inp, "--out", out_f, "--method", "mesh-bilinear"], capsys)
    assert code == 0, se
    code, _, se = _run(["correct", "points", scan["img"], "-c", "rollei-6006", "-d", scan["det"],
                        "--points", inp, "--out", out_p, "--to", "photo",
                        "--method", "mesh-bilinear"], capsys)
    assert code == 0, se
    _, f, _ = _read_out(out_f)
    _, p, _ = _read_out(out_p)
    io = InteriorOrientation(load_camera("rollei-6006"))
    np.testing.assert_allclose(p, io.film_to_photo(f), atol=2e-6)  # 6 decimals in the CSV


def test_points_without_detection_runs_the_detector(scan, tmp_path, capsys):
    film = np.random.default_rng(2).uniform(-24, 24, (100, 2))
    inp = _points_file(tmp_path / "in.csv", scan["tm"], film)
    out = tmp_path / "out.csv"
    code, so, se = _run(["correct", scan["img"], "-c", "rollei-6006", "--points", inp,
                         "--out", out], capsys)
    assert code == 0, se
    assert "detecting marks" in se
    _, xy, flags = _read_out(out)
    err = np.hypot(*(xy - film).T) * 1000
    assert np.sqrt(np.mean(err**2)) < 2.5


def test_resample_writes_film_grid_tiff_and_sidecar(scan, tmp_path, capsys):
    import tifffile

    out = tmp_path / "flat.tif"
    code, so, se = _run(["correct", scan["img"], "-c", "rollei-6006", "-d", scan["det"],
                         "--resample", out, "--pixel-size", "25"], capsys)
    assert code == 0, se
    side = tmp_path / "flat.tif.json"
    meta = json.loads(side.read_text())
    ps = meta["pixel_size_mm"]
    assert ps == pytest.approx(0.025)
    with tifffile.TiffFile(out) as tf:
        page = tf.pages[0]
        img = page.asarray()
        scale = page.tags[33550].value
        tie = page.tags[33922].value
        desc = json.loads(page.description)
    assert img.shape == (meta["height"], meta["width"]) == (2240, 2240)
    assert scale[:2] == pytest.approx((ps, ps))
    assert tie[3:5] == pytest.approx((meta["x_min_mm"], meta["y_max_mm"]))
    assert desc["pixel_centre_to_film"] == meta["pixel_centre_to_film"]
    # the crosses sit where the film grid says: darkness centroid of a window holding the
    # whole cross (arms 0.8 mm = 32 output px; window 41 px, so no arm is cut off)
    cam = load_camera("rollei-6006")
    film = cam.reseau.film()
    a = np.array(meta["pixel_centre_to_film"])
    inv = np.linalg.inv(np.vstack([a, [0, 0, 1]]))
    errs = []
    for name, (x, y) in zip(cam.reseau.names(), film, strict=True):
        if name == "R3C4":
            continue  # covered
        c, r, _ = inv @ [x, y, 1.0]
        ci, ri = int(round(c)), int(round(r))
        win = img[ri - 20 : ri + 21, ci - 20 : ci + 21].astype(float)
        dark = np.clip(np.median(win) - win, 0, None)
        dark[dark < 0.3 * dark.max()] = 0.0  # keep the cross, drop the noise
        yy, xx = np.mgrid[ri - 20 : ri + 21, ci - 20 : ci + 21]
        errs.append([(dark * xx).sum() / dark.sum() - c, (dark * yy).sum() / dark.sum() - r])
    errs = np.array(errs)
    # output px (25 um): the crosses are on the grid (a plain centroid, not the LSM detector)
    assert np.sqrt(np.mean(errs**2)) < 0.1
    assert np.abs(errs.mean(axis=0)).max() < 0.03
    # never overwrite: the same command again is refused, and so is the sidecar
    code, _, se = _run(["correct", scan["img"], "-c", "rollei-6006", "-d", scan["det"],
                        "--resample", out], capsys)
    assert code == 2 and "exists" in se


def test_compare_from_detection_json(scan, tmp_path, capsys):
    js = tmp_path / "cv.json"
    code, so, se = _run(["correct", "compare", scan["det"], "-c", "rollei-6006", "--json", js],
                        capsys)
    assert code == 0, se
    assert "LOO rms" in so and "recommended: mesh" in so
    d = json.loads(js.read_text())
    by = {m["method"]: m for m in d["methods"]}
    assert by["mesh-homography"]["loo_rms_um"] < by["affine"]["loo_rms_um"] / 3
    assert d["recommended"].startswith("mesh")
    assert by["mesh-homography"]["loo_n"] == 120  # R3C4 is covered


def test_compare_from_scan_runs_the_detector(scan, capsys):
    code, so, se = _run(["correct", "compare", scan["img"], "-c", "rollei-6006",
                         "--method", "affine", "--method", "mesh-homography"], capsys)
    assert code == 0, se
    assert "detecting marks" in se and "recommended: mesh-homography" in so


def test_compare_limited_methods(scan, capsys):
    code, so, se = _run(["correct", "compare", scan["det"], "-c", "rollei-6006",
                         "--method", "affine", "--method", "poly2"], capsys)
    assert code == 0, se
    assert "poly2" in so and "mesh-bilinear" not in so


def test_bad_points_file_names_the_line(scan, tmp_path, capsys):
    base = ["correct", scan["img"], "-c", "rollei-6006", "-d", scan["det"]]
    p = tmp_path / "nocol.csv"
    p.write_text("name,x\np1,10\n")
    code, _, se = _run(base + ["--points", p, "--out", tmp_path / "o1.csv"], capsys)
    assert code == 2 and "line 1" in se and "missing column 'y'" in se
    assert "Traceback" not in se
    p = tmp_path / "nan.csv"
    p.write_text("name,x,y\np1,10,20\n\np2,abc,5\n")
    code, _, se = _run(base + ["--points", p, "--out", tmp_path / "o2.csv"], capsys)
    assert code == 2 and "line 4" in se and "x is not a number: 'abc'" in se
    p = tmp_path / "short.csv"
    p.write_text("name,x,y\np1,10\n")
    code, _, se = _run(base + ["--points", p, "--out", tmp_path / "o3.csv"], capsys)
    assert code == 2 and "line 2" in se
    assert not any((tmp_path / f"o{i}.csv").exists() for i in (1, 2, 3))


def test_too_few_marks_names_method_and_counts(scan, tmp_path, capsys):
    det = json.loads(scan["det"].read_text())
    kept = 0
    for m in det["marks"]:
        if m["status"] == "measured":
            kept += 1
            if kept > 3:
                m["status"] = "rejected"
    few = tmp_path / "few.json"
    few.write_text(json.dumps(det))
    p = _points_file(tmp_path / "in.csv", scan["tm"], np.zeros((1, 2)))
    for method, msg in [
        ("mesh", "method mesh needs at least 4 measured reseau crosses, got 3 of 121"),
        ("poly2", "method poly2 needs at least 6 measured reseau crosses, got 3"),
        ("projective", "method projective needs at least 4 measured reseau crosses, got 3"),
    ]:
        code, _, se = _run(["correct", scan["img"], "-c", "rollei-6006", "-d", few, "--method",
                            method, "--points", p, "--out", tmp_path / f"{method}.csv"], capsys)
        assert code == 2 and msg in se, se


def test_refusals(scan, tmp_path, capsys):
    p = _points_file(tmp_path / "in.csv", scan["tm"], np.zeros((1, 2)))
    base = ["correct", scan["img"], "-c", "rollei-6006", "-d", scan["det"]]
    code, _, se = _run(base + ["--points", p, "--out", p], capsys)
    assert code == 2 and "input file" in se
    assert p.read_text().startswith("name,x,y")
    code, _, se = _run(base + ["--points", p, "--out", scan["det"]], capsys)
    assert code == 2 and "refusing to overwrite" in se
    code, _, se = _run(base, capsys)
    assert code == 2 and "nothing to do" in se
    code, _, se = _run(base + ["--points", p], capsys)
    assert code == 2 and "--points needs --out" in se
    code, _, se = _run(base + ["--points", p, "--out", tmp_path / "x.csv", "--method", "tps"],
                       capsys)
    assert code == 2 and "tps" in se
    code, _, se = _run(["correct", scan["img"], "-c", "pentax-645", "-d", scan["det"], "--points",
                        p, "--out", tmp_path / "y.csv"], capsys)
    assert code == 2 and "'rollei-6006'" in se and "'pentax-645'" in se
    code, _, se = _run(base + ["--resample", tmp_path / "flat.png"], capsys)
    assert code == 2 and ".tif" in se
    code, so, se = _run(["correct", "--help"], capsys)
    assert code == 0 and "compare" in so
