"""``softplot detect``: JSON keys, QC plot, MicMac XML, bad input, several scans (issue 3)."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from softplot.io import save_tiff
from softplot.marks.micmac import read_measures_im
from softplot.synthetic import ScanSpec, write_scan

KEYS = {"image", "camera", "width", "height", "dpi", "polarity", "marks", "transform", "rms_px",
        "warnings"}
MARK_KEYS = {"kind", "name", "row", "col", "x", "y", "sigma", "score", "status"}


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-c", "from softplot.cli import main; main()", "detect",
                           *args],
                          capture_output=True, text=True, cwd=cwd)


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    d = tmp_path_factory.mktemp("detect")
    a, ta = write_scan(d, "rollei-6006", ScanSpec(dpi=700, cover=2), seed=31, stem="ra")
    b, tb = write_scan(d, "rollei-6006", ScanSpec(dpi=650, polarity="negative"), seed=32,
                       stem="rb")
    save_tiff(d / "blank.tif", np.full((1600, 1600), 180, np.uint8), dpi=700)
    return d, (a, ta), (b, tb)


def test_cli_json_plot_micmac(scans):
    d, (a, ta), _ = scans
    out = d / "ra.json"
    r = run(str(a), "--camera", "rollei-6006", "--json", str(out), "--plot", str(d / "qc.png"),
            "--micmac", str(d / "mm"))
    assert r.returncode == 0, r.stderr
    assert "ra.tif: 119/121 marks measured" in r.stdout
    doc = json.loads(out.read_text())
    assert KEYS <= set(doc)
    assert doc["scene"] in ("opening", "joint")
    assert len(doc["marks"]) == 121
    truth = json.loads(ta.read_text())
    tm = {m["name"]: m for m in truth["marks"]}
    for m in doc["marks"]:
        assert MARK_KEYS <= set(m)
        assert m["kind"] == "reseau" and m["name"] == f"R{m['row']}C{m['col']}"
        t = tm[m["name"]]
        if m["status"] == "measured":
            assert t["visible"] and abs(m["x"] - t["x"]) < 0.1 and abs(m["y"] - t["y"]) < 0.1
            assert 0 < m["sigma"] < 0.1
        else:
            assert m["x"] is None or m["status"] == "rejected"
    assert sum(m["status"] == "missing" for m in doc["marks"]) >= 2  # the covered ones
    assert doc["transform"]["kind"] == "projective"
    assert np.array(doc["transform"]["matrix"]).shape == (3, 3)
    # the QC plot is a PNG that decodes; the MicMac file parses and holds the measured marks
    img = cv2.imread(str(d / "qc.png"))
    assert img is not None and img.shape[0] > 300
    name, pts = read_measures_im(d / "mm" / "MeasuresIm-ra.tif.xml")
    assert name == "ra.tif"
    meas = {m["name"]: (m["x"], m["y"]) for m in doc["marks"] if m["status"] == "measured"}
    assert set(pts) == set(meas)
    k = next(iter(meas))
    assert np.allclose(pts[k], meas[k], atol=1e-3)


def test_cli_several_scans_one_bad(scans):
    d, (a, _), (b, _) = scans
    od = d / "out"
    r = run(str(a), str(d / "blank.tif"), str(b), "--camera", "rollei-6006", "--out-dir", str(od))
    assert r.returncode == 2
    err = [line for line in r.stderr.splitlines() if line.strip()]
    assert any("blank.tif" in line and "blank image" in line for line in err)
    assert "Traceback" not in r.stderr
    assert (od / "ra.json").exists() and (od / "rb.json").exists()
    assert not (od / "blank.json").exists()
    assert json.loads((od / "rb.json").read_text())["polarity"] == "negative"


@pytest.mark.parametrize("args,needle", [
    (["--camera", "rollei-6006", "--dpi", "9000"], "much smaller"),
    (["--camera", "zeiss-rmk-a-15-23"], "much smaller than the zeiss-rmk-a-15-23 fiducial"),
    (["--camera", "zeiss-rmk-a-15-23", "--dpi", "150"], "fiducial marks not found"),
    (["--camera", "no-such-camera"], "unknown camera"),
])
def test_cli_bad_input_one_line_exit_2(scans, args, needle):
    d, (a, _), _ = scans
    r = run(str(a), *args)
    assert r.returncode == 2
    lines = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and needle in lines[0], r.stderr


def test_cli_refuses_to_overwrite_an_input(scans):
    d, (a, _), _ = scans
    r = run(str(a), "--camera", "rollei-6006", "--json", str(a))
    assert r.returncode == 2 and "refusing" in r.stderr
    assert a.stat().st_size > 1000


def test_cli_rotate_and_given_polarity(scans):
    """``--rotate 90 --polarity negative`` on a quarter-turned negative: every cross measured,
    row 0 still the top row of the upright photo; the wrong polarity finds no reseau (exit 2)."""
    d, _, (b, tb) = scans
    img = cv2.imread(str(b), cv2.IMREAD_UNCHANGED)
    turned = d / "rb-turned.tif"
    save_tiff(turned, np.ascontiguousarray(np.rot90(img, 1)), dpi=650)
    out = d / "rb-turned.json"
    r = run(str(turned), "--camera", "rollei-6006", "--rotate", "90", "--polarity", "negative",
            "--scene", "joint", "--json", str(out))
    assert r.returncode == 0, r.stderr
    doc = json.loads(out.read_text())
    assert doc["polarity"] == "negative" and doc["scene"] == "joint"
    marks = {m["name"]: m for m in doc["marks"] if m["status"] == "measured"}
    assert len(marks) >= 120
    W = img.shape[1]
    for t in json.loads(tb.read_text())["marks"]:
        if t["name"] in marks:  # a counter-clockwise quarter turn: (x, y) -> (y, W - 1 - x)
            m = marks[t["name"]]
            assert np.hypot(m["x"] - t["y"], m["y"] - (W - 1 - t["x"])) < 0.1, t["name"]
    wrong = run(str(turned), "--camera", "rollei-6006", "--rotate", "90", "--polarity",
                "positive", "--json", str(d / "rb-wrong.json"))
    assert wrong.returncode == 2
    assert len(wrong.stderr.strip().splitlines()) == 1 and "reseau" in wrong.stderr


def test_cli_keeps_existing_results_without_overwrite(scans):
    d, (a, _), _ = scans
    out = d / "kept.json"
    out.write_text("{}\n", encoding="utf-8")
    mm = d / "mm-kept"
    r = run(str(a), "--camera", "rollei-6006", "--json", str(out), "--micmac", str(mm))
    assert r.returncode == 2
    err = [line for line in r.stderr.splitlines() if line.strip()]
    assert len(err) == 1 and "kept.json: exists" in err[0] and "--overwrite" in err[0]
    assert out.read_text(encoding="utf-8") == "{}\n" and not mm.exists()
    r = run(str(a), "--camera", "rollei-6006", "--json", str(out), "--overwrite")
    assert r.returncode == 0, r.stderr
    assert len(json.loads(out.read_text(encoding="utf-8"))["marks"]) == 121
