"""Output a surveyor can read: units and standard deviations in the orientation reports,
model points as a CSV from relor, restituted points compared with check points."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from softplot.cli import main
from softplot.cli._orient import report
from softplot.pipeline.demo import run_demo


@pytest.fixture(scope="module")
def tour(tmp_path_factory):
    out = tmp_path_factory.mktemp("tour")
    run_demo(out, progress=False)
    for side in ("left", "right"):
        code = main_code(["correct", str(out / f"{side}.tif"), "--camera", "rollei-6006",
                          "--detection", str(out / f"{side}.detection.json"), "--points",
                          str(out / f"points-{side}.csv"), "--out", str(out / f"photo-{side}.csv"),
                          "--to", "photo"])
        assert code == 0
    return out


def main_code(args) -> int:
    try:
        main(args)
    except SystemExit as e:
        return e.code
    return 0


def _run(args, capsys):
    with pytest.raises(SystemExit) as e:
        main(args)
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def _invoke(args, capsys):
    code, out, err = _run(args, capsys)
    assert code == 0, err
    return out


def test_std_never_printed_as_zero():
    txt = report("T", [], [("by", "model", 0.0123456, 3.2e-6, 4)], 1.0, None, 3, "mm")
    line = next(ln for ln in txt.splitlines() if ln.startswith("by"))
    assert "0.0000032" in line and "model" in line
    assert " 0.0000 " not in line + " "


def test_relor_csv_and_units_absor_units(tour, capsys):
    t = tour
    out = _invoke(["relor", "--camera", "rollei-6006", "--left", str(t / "photo-left.csv"),
                   "--right", str(t / "photo-right.csv"), "--bx", "1", "--sigma-image", "0.002",
                   "--json", str(t / "relor.json"), "--csv", str(t / "model.csv")], capsys)
    by = next(ln for ln in out.splitlines() if ln.startswith("by "))
    assert "model" in by and not by.rstrip().endswith(" 0.0000")
    pts = {p["name"]: p for p in json.loads((t / "relor.json").read_text())["points"]}
    rows = list(csv.DictReader((t / "model.csv").open()))
    assert list(rows[0]) == ["name", "x", "y", "z"] and len(rows) == len(pts)
    for r in rows:
        p = pts[r["name"]]
        assert np.allclose([float(r["x"]), float(r["y"]), float(r["z"])],
                           [p["X"], p["Y"], p["Z"]], rtol=0, atol=1e-6)
    out = _invoke(["absor", "--model", str(t / "model.csv"), "--control",
                   str(t / "control.csv"), "--json", str(t / "absor.json")], capsys)
    for name in ("TX", "TY", "TZ"):
        line = next(ln for ln in out.splitlines() if ln.startswith(name + " "))
        assert "object" in line
    code, _, err = _run(["relor", "--camera", "rollei-6006", "--left", str(t / "photo-left.csv"),
                         "--right", str(t / "photo-right.csv"), "--csv",
                         str(t / "photo-left.csv")], capsys)
    assert code == 2 and "would overwrite the input file" in err


def test_restitute_check_rms(tour, capsys):
    t = tour
    out = _invoke(["restitute", "--photos", str(t / "photos.csv"), "--mode", "free",
                   "--points", str(t / "check-photo.csv"), "--out", str(t / "chk.csv"),
                   "--check", str(t / "check.csv")], capsys)
    rms_line = next(ln for ln in out.splitlines() if ln.startswith("RMS"))
    rms = np.array([float(v) for v in rms_line.split()[1:4]])
    # the same RMS from the files
    got = {r["name"]: r for r in csv.DictReader((t / "chk.csv").open())}
    ref = {r["name"]: r for r in csv.DictReader((t / "check.csv").open())}
    d = np.array([[float(got[n][k]) - float(ref[n][k]) for k in "XYZ"] for n in got if n in ref])
    dec = len(rms_line.split()[1].split(".")[1])
    assert np.allclose(rms, np.sqrt((d**2).mean(0)), rtol=0, atol=10.0**-dec)
