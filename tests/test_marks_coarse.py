"""The coarse stage of reseau detection: the lattice at the certificate's spacing among clutter,
quarter frames named from the format's edges, ``--grid-part`` when the user knows the part."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from softplot.camera import load_camera
from softplot.errors import SoftplotError
from softplot.io import Scan
from softplot.marks import detect, grid
from softplot.marks.detect import format_grid_part, parse_grid_part
from softplot.synthetic import ScanSpec, render_scan


def _points(seed, rows=range(5), cols=range(5), rot_deg=3.0, n_clutter=400, decoy=0.89):
    """Peaks of a part of the Rollei reseau (pixel system, 1200 dpi) among uniform clutter and
    a decoy lattice at ``decoy`` times the pitch (what JPEG block corners or a periodic scene
    give), in an image that ends half a pitch beyond the part."""
    cam = load_camera("rollei-6006")
    res = cam.reseau
    ppm = 1200 / 25.4
    th = np.radians(rot_deg)
    Rm = ppm * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]) @ np.diag([1, -1])
    rc = res.row_col()
    sel = np.isin(rc[:, 0], list(rows)) & np.isin(rc[:, 1], list(cols))
    film = res.film()
    rng = np.random.default_rng(seed)
    pix = film @ Rm.T
    lo = pix[sel].min(0) - 0.5 * res.pitch_x * ppm
    pix = pix - lo
    size = tuple(int(v) for v in pix[sel].max(0) + 0.5 * res.pitch_x * ppm)
    true_xy = pix[sel] + rng.normal(0, 0.4, (sel.sum(), 2))
    clutter = rng.uniform(0, size, (n_clutter, 2))
    g = np.arange(0, max(size), decoy * res.pitch_x * ppm)
    dx, dy = np.meshgrid(g + 17.0, g + 9.0)
    dec = np.column_stack([dx.ravel(), dy.ravel()])
    dec = dec[(dec < size).all(1)]
    xy = np.vstack([true_xy, clutter, dec])
    score = np.concatenate([rng.uniform(0.45, 0.9, sel.sum()), rng.uniform(0.2, 0.7, n_clutter),
                            rng.uniform(0.4, 0.8, len(dec))])
    return xy, score, res, size, ppm, np.where(sel)[0]


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_lattice_keeps_the_certificates_spacing_among_clutter(seed):
    """A quarter of the grid (25 crosses) among 16 times as many clutter peaks and a decoy
    lattice at 0.89x the pitch: the lattice is the certificate's at the given dpi, every cross
    on it with its row and col (the part given), no clutter peak taken for a cross."""
    xy, score, res, size, ppm, nodes = _points(seed)
    g = grid.fit_grid(xy, score, res, size, px_per_mm=ppm, scale_tol=0.03, part=(0, 5, 0, 5))
    assert g is not None
    assert abs(g.px_per_mm / ppm - 1.0) < 0.005
    assert abs(g.rotation_deg - 3.0) < 0.1
    got = dict(zip(g.index.tolist(), g.node.tolist(), strict=True))
    assert all(k < len(nodes) for k in got), "a clutter peak was taken for a cross"
    assert all(got[k] == nodes[k] for k in got)
    assert len(got) >= len(nodes) - 1


def test_lattice_without_the_dpi_still_follows_the_peaks():
    """The dpi being estimated (no ``scale_tol``), the spacing follows the crosses."""
    xy, score, res, size, ppm, nodes = _points(3, rows=range(11), cols=range(11), n_clutter=60,
                                               decoy=0.0 + 1e9)
    g = grid.fit_grid(xy, score, res, size, px_per_mm=ppm * 1.02)
    assert g is not None and abs(g.px_per_mm / ppm - 1.0) < 0.005


def test_grid_part_text():
    assert parse_grid_part("cols=0:12,rows=3:") == (0, 12, 3, None)
    assert parse_grid_part("rows=:4", rows=11, cols=11) == (0, 11, 0, 4)
    assert parse_grid_part({"cols": (2, 5)}) == (2, 5, None, None)
    assert format_grid_part("rows=3:, cols=0:12") == "cols=0:12,rows=3:"
    for bad in ("cols=0-12", "col=0:3", "cols=a:b", "cols=1:2,cols=3:4", ""):
        with pytest.raises(SoftplotError, match="grid-part"):
            parse_grid_part(bad)
    with pytest.raises(SoftplotError, match="not a part of the 11x11 grid"):
        parse_grid_part("cols=5:12", rows=11, cols=11)
    with pytest.raises(SoftplotError, match="not a part"):
        parse_grid_part("rows=4:4", rows=11, cols=11)


def _named(det, truth):
    """(right, wrong, claimed, visible) of a detection against its truth."""
    tm = {m["name"]: m for m in truth["marks"]}
    right = wrong = claimed = 0
    for i, n in enumerate(det.name):
        if det.status[i] != "measured":
            continue
        t = tm[n]
        if t["state"] != "visible":
            claimed += 1
        elif np.hypot(*(det.xy[i] - (t["x"], t["y"]))) > 1.0:
            wrong += 1
        else:
            right += 1
    return right, wrong, claimed, sum(m["state"] == "visible" for m in truth["marks"])


@pytest.mark.parametrize("camera,crop,rot", [
    ("hasselblad-mk70", (0.0, 0.0, 21.0, 21.0), 0.6),   # top-left quarter of a 5 x 5
    ("hasselblad-mk70", (21.0, 21.0, 0.0, 0.0), 90.4),  # bottom-right, a quarter turn
    ("rollei-6006", (27.0, 0.0, 0.0, 27.0), -1.5),      # top-right quarter of an 11 x 11
])
def test_a_quarter_frame_gives_every_cross_it_shows(camera, crop, rot):
    """A true quarter frame, JPEG-compressed with low-contrast 1-px crosses: every visible
    cross measured with its own row and col, nothing claimed outside."""
    import cv2

    spec = ScanSpec(dpi=800, crop_mm=crop, rotation_deg=rot, contrast=0.15, scene="texture",
                    mark_width_scale=0.7)
    img, truth = render_scan(camera, spec, 5)
    ok, enc = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 55])
    img = cv2.imdecode(enc, cv2.IMREAD_UNCHANGED)
    rotate = 90.0 if rot > 45 else 0.0
    det = detect(Scan.from_array(img, dpi=800), camera, rotate=rotate)
    right, wrong, claimed, visible = _named(det, truth)
    assert (wrong, claimed) == (0, 0)
    assert right == visible and visible < len(det)


@pytest.fixture(scope="module")
def strip():
    """A Rollei scan cut through rows above and below (no format edge on that axis), off the
    frame's centre: which rows it shows, the scan cannot tell."""
    return render_scan("rollei-6006", ScanSpec(dpi=500, crop_mm=(0, 4, 0, 26)), 7)


def test_grid_part_names_a_strip_the_scan_cannot_name(strip):
    img, truth = strip
    rows = sorted({m["row"] for m in truth["marks"] if m["state"] == "visible"})
    sc = Scan.from_array(img, dpi=500)
    plain = detect(sc, "rollei-6006")
    assert any("could be several" in w for w in plain.warnings)
    det = detect(sc, "rollei-6006", grid_part=f"rows={rows[0]}:{rows[-1] + 1}")
    right, wrong, claimed, visible = _named(det, truth)
    assert (wrong, claimed) == (0, 0) and right == visible
    assert not any("could be several" in w for w in det.warnings)


def _cli(*args):
    return subprocess.run([sys.executable, "-c", "from softplot.cli import main; main()",
                           *args], capture_output=True, text=True)


@pytest.mark.parametrize("part,msg", [("cols=1-3", "expected cols=A:B"),
                                      ("cols=0:12", "not a part of the 11x11 grid")])
def test_cli_bad_grid_part_is_one_line_exit_2(tmp_path, part, msg):
    from softplot.io import save_tiff

    p = tmp_path / "s.tif"
    save_tiff(p, np.full((64, 64), 128, np.uint8), dpi=600)
    r = _cli("detect", str(p), "--camera", "rollei-6006", "--grid-part", part)
    assert r.returncode == 2, r.stderr
    errs = [ln for ln in r.stderr.splitlines() if "rror" in ln]
    assert len(errs) == 1 and msg in errs[0], r.stderr  # one line says what is wrong


@pytest.mark.parametrize("command", ["process", "batch"])
def test_process_and_batch_pass_grid_part_and_record_it(monkeypatch, tmp_path, command):
    """``--grid-part`` given to process or batch reaches the detection of every scan (written
    the one way) and is among the settings a rerun must match."""
    from click.testing import CliRunner

    import softplot.pipeline.batch as bat
    import softplot.pipeline.process as proc
    from softplot.cli import cli

    seen = {}

    class Rep:
        rows: list = []
        failed = interrupted = 0

        def table(self):
            return ""

    def fake_process(paths, out, progress=True, **kw):
        seen.update(kw)
        return Rep()

    def fake_batch(scans, out, fn, kw, **_):
        seen.update(kw)
        return Rep()

    monkeypatch.setattr(proc, "process_scans", fake_process)
    monkeypatch.setattr(bat, "run_batch", fake_batch)
    monkeypatch.setattr(proc, "write_report", lambda *a, **k: tmp_path / "r.html")
    monkeypatch.setattr(proc, "load_results", lambda *a, **k: [])
    scan = tmp_path / "s.tif"
    scan.write_bytes(b"x")
    r = CliRunner().invoke(cli, [command, str(scan), "--camera", "rollei-6006", "--out",
                                 str(tmp_path / "o"), "--grid-part", "rows=2:5, cols=0:6"])
    assert r.exit_code == 0, r.output
    assert seen["grid_part"] == "cols=0:6,rows=2:5"
    assert bat.settings_of(seen)["grid_part"] == "cols=0:6,rows=2:5"


@pytest.mark.parametrize("scale", [1.6, 2.0])
def test_a_larger_centre_cross_is_measured_too(scale):
    """Crosses of different sizes on one plate (the centre cross ``scale`` times the others):
    every one measured, the large one as precisely as a cross of its own size allows."""
    spec = ScanSpec(dpi=1300, centre_scale=scale, scene="texture", crop_mm=(14, 14, 14, 14),
                    mark_arm_scale=0.64, mark_width_scale=1.8, contrast=0.3)
    img, truth = render_scan("rollei-6006", spec, 11)
    det = detect(Scan.from_array(img, dpi=1300), "rollei-6006")
    right, wrong, claimed, visible = _named(det, truth)
    assert (wrong, claimed) == (0, 0) and right == visible
    i = det.name.index("R5C5")
    t = next(m for m in truth["marks"] if m["name"] == "R5C5")
    assert det.status[i] == "measured"
    assert np.hypot(*(det.xy[i] - (t["x"], t["y"]))) < 0.1
