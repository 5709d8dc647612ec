"""One command line: every command's --help runs, every option has a help text, the angle
option has one name and one default everywhere, detection options are the same in detect,
process and batch, and impossible resolutions are refused at the option."""

from __future__ import annotations

import importlib

import click
import numpy as np
import pytest
from click.testing import CliRunner

from softplot.cli import COMMAND_TABLE, cli


def _walk(cmd, path):
    if isinstance(cmd, click.Group):
        for name, sub in cmd.commands.items():
            yield from _walk(sub, [*path, name])
    yield path, cmd


def _all_commands():
    out = []
    for name, module, _ in COMMAND_TABLE:
        cmd = importlib.import_module(f"softplot.cli.{module}").command
        out.extend(_walk(cmd, [name]))
    return out


ALL = _all_commands()


@pytest.mark.parametrize("path,cmd", ALL, ids=[" ".join(p) for p, _ in ALL])
def test_help_runs_and_every_option_has_help(path, cmd):
    r = CliRunner().invoke(cli, [*path, "--help"])
    assert r.exit_code == 0, r.output
    assert r.output.count("Usage:") == 1, r.output
    assert "``" not in r.output, "raw reStructuredText in the help"
    assert cmd.help, f"softplot {' '.join(path)} has no help text"
    missing = [p.opts[0] for p in cmd.params
               if isinstance(p, click.Option) and not p.hidden and not p.help]
    assert not missing, f"softplot {' '.join(path)}: options without help: {missing}"


def test_one_angle_option_everywhere():
    found = []
    for path, cmd in ALL:
        for p in cmd.params:
            if isinstance(p, click.Option) and p.name == "angle_unit":
                found.append(" ".join(path))
                assert p.opts[0] == "--angles", (path, p.opts)
                assert p.default == "deg", (path, p.default)
            elif isinstance(p, click.Option):
                assert not any("angle" in o for o in p.opts), (path, p.opts)
    for need in ("resect", "intersect", "relor", "absor", "bundle", "calibrate", "restitute",
                 "plot new"):
        assert need in found, f"{need} lacks --angles"


def test_detection_options_in_detect_process_batch():
    by_path = {" ".join(p): c for p, c in ALL}
    for name in ("detect", "process", "batch"):
        opts = {p.name: p for p in by_path[name].params}
        for o in ("polarity", "rotate", "scene", "dpi"):
            assert o in opts, f"{name} lacks --{o}"
        assert opts["polarity"].default == "auto" and opts["scene"].default == "auto"


@pytest.mark.parametrize("argv", [
    ["detect", "x.tif", "--camera", "rollei-6006"],
    ["process", "x.tif", "--camera", "rollei-6006", "--out", "o"],
    ["batch", "x.tif", "--camera", "rollei-6006", "--out", "o"],
])
@pytest.mark.parametrize("dpi", ["0", "-300"])
def test_impossible_dpi_refused_at_the_option(argv, dpi, tmp_path):
    r = CliRunner().invoke(cli, [*argv, "--dpi", dpi])
    assert r.exit_code == 2
    assert "--dpi" in r.output and "x>0" in r.output


def test_process_passes_detection_options(monkeypatch, tmp_path):
    """--polarity/--rotate/--scene given to process reach the detection of every scan."""
    import softplot.pipeline.process as proc

    seen = {}

    class Rep:
        rows: list = []
        failed = 0

        def table(self):
            return ""

    def fake(paths, out, progress=True, **kw):
        seen.update(kw)
        return Rep()

    monkeypatch.setattr(proc, "process_scans", fake)
    monkeypatch.setattr(proc, "write_report", lambda *a, **k: tmp_path / "r.html")
    monkeypatch.setattr(proc, "load_results", lambda *a, **k: [])
    scan = tmp_path / "s.tif"
    scan.write_bytes(b"x")
    r = CliRunner().invoke(cli, ["process", str(scan), "--camera", "rollei-6006", "--out",
                                 str(tmp_path / "o"), "--polarity", "negative", "--rotate",
                                 "90", "--scene", "opening"])
    assert r.exit_code == 0, r.output
    assert (seen["polarity"], seen["rotate"], seen["scene"]) == ("negative", 90.0, "opening")


def test_angles_in_gon_read_by_restitute(tmp_path):
    """restitute reads the photos' angles in the --angles unit: the same pair in deg and gon
    gives the same model points."""
    import csv

    rows = [["photo", "X0", "Y0", "Z0", "omega", "phi", "kappa", "c"],
            ["L", "0", "0", "10", "1.0", "-2.0", "0.5", "80"],
            ["R", "2", "0", "10", "-1.5", "1.0", "-0.3", "80"]]
    gon = [rows[0]] + [r[:4] + [str(float(v) * 400 / 360) for v in r[4:7]] + r[7:]
                       for r in rows[1:]]
    for name, data in (("deg.csv", rows), ("gon.csv", gon)):
        with open(tmp_path / name, "w", newline="") as fh:
            csv.writer(fh).writerows(data)
    (tmp_path / "pts.csv").write_text("name,X,Y,Z\np1,1.0,0.5,0.2\np2,0.5,-0.4,-0.1\n")
    outs = []
    for name, unit in (("deg.csv", "deg"), ("gon.csv", "gon")):
        out = tmp_path / f"out-{unit}.csv"
        r = CliRunner().invoke(cli, ["restitute", "--photos", str(tmp_path / name), "--mode",
                                     "drive-to", "--points", str(tmp_path / "pts.csv"),
                                     "--out", str(out), "--angles", unit])
        assert r.exit_code == 0, r.output
        outs.append(np.loadtxt(out, delimiter=",", skiprows=1, usecols=range(1, 5)))
    assert np.allclose(outs[0], outs[1], rtol=0, atol=1e-9)
    r = CliRunner().invoke(cli, ["restitute", "--photos", str(tmp_path / "gon.csv"), "--mode",
                                 "drive-to", "--points", str(tmp_path / "pts.csv"), "--out",
                                 str(tmp_path / "out-wrong.csv")])
    assert r.exit_code == 0
    wrong = np.loadtxt(tmp_path / "out-wrong.csv", delimiter=",", skiprows=1, usecols=range(1, 5))
    assert not np.allclose(wrong, outs[0], rtol=0, atol=1e-3)
