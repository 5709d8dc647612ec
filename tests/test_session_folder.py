"""Session folders are data: film corrections as JSON + npz, scans tied by content, upgrades.

Film corrections are stored as what defines them (certificate, method, reference marks) and
rebuilt by the same fit, so the numbers are bit-identical; nothing in a session folder is a
pickle; a session names its scans by path and content and says when they moved or changed;
version-1 folders (pickled corrections) are converted by ``softplot plot upgrade``.
"""

from __future__ import annotations

import json
import os
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest

from softplot.cli import main
from softplot.correction import (
    FilmCorrection,
    ScanPhotoMap,
    load_correction,
    save_correction,
)
from softplot.errors import SoftplotError
from softplot.io import Scan, fingerprint, load_scan
from softplot.marks import detect
from softplot.pipeline.session import Session, scan_photo_map, upgrade_session
from softplot.stereo import OrientedPhoto, StereoModel
from softplot.synthetic import ScanSpec, render_scan
from softplot.synthetic.files import write_image

DATA = Path(__file__).parent / "data"
CAM = "pentax-645"


def _run(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    """Two small Pentax 645 scans on disk with their detections."""
    d = tmp_path_factory.mktemp("scans")
    out = []
    for k in range(2):
        img, _ = render_scan(CAM, ScanSpec(dpi=300, deform_um=10.0, rotation_deg=0.4 - 0.7 * k,
                                           noise_sigma=0.005), seed=40 + k)
        p = write_image(d / f"s{k}.tif", img, 300, "tif")
        det = detect(Scan.from_array(img, dpi=300), CAM).to_json()
        det["scan"] = fingerprint(p)
        dp = d / f"s{k}.detection.json"
        dp.write_text(json.dumps(det))
        out.append((p, dp, det))
    return out


def _model(maps):
    return StereoModel(
        OrientedPhoto([0, 0, 100], np.deg2rad([0.3, -0.2, 1.0]), 75.0, name="L",
                      to_photo=maps[0], to_film=maps[0].inverse),
        OrientedPhoto([30, 0, 100], np.deg2rad([-0.1, 0.4, 0.5]), 75.0, name="R",
                      to_photo=maps[1], to_film=maps[1].inverse),
    )


def test_film_correction_as_data_is_bit_identical(scans, tmp_path):
    _, _, det = scans[0]
    fc = FilmCorrection.from_detection(CAM, det, "mesh")
    p = save_correction(fc, tmp_path / "c.json")
    back, meta = load_correction(p)
    assert meta["method"] == fc.method and back.method == fc.method
    rng = np.random.default_rng(3)
    px = np.c_[rng.uniform(-5, 700, 10_000), rng.uniform(-5, 560, 10_000)]
    for to in ("film", "photo"):
        a, fa = fc.pixel_to(px, to=to)
        b, fb = back.pixel_to(px, to=to)
        assert np.array_equal(a, b, equal_nan=True) and np.array_equal(fa, fb)
    mm = fc.pixel_to(px, to="photo")[0]
    assert np.array_equal(fc.to_pixel(mm, frm="photo")[0], back.to_pixel(mm, frm="photo")[0],
                          equal_nan=True)
    # the arrays are plain data: a pickle-free load reads them
    with np.load(tmp_path / "c.npz", allow_pickle=False) as z:
        assert "marks.grid_pixel" in z.files


def test_session_round_trip_holds_no_pickle_and_same_numbers(scans, tmp_path):
    maps = [scan_photo_map(p, CAM, dp) for p, dp, _ in scans]
    model = _model(maps)
    Session.create(tmp_path / "s", model, mode="single").close()
    s = Session.resume(tmp_path / "s")
    rng = np.random.default_rng(4)
    instr = rng.uniform(-25, 25, (10_000, 2))
    for a, b in ((model.left, s.model.left), (model.right, s.model.right)):
        assert np.array_equal(a.film_to_photo(instr), b.film_to_photo(instr), equal_nan=True)
        ph = a.film_to_photo(instr[:500])
        assert np.array_equal(a.photo_to_film(ph), b.photo_to_film(ph), equal_nan=True)
    for f in (tmp_path / "s").rglob("*"):
        if f.is_file():
            assert not f.read_bytes().startswith(b"\x80"), f"{f} looks like a pickle"
            if f.suffix == ".npz":
                np.load(f, allow_pickle=False).close()
            elif f.suffix == ".json":
                json.loads(f.read_text())
    meta = json.loads((tmp_path / "s" / "session.json").read_text())
    assert meta["format"] == "softplot-session" and meta["version"] == 2
    assert meta["photos"]["left"]["camera"] == CAM
    assert meta["photos"]["left"]["scan"]["sha256"] == scans[0][2]["scan"]["sha256"]
    assert s.scan_path("left") == scans[0][0].resolve()
    s.close()


def test_moved_or_changed_scans_are_named(scans, tmp_path):
    work = tmp_path / "w"
    work.mkdir()
    paths = []
    for p, _, _ in scans:
        q = work / p.name
        shutil.copy(p, q)
        paths.append(q)
    maps = [scan_photo_map(q, CAM, dp) for q, (_, dp, _) in zip(paths, scans, strict=True)]
    Session.create(work / "s", _model(maps)).close()
    s = Session.resume(work / "s")
    assert s.scan_path("right") == paths[1].resolve()
    # moved: the error names where the session expects it
    os.replace(paths[0], work / "elsewhere.tif")
    with pytest.raises(SoftplotError, match=rf"left scan is missing: expected at .*{paths[0].name}"
                       ):
        s.scan_path("left")
    # moved back with a new modification time: the content decides, accepted
    shutil.copy(work / "elsewhere.tif", paths[0])
    assert s.scan_path("left") == paths[0].resolve()
    # changed in place (same size): refused
    data = bytearray(paths[1].read_bytes())
    data[-100] ^= 0xFF
    paths[1].write_bytes(bytes(data))
    with pytest.raises(SoftplotError, match="right scan has changed.*sha256"):
        s.scan_path("right")
    # the plotting itself does not need the scans: resume still works
    assert Session.resume(work / "s").model.right.name == "R"


def test_a_detection_of_another_scan_is_refused(scans):
    (p0, _, _), (_, dp1, _) = scans
    with pytest.raises(SoftplotError, match="not the scan"):
        scan_photo_map(p0, CAM, dp1)


def test_plot_new_with_scans_from_the_cli(scans, tmp_path, capsys):
    photos = tmp_path / "photos.csv"
    photos.write_text("photo,X0,Y0,Z0,omega,phi,kappa,c\nL,0,0,100,0,0,0,75\n"
                      "R,30,0,100,0,0,0,75\n")
    (p0, d0, _), (p1, d1, _) = scans
    code, out, err = _run(["plot", "new", str(tmp_path / "s"), "--photos", str(photos),
                           "--left-scan", str(p0), "--right-scan", str(p1), "--camera", CAM,
                           "--left-detection", str(d0), "--right-detection", str(d1)], capsys)
    assert code == 0, err
    s = Session.resume(tmp_path / "s")
    m = s.photo_map("left")
    sc = load_scan(p0)
    assert isinstance(m, ScanPhotoMap)
    assert (m.frame.width, m.frame.height) == (sc.width, sc.height)
    assert m.frame.pixel_mm == pytest.approx(25.4 / 300)
    # a cross measured in the scan maps to its certificate film position (within 5 um)
    det = scans[0][2]
    cross = next(c for c in det["marks"] if c["status"] == "measured" and c["name"] == "R1C1")
    film = m.correction.pixel_to([[cross["x"], cross["y"]]], to="film")[0][0]
    assert np.hypot(*film) < 0.005  # R1C1 is the centre cross of the 3 x 3 reseau
    code, _, err = _run(["plot", "new", str(tmp_path / "t"), "--photos", str(photos),
                         "--left-scan", str(p0), "--right-scan", str(p1), "--camera", CAM,
                         "--left-detection", str(d1), "--right-detection", str(d0)], capsys)
    assert code == 2 and "not the scan" in err and "\n" == err[-1] and err.count("\n") == 1
    code, _, err = _run(["plot", "new", str(tmp_path / "u"), "--photos", str(photos),
                         "--left-scan", str(p0)], capsys)
    assert code == 2 and "both --left-scan and --right-scan" in err


def test_version_1_folders_are_upgraded_to_data(tmp_path, capsys):
    folder = tmp_path / "old"
    shutil.copytree(DATA / "session-v1", folder)
    with pytest.raises(SoftplotError, match="softplot plot upgrade"):
        Session.resume(folder)
    code, out, err = _run(["plot", "upgrade", str(folder)], capsys)
    assert code == 0, err
    assert not (folder / "corrections.pkl").exists() and (folder / "corrections.pkl.v1").exists()
    s = Session.resume(folder)
    assert s.mode == "contour" and s.height == 12.5 and len(s.features) == 1
    exp = json.loads((folder / "expected.json").read_text())
    for side, p in (("left", s.model.left), ("right", s.model.right)):
        instr = np.array(exp[side]["instrument_mm"])
        want = np.array(exp[side]["photo_mm"])
        assert np.array_equal(p.film_to_photo(instr), want)
        back = np.array(exp[side]["back_mm"])
        assert np.max(np.abs(p.photo_to_film(want) - back)) < 1e-12
    code, _, err = _run(["plot", "upgrade", str(folder)], capsys)
    assert code == 2 and "already a version-2 session" in err


class _Evil:
    def __reduce__(self):
        return (os.system, ("touch PWNED",))


def test_upgrade_runs_no_foreign_code(tmp_path, monkeypatch):
    folder = tmp_path / "evil"
    shutil.copytree(DATA / "session-v1", folder)
    (folder / "corrections.pkl").write_bytes(pickle.dumps({"left": (_Evil(), None)}))
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SoftplotError, match="refusing to load"):
        upgrade_session(folder)
    assert not (tmp_path / "PWNED").exists()
    assert (folder / "corrections.pkl").exists()  # nothing changed
    assert json.loads((folder / "session.json").read_text()).get("version", 1) == 1
