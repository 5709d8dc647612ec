"""softplot process: synthetic scans with exact truth plus a corrupt one."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from softplot.cli import main
from softplot.synthetic import ScanSpec, write_scan


def run_cli(*args) -> int:
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    return e.value.code


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    d = tmp_path_factory.mktemp("scans")
    specs = [
        ScanSpec(dpi=600, scene="texture", deform_um=15, shrink_ppm=120, rotation_deg=0.3),
        ScanSpec(dpi=600, polarity="negative", scene="busy", deform_um=20, rotation_deg=-0.6,
                 dust=6, file_format="png"),
    ]
    out = [write_scan(d, "rollei-6006", s, seed=i + 1, stem=f"scan{i}") for i, s in
           enumerate(specs)]
    bad = d / "corrupt.tif"
    bad.write_bytes(out[0][0].read_bytes()[:4096])  # a truncated TIFF
    return d, out, bad


def test_process_cli(scans, tmp_path, capsys):
    d, out, bad = scans
    res = tmp_path / "res"
    code = run_cli("process", out[0][0], out[1][0], bad, "--camera", "rollei-6006",
                   "--out", res, "--quiet", "--flatten", "--method", "mesh")
    assert code == 1  # documented: 1 when some scan failed, the others done
    text = capsys.readouterr().out
    assert "2 done, 1 failed" in text and "corrupt.tif" in text
    rows = list(csv.DictReader(open(res / "summary.csv", encoding="utf-8")))
    status = {r["scan"].rsplit("/", 1)[-1]: r["status"] for r in rows}
    assert status == {"scan0.tif": "done", "scan1.png": "done", "corrupt.tif": "failed"}
    err = json.loads((res / "corrupt.error.json").read_text())
    assert err["complete"] is False and "corrupt.tif" in err["error"]
    for (img, truth_path) in out:
        r = json.loads((res / f"{img.stem}.json").read_text())
        assert r["complete"] is True and r["softplot"] == "process"
        truth = json.loads(truth_path.read_text())
        tx = {m["name"]: (m["x"], m["y"]) for m in truth["marks"] if m["visible"]}
        clean = sum(1 for m in truth["marks"] if m["visible"] and not m.get("damaged"))
        meas = [m for m in r["detection"]["marks"] if m["status"] == "measured"]
        assert r["marks_measured"] == len(meas) and r["marks_total"] == 121
        # detection against the exact truth: (nearly) every clean cross, far below 0.1 px
        assert len(meas) >= 0.85 * clean
        d = np.array([[m["x"] - tx[m["name"]][0], m["y"] - tx[m["name"]][1]] for m in meas])
        assert np.sqrt(np.mean(np.sum(d * d, axis=1))) < 0.1
        # per-method comparison: every method scored, the applied one within QC
        names = {m["method"] for m in r["crossval"]["methods"]}
        assert {"affine", "poly3", "mesh-homography"} <= names
        assert r["loo_rms_um"] is not None and r["loo_rms_um"] < 5.0
        assert (res / f"{img.stem}.film.tif").is_file()
        assert len(r["worst"]) == 6
    html = (res / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 4
    assert "scan0.tif" in html and "corrupt.tif" in html


def test_process_bad_input(scans, tmp_path, capsys):
    d, out, _ = scans
    assert run_cli("process", tmp_path / "nope.tif", "--camera", "rollei-6006",
                   "--out", tmp_path / "o") == 2
    assert run_cli("process", out[0][0], "--camera", "no-such-camera",
                   "--out", tmp_path / "o") == 2
    # a file where the result would go is never overwritten without --overwrite (refused
    # before any work), and a foreign one not even with it
    res = tmp_path / "r"
    res.mkdir()
    (res / "scan0.json").write_text('{"mine": 1}')
    assert run_cli("process", out[0][0], "--camera", "rollei-6006", "--out", res,
                   "--quiet") == 2
    assert "--overwrite" in capsys.readouterr().err
    assert run_cli("process", out[0][0], "--camera", "rollei-6006", "--out", res,
                   "--quiet", "--overwrite") == 1
    assert (res / "scan0.json").read_text() == '{"mine": 1}'
    err = capsys.readouterr()
    assert "Traceback" not in err.err + err.out


def test_coarse_film_maps_match_the_exact_maps(scans):
    """The flattening workaround for smooth global methods: same maps to < 1e-3 px."""
    from softplot.correction import FilmCorrection, film_maps
    from softplot.pipeline.process import coarse_film_maps

    truth = json.loads(scans[1][0][1].read_text())
    det = {"marks": [m for m in truth["marks"] if m["visible"]]}
    for method in ("poly3", "projective", "affine"):
        fc = FilmCorrection.from_detection("rollei-6006", det, method)
        exact = film_maps(fc, 0.2)
        fast = coarse_film_maps(fc, 0.2)
        assert exact[2:] == fast[2:]
        assert exact[0].shape == fast[0].shape
        for a, b in zip(exact[:2], fast[:2], strict=True):
            assert np.max(np.abs(a - b)) < 1e-3
