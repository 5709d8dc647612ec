"""``softplot synth`` / ``softplot demo`` and the synthetic scan files."""

from __future__ import annotations

import json

import numpy as np
import pytest

from softplot.cli import main
from softplot.io import load_scan
from softplot.synthetic import ScanSpec, render_scan, write_scan


def run(argv: list[str], capsys) -> tuple[int, str, str]:
    with pytest.raises(SystemExit) as e:
        main(argv)
    out, err = capsys.readouterr()
    return e.value.code, out, err


def test_synth_writes_scans_and_truth(tmp_path, capsys):
    code, out, err = run(["synth", str(tmp_path), "--camera", "hasselblad-mk70", "--count", "2",
                          "--seed", "5", "--dpi", "300", "--deform", "40", "--rotate", "1.5",
                          "--bits", "16"], capsys)
    assert code == 0, err
    for seed in (5, 6):
        img = tmp_path / f"hasselblad-mk70-{seed:04d}.tif"
        truth = json.loads((tmp_path / f"hasselblad-mk70-{seed:04d}.truth.json").read_text())
        assert str(img) in out
        scan = load_scan(img)
        assert (scan.width, scan.height) == (truth["width"], truth["height"])
        assert scan.dpi == pytest.approx(300.0)
        assert scan.bit_depth == 16 and truth["bit_depth"] == 16
        assert truth["image"] == img.name and truth["seed"] == seed
        assert len(truth["marks"]) == 25 and truth["spec"]["rotation_deg"] == 1.5
        # the file holds exactly what render_scan returns for that seed
        spec = ScanSpec(dpi=300, deform_um=40, rotation_deg=1.5, bits=16)
        ref, ref_truth = render_scan("hasselblad-mk70", spec, seed=seed)
        assert np.array_equal(np.asarray(scan.data), ref)
        assert ref_truth["marks"] == truth["marks"]


def test_synth_refuses_to_overwrite(tmp_path, capsys):
    args = ["synth", str(tmp_path), "--camera", "pentax-645", "--dpi", "150"]
    assert run(args, capsys)[0] == 0
    img = tmp_path / "pentax-645-0000.tif"
    before = img.read_bytes()
    code, out, err = run(args + ["--noise", "0.2"], capsys)
    assert code == 2 and "exists" in err and len(err.strip().splitlines()) == 1
    assert img.read_bytes() == before
    code, out, err = run(args + ["--noise", "0.2", "--overwrite"], capsys)
    assert code == 0 and img.read_bytes() != before


@pytest.mark.parametrize(
    "extra,word",
    [
        (["--camera", "no-such-camera"], "unknown camera"),
        (["--camera", "rollei-6006", "--dpi", "-300"], "dpi"),
        (["--camera", "rollei-6006", "--dpi", "abc"], "--dpi"),
        (["--camera", "rollei-6006", "--bits", "12"], "bits"),
        (["--camera", "rollei-6006", "--scene", "forest"], "scene"),
        (["--camera", "rollei-6006", "--format", "gif"], "file_format"),
        (["--camera", "rollei-6006", "--format", "jpg", "--bits", "16"], "JPEG"),
        (["--camera", "rollei-6006", "--count", "0"], "--count"),
        (["--camera", "rollei-6006", "--occlusion", "partial"], "occlusion"),
    ],
)
def test_synth_bad_options_exit_2_one_line(tmp_path, capsys, extra, word):
    code, out, err = run(["synth", str(tmp_path / "o")] + extra, capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and word in lines[0]
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_synth_exact_occlusion(tmp_path, capsys):
    """``--occlusion exact`` renders what ``ScanSpec(occlusion="exact")`` renders and says so
    in the truth."""
    code, out, err = run(["synth", str(tmp_path), "--camera", "pentax-645", "--dpi", "300",
                          "--scene", "busy", "--occlusion", "exact"], capsys)
    assert code == 0, err
    truth = json.loads((tmp_path / "pentax-645-0000.truth.json").read_text())
    assert truth["render"]["occlusion"] == "exact" and truth["spec"]["occlusion"] == "exact"
    ref, _ = render_scan("pentax-645", ScanSpec(dpi=300, scene="busy", occlusion="exact"), 0)
    first, _ = render_scan("pentax-645", ScanSpec(dpi=300, scene="busy"), 0)
    data = np.asarray(load_scan(tmp_path / "pentax-645-0000.tif").data)
    assert np.array_equal(data, ref) and not np.array_equal(data, first)


def test_synth_with_a_certificate_file(tmp_path, capsys):
    from softplot.camera import load_camera, write_certificate

    cert = write_certificate(load_camera("pentax-645").with_(name="my-pentax"),
                             tmp_path / "mine.toml")
    code, out, err = run(["synth", str(tmp_path), "--camera", str(cert), "--dpi", "600",
                          "--negative", "--rgb", "--format", "jpg", "--scene", "none"], capsys)
    assert code == 0, err
    scan = load_scan(tmp_path / "my-pentax-0000.jpg")
    assert scan.channels == 3 and scan.dpi == pytest.approx(600.0)
    truth = json.loads((tmp_path / "my-pentax-0000.truth.json").read_text())
    assert truth["camera"] == "my-pentax" and truth["polarity"] == "negative"
    grey = scan.grey()
    for m in truth["marks"]:  # bright marks survive JPEG
        x, y = int(round(m["x"])), int(round(m["y"]))
        assert grey[y - 1 : y + 2, x - 1 : x + 2].max() > truth["render"]["background"] + 0.05


@pytest.mark.parametrize("fmt,bits", [("tif", 8), ("tif", 16), ("png", 8), ("png", 16),
                                      ("jpg", 8)])
def test_files_are_deterministic_and_read_back(tmp_path, fmt, bits):
    spec = ScanSpec(dpi=200, bits=bits, file_format=fmt, scene="busy", dust=5, grain_sigma=0.01)
    a = write_scan(tmp_path / "a", "rollei-6006", spec, seed=3)
    b = write_scan(tmp_path / "b", "rollei-6006", spec, seed=3)
    for pa, pb in zip(a, b, strict=True):
        assert pa.read_bytes() == pb.read_bytes()
    scan = load_scan(a[0])
    assert scan.dpi == pytest.approx(200.0, abs=0.01)
    ref, _ = render_scan("rollei-6006", spec, seed=3)
    data = np.asarray(scan.data)
    if fmt == "jpg":
        assert np.abs(data.astype(float) - ref).mean() < 3
    else:
        assert np.array_equal(data, ref)
