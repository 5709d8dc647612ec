"""No invented calibration: built-in certificates carry no distortion and no principal-point
offset unless a published calibration is cited; ``correct --to photo`` says when there is none."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from softplot.camera import builtin_names, load_camera, parse_certificate, to_toml
from softplot.cli import main
from softplot.errors import CertificateError
from softplot.orientation.interior import InteriorOrientation

SCALE = 20.0  # px per film mm of the hand-made detection below


@pytest.mark.parametrize("name", builtin_names())
def test_builtins_carry_no_invented_calibration(name):
    cam = load_camera(name)
    if cam.uncalibrated:
        assert (cam.x0, cam.y0) == (0.0, 0.0)
        assert cam.distortion.model == "none"
        # exact truth: with no calibration film -> photo is the identity, even at the corner
        w, h = cam.format_mm
        film = np.array([[w / 2, h / 2], [-w / 2, h / 3], [0.0, 0.0], [1.25, -h / 2]])
        np.testing.assert_array_equal(InteriorOrientation(cam).film_to_photo(film), film)
    else:  # a calibration must be named and cited
        assert cam.calibration and any(cam.calibration in n for n in cam.notes)


def test_calibration_none_refuses_invented_values():
    base = to_toml(load_camera("rollei-6006"))
    assert 'calibration = "none"' in base
    assert parse_certificate(base, "x").uncalibrated
    bad_k1 = base.replace('model = "none"', 'model = "brown"\nk1 = -2e-05')
    with pytest.raises(CertificateError, match="calibration.*distortion"):
        parse_certificate(bad_k1, "x")
    bad_pp = base.replace("x0_mm = 0.0", "x0_mm = 0.01")
    with pytest.raises(CertificateError, match="calibration.*principal point"):
        parse_certificate(bad_pp, "x")
    cited = bad_k1.replace('calibration = "none"', 'calibration = "Lab cert. 42 (2019)"')
    cam = parse_certificate(cited, "x")
    assert not cam.uncalibrated and cam.distortion.k1 == -2e-05
    assert parse_certificate(to_toml(cam), "y") == cam


def _detection(tmp_path, cam):
    xy = cam.reseau.film()
    rc = cam.reseau.row_col()
    marks = [
        {"kind": "reseau", "name": n, "row": int(r), "col": int(c),
         "x": 600.0 + SCALE * x, "y": 600.0 - SCALE * y, "status": "measured"}
        for n, (r, c), (x, y) in zip(cam.reseau.names(), rc, xy, strict=True)
    ]
    det = {"image": "s.tif", "camera": cam.name, "width": 1200, "height": 1200, "marks": marks}
    p = tmp_path / "s.det.json"
    p.write_text(json.dumps(det))
    return p


def _run(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in argv])
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def test_correct_to_photo_says_when_there_is_no_calibration(tmp_path, capsys):
    cam = load_camera("rollei-6006")
    det = _detection(tmp_path, cam)
    film = np.array([[27.0, 27.0], [-20.0, 5.0], [3.0, -26.5]])
    inp = tmp_path / "in.csv"
    with inp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["name", "x", "y"])
        for i, (x, y) in enumerate(film):
            w.writerow([f"p{i}", 600.0 + SCALE * x, 600.0 - SCALE * y])
    code, out, err = _run(["correct", det, "-c", "rollei-6006", "--points", inp,
                           "--out", tmp_path / "a.csv", "--to", "photo", "-m", "affine"], capsys)
    assert code == 0, err
    assert "no calibration" in out
    rows = list(csv.DictReader((tmp_path / "a.csv").open()))
    got = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    np.testing.assert_allclose(got, film, atol=2e-6)  # identity: no made-up correction
    # a cited calibration: no note, and its distortion is applied
    cert = tmp_path / "cal.toml"
    cert.write_text(to_toml(cam).replace('calibration = "none"', 'calibration = "Lab cert. 42"')
                    .replace('model = "none"', 'model = "brown"\nk1 = -2e-05'))
    code, out, err = _run(["correct", det, "-c", cert, "--points", inp,
                           "--out", tmp_path / "b.csv", "--to", "photo", "-m", "affine"], capsys)
    assert code == 0, err
    assert "no calibration" not in out
    rows = list(csv.DictReader((tmp_path / "b.csv").open()))
    got = np.array([[float(r["x"]), float(r["y"])] for r in rows])
    np.testing.assert_allclose(got, InteriorOrientation(load_camera(cert)).film_to_photo(film),
                               atol=2e-6)
    # film mode never prints the note
    code, out, _ = _run(["correct", det, "-c", "rollei-6006", "--points", inp,
                         "--out", tmp_path / "c.csv", "-m", "affine"], capsys)
    assert code == 0 and "no calibration" not in out
