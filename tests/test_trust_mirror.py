"""A scan mirrored left-right (scanned through the film base): ``--mirror`` measures it with
every mark named from the right side, in the scan's own pixels; the JSON records it and the
correction made from it gives the true film coordinates; the output says when the side rests on
the option (every mirror-symmetric layout)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import tifffile

from softplot.camera import builtin_names, load_camera
from softplot.cli import main
from softplot.io import load_scan
from softplot.mirror import detect_oriented, mirror_symmetric
from softplot.synthetic import ScanSpec, TruthMapping, render_scan, write_scan


def run(args):
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    return e.value.code


@pytest.fixture(scope="module")
def mirrored(tmp_path_factory):
    d = tmp_path_factory.mktemp("mirror")
    img, truth_p = write_scan(d, "pentax-645", ScanSpec(dpi=400.0, scene="none",
                                                        rotation_deg=0.7), seed=3, stem="s")
    truth = json.loads(truth_p.read_text())
    data = tifffile.imread(img)
    m = d / "m.tif"
    tifffile.imwrite(m, np.ascontiguousarray(data[:, ::-1]), resolution=(400.0, 400.0),
                     resolutionunit="INCH")
    return d, img, m, truth


def test_mirrored_scan_measured_with_true_names(mirrored):
    d, img, m, truth = mirrored
    cam = load_camera("pentax-645")
    w = truth["width"]
    true_xy = {t["name"]: (w - 1.0 - t["x"], t["y"]) for t in truth["marks"] if t["visible"]}
    det = detect_oriented(load_scan(m), cam, mirror=True)
    got = {n: det.xy[i] for i, n in enumerate(det.name) if det.status[i] == "measured"}
    assert len(got) >= 8
    err = max(np.hypot(*(np.asarray(got[n]) - true_xy[n])) for n in got)
    assert err < 0.2  # px: every cross named from the right side, at its place in the file
    # without --mirror the same scan names the crosses from the wrong side
    det0 = detect_oriented(load_scan(m), cam, mirror=False)
    got0 = {n: det0.xy[i] for i, n in enumerate(det0.name) if det0.status[i] == "measured"}
    assert max(np.hypot(*(np.asarray(got0[n]) - true_xy[n])) for n in got0 if n in true_xy) > 50


def test_mirror_recorded_and_carried_to_the_correction(mirrored, tmp_path, capsys):
    d, img, m, truth = mirrored
    js = tmp_path / "m.json"
    assert run(["detect", m, "--camera", "pentax-645", "--mirror", "--json", js]) == 0
    out = capsys.readouterr().out
    assert "rests on --mirror" in out and "given: mirrored" in out
    doc = json.loads(js.read_text())
    assert doc["mirror"] is True and doc["side_from"] == "--mirror"
    # points of the mirrored file -> film mm, against the exact truth
    tm = TruthMapping.from_truth(truth)
    film = np.random.default_rng(0).uniform(-20, 20, (20, 2))
    px = tm.film_to_pixel(film)

    def correct(scan, det, px, stem):
        pts = tmp_path / f"{stem}.csv"
        pts.write_text("name,x,y\n" + "".join(f"p{i},{x:.6f},{y:.6f}\n"
                                               for i, (x, y) in enumerate(px)))
        o = tmp_path / f"{stem}.out.csv"
        assert run(["correct", scan, "-c", "pentax-645", "-d", det, "--points", pts, "--out", o,
                    "-m", "affine"]) == 0
        rows = [r.split(",") for r in o.read_text().splitlines()[1:]]
        return np.array([[float(r[1]), float(r[2])] for r in rows])

    pm = px.copy()
    pm[:, 0] = truth["width"] - 1.0 - pm[:, 0]
    xy_m = correct(m, js, pm, "m")
    js0 = tmp_path / "s.json"
    assert run(["detect", img, "--camera", "pentax-645", "--json", js0]) == 0
    xy_0 = correct(img, js0, px, "s")
    # the mirrored scan gives the film coordinates the upright scan gives (same crosses, same
    # correction), both at the truth within the affine model's residual deformation
    assert np.abs(xy_m - xy_0).max() < 0.002
    assert np.abs(xy_m - film).max() < 0.03


@pytest.mark.parametrize("name", builtin_names())
def test_symmetry_of_the_builtin_layouts(name):
    cam = load_camera(name)
    assert mirror_symmetric(cam)  # every built-in: the side rests on --mirror
    fids = [f for f in cam.fiducials]
    if fids:  # one fiducial moved off the axis: no longer symmetric
        f0 = fids[0]
        moved = cam.with_(fiducials=(f0.__class__(**{**f0.__dict__, "x": f0.x + 3.0,
                                                     "y": f0.y}), *fids[1:]))
        assert not mirror_symmetric(moved)


# ---------------------------------------------------------------- asymmetric layouts
#: four corner crosses and an off-axis dot: no turn or mirror maps the layout onto itself
ASYMMETRIC = Path(__file__).parent / "data" / "asymmetric-fiducials.toml"


@pytest.fixture(scope="module")
def asym(tmp_path_factory):
    """An upright scan of the asymmetric layout, the same scan mirrored, turned 90 degrees,
    and the truth (pixel positions in the upright scan)."""
    d = tmp_path_factory.mktemp("asym")
    cam = load_camera(ASYMMETRIC)
    img, truth = render_scan(cam, ScanSpec(dpi=300, rotation_deg=0.6, scene="texture"), 5)
    out = {}
    for key, im in (("upright", img), ("mirrored", img[:, ::-1]), ("turned", np.rot90(img))):
        p = d / f"{key}.tif"
        tifffile.imwrite(p, np.ascontiguousarray(im), resolution=(300.0, 300.0),
                         resolutionunit="INCH")
        out[key] = p
    return d, out, truth


def _detect_cli(scan, capsys, *extra, camera=ASYMMETRIC):
    js = scan.with_suffix(".json")
    js.unlink(missing_ok=True)
    code = run(["detect", scan, "--camera", camera, "--json", js, *extra])
    out = capsys.readouterr()
    return code, out.out, out.err, js


def test_asymmetric_layout_is_never_mirrored_or_turned_silently(asym, capsys):
    assert mirror_symmetric(load_camera(ASYMMETRIC)) is False
    d, scans, truth = asym
    true_xy = {m["name"]: (m["x"], m["y"]) for m in truth["marks"]}
    w = truth["width"]
    # the right orientation: every mark, named right; the side comes from the marks
    code, out, err, js = _detect_cli(scans["upright"], capsys)
    assert code == 0, err
    doc = json.loads(js.read_text())
    assert doc["side_from"] == "marks" and "rests on --mirror" not in out
    got = {m["name"]: (m["x"], m["y"]) for m in doc["marks"] if m["status"] == "measured"}
    assert set(got) == set(true_xy)
    assert max(np.hypot(*np.subtract(got[n], true_xy[n])) for n in got) < 0.3
    # a mirrored scan without --mirror, a turned one without --rotate, and a wrong --mirror:
    # one line naming what the marks show and the options to give; nothing written
    for scan, extra, shows, give in (
        (scans["mirrored"], [], "mirrored left-right", "give --mirror"),
        (scans["turned"], [], "turned 90 degrees", "give --rotate 90"),
        (scans["turned"], ["--rotate", "90", "--mirror"], "not mirrored", "give --rotate 90"),
        (scans["upright"], ["--mirror"], "not mirrored", "give neither"),
    ):
        code, out, err, js = _detect_cli(scan, capsys, *extra)
        assert code == 2, (scan, extra, out)
        assert len(err.strip().splitlines()) == 1
        assert shows in err and give in err, err
        assert not js.exists()
    # the options that match the scan: measured, every mark named from the right side
    code, out, err, js = _detect_cli(scans["mirrored"], capsys, "--mirror")
    assert code == 0, err
    got = {m["name"]: (m["x"], m["y"]) for m in json.loads(js.read_text())["marks"]}
    assert max(np.hypot(got[n][0] - (w - 1.0 - x), got[n][1] - y)
               for n, (x, y) in true_xy.items()) < 0.3
    code, out, err, js = _detect_cli(scans["turned"], capsys, "--rotate", "90")
    assert code == 0, err
    assert all(m["status"] == "measured" for m in json.loads(js.read_text())["marks"])


def test_symmetric_layout_says_the_options_decide(asym, tmp_path, capsys):
    """The same corners without the dot look the same every way: the mirrored scan is
    measured as given, and the output says that side and names rest on the options."""
    d, scans, _ = asym
    sym = tmp_path / "symmetric.toml"
    text = ASYMMETRIC.read_text()
    sym.write_text(text[: text.index('[[fiducials]]\nname = "5"')]
                   .replace('"test-asymmetric"', '"test-symmetric"'))
    assert mirror_symmetric(load_camera(sym))
    code, out, err, js = _detect_cli(scans["mirrored"], capsys, camera=sym)
    assert code == 0, err
    assert "rests on --mirror" in out and "rest on --rotate" in out
    assert json.loads(js.read_text())["side_from"] == "--mirror"


def test_process_refuses_a_contradicted_orientation(asym, tmp_path, capsys):
    """``process`` (and ``batch``, through the same detection) fails the scan with the same
    line; the summary names it."""
    d, scans, _ = asym
    out = tmp_path / "o"
    code = run(["process", scans["mirrored"], "--camera", ASYMMETRIC, "--out", out])
    capsys.readouterr()
    assert code == 1
    summary = (out / "summary.csv").read_text()
    assert "mirrored left-right" in summary and "give --mirror" in summary
