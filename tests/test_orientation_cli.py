"""CLI: resect, intersect, relor, absor, pc on files written here; keys, values, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from orientation_helpers import C, aerial_points, photo, stereo_pair
from softplot.camera import load_camera
from softplot.cli import main
from softplot.orientation.absolute import transform
from softplot.orientation.two_planes import plane_readings

EO = ["X0", "Y0", "Z0", "omega", "phi", "kappa"]


def run(args, capsys):
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def write_csv(path, header, rows):
    with open(path, "w") as fh:
        fh.write(",".join(header) + "\n")
        for r in rows:
            fh.write(",".join(f"{v:.10f}" if isinstance(v, float) else str(v) for v in r) + "\n")
    return path


@pytest.fixture
def resection_files(tmp_path):
    rng = np.random.default_rng(0)
    X = aerial_points(rng, 9, offset=(512000.0, 4987000.0, 200.0))
    X0 = np.array([512020.0, 4986990.0, 1700.0])
    ang = np.radians([1.5, -2.0, 95.0])
    xy = photo(X, X0, ang)
    pts = write_csv(
        tmp_path / "pts.csv", ["name", "x", "y"], [(f"P{i}", *p) for i, p in enumerate(xy)]
    )
    gcp = write_csv(
        tmp_path / "gcp.csv", ["name", "X", "Y", "Z"], [(f"P{i}", *p) for i, p in enumerate(X)]
    )
    return pts, gcp, X0, ang


@pytest.mark.parametrize("unit, k", [("deg", 180 / np.pi), ("gon", 200 / np.pi), ("rad", 1.0)])
def test_resect(resection_files, tmp_path, capsys, unit, k):
    pts, gcp, X0, ang = resection_files
    out = tmp_path / "eo.json"
    code, text, err = run(
        [
            "resect",
            "--principal-distance",
            C,
            "--image-points",
            pts,
            "--control",
            gcp,
            "--json",
            out,
            "--angles",
            unit,
        ],
        capsys,
    )
    assert code == 0, err
    d = json.loads(out.read_text())
    for key in [*EO, "sigma0", "redundancy", "std", "covariance", "residuals"]:
        assert key in d
    assert set(d["std"]) == set(EO)
    np.testing.assert_allclose([d["X0"], d["Y0"], d["Z0"]], X0, atol=1e-6)
    np.testing.assert_allclose([d["omega"], d["phi"], d["kappa"]], ang * k, atol=1e-8 * k)
    assert d["redundancy"] == 12
    assert np.array(d["covariance"]).shape == (6, 6)
    assert [r["name"] for r in d["residuals"]] == [f"P{i}" for i in range(9)]
    assert set(d["residuals"][0]) == {"name", "vx", "vy"}
    assert "SPACE RESECTION" in text and "sigma0" in text and "redundancy r = 12" in text


def test_resect_camera_certificate(resection_files, tmp_path, capsys):
    pts, gcp, _, _ = resection_files
    out = tmp_path / "eo.json"
    code, _, err = run(
        [
            "resect",
            "--camera",
            "wild-rc10",
            "--image-points",
            pts,
            "--control",
            gcp,
            "--json",
            out,
        ],
        capsys,
    )
    assert code == 0, err
    assert json.loads(out.read_text())["principal_distance"] == load_camera("wild-rc10").c


def test_intersect(tmp_path, capsys):
    rng = np.random.default_rng(1)
    s = stereo_pair(rng, n=6)
    photos = write_csv(
        tmp_path / "photos.csv",
        ["photo", "X0", "Y0", "Z0", "omega", "phi", "kappa", "c"],
        [("L", *s["C1"], *np.degrees(s["a1"]), C), ("R", *s["C2"], *np.degrees(s["a2"]), C)],
    )
    rows = [("L", f"p{i}", *p) for i, p in enumerate(s["xy1"])]
    rows += [("R", f"p{i}", *p) for i, p in enumerate(s["xy2"])]
    rows.append(("L", "lonely", 1.0, 2.0))
    pts = write_csv(tmp_path / "pts.csv", ["photo", "name", "x", "y"], rows)
    out = tmp_path / "xyz.json"
    code, text, err = run(
        ["intersect", "--photos", photos, "--image-points", pts, "--json", out], capsys
    )
    assert code == 0, err
    d = json.loads(out.read_text())
    assert [p["name"] for p in d["points"]] == [f"p{i}" for i in range(6)]
    assert {"name", "X", "Y", "Z", "std", "rms"} <= set(d["points"][0])
    np.testing.assert_allclose([[p["X"], p["Y"], p["Z"]] for p in d["points"]], s["X"], atol=1e-5)
    assert len(d["points"][0]["std"]) == 3
    assert d["skipped"] == ["lonely"]
    assert "SPACE INTERSECTION" in text


@pytest.mark.parametrize("independent", [False, True])
def test_relor(tmp_path, capsys, independent):
    s = stereo_pair(np.random.default_rng(2), n=12)
    left = write_csv(
        tmp_path / "l.csv", ["name", "x", "y"], [(f"p{i}", *p) for i, p in enumerate(s["xy1"])]
    )
    right = write_csv(
        tmp_path / "r.csv",
        ["name", "x", "y"],
        [(f"p{i}", *p) for i, p in enumerate(s["xy2"])][::-1],
    )  # any order
    out = tmp_path / "ro.json"
    args = [
        "relor",
        "--principal-distance",
        C,
        "--left",
        left,
        "--right",
        right,
        "--bx",
        50,
        "--json",
        out,
    ]
    code, text, err = run(args + (["--independent"] if independent else []), capsys)
    assert code == 0, err
    d = json.loads(out.read_text())
    for key in ["omega", "phi", "kappa", "bx", "by", "bz", "sigma0", "redundancy", "std", "points"]:
        assert key in d
    assert d["bx"] == 50 and d["redundancy"] == 7
    assert {"name", "X", "Y", "Z", "py"} <= set(d["points"][0])
    assert max(abs(p["py"]) for p in d["points"]) < 1e-8
    if independent:
        assert d["by"] == 0 and d["bz"] == 0 and "phi1" in d["std"]
    else:
        assert {"by", "bz", "omega", "phi", "kappa"} == set(d["std"])
    assert "RELATIVE ORIENTATION" in text


def test_absor(tmp_path, capsys):
    rng = np.random.default_rng(3)
    truth = np.array([3.0, 0.02, -0.01, 0.7, 1000.0, 2000.0, 300.0])
    m = np.c_[rng.uniform(-50, 50, (8, 2)), rng.uniform(-400, -380, 8)]
    obj = transform(truth, m)
    model = write_csv(
        tmp_path / "m.csv", ["name", "x", "y", "z"], [(f"p{i}", *p) for i, p in enumerate(m)]
    )
    rows = [(f"p{i}", *p, 0.01, 0.01, 0.02) for i, p in enumerate(obj[:5])]
    gcp = write_csv(tmp_path / "g.csv", ["name", "X", "Y", "Z", "sX", "sY", "sZ"], rows)
    out = tmp_path / "ao.json"
    code, text, err = run(
        ["absor", "--model", model, "--control", gcp, "--json", out, "--angles", "rad"], capsys
    )
    assert code == 0, err
    d = json.loads(out.read_text())
    keys = ["scale", "omega", "phi", "kappa", "TX", "TY", "TZ"]
    np.testing.assert_allclose([d[k] for k in keys], truth, rtol=1e-8)
    assert d["redundancy"] == 8 and set(d["std"]) == set(keys)
    assert len(d["residuals"]) == 5 and len(d["points"]) == 8
    np.testing.assert_allclose([[p["X"], p["Y"], p["Z"]] for p in d["points"]], obj, atol=1e-6)
    assert "ABSOLUTE ORIENTATION" in text


def test_pc_chain(tmp_path, capsys):
    F, PC, Z1, Z2 = 152.3, np.array([100.2, 200.3, 350.0]), 100.0, 250.0
    g = np.arange(-80.0, 81.0, 40.0)
    grid = np.array([(x, y) for x in g for y in g])
    R1 = plane_readings(grid, Z1, PC, np.zeros(3), F)
    R2 = plane_readings(grid, Z2, PC, np.zeros(3), F)
    rd = write_csv(
        tmp_path / "rd.csv",
        ["name", "X1", "Y1", "X2", "Y2", "x", "y"],
        [(f"g{i}", *a, *b, *c) for i, (a, b, c) in enumerate(zip(R1, R2, grid, strict=True))],
    )
    a = tmp_path / "a.json"
    code, text, err = run(
        ["pc", "two-planes", "--readings", rd, "--z1", Z1, "--z2", Z2, "--json", a], capsys
    )
    assert code == 0, err
    da = json.loads(a.read_text())
    np.testing.assert_allclose([da["X0"], da["Y0"], da["Z0"]], PC, atol=1e-8)
    assert da["f"] == pytest.approx(F, rel=1e-9)
    fids = np.array([[-80.0, 0.0], [80.0, 0.0], [0.0, 80.0], [0.0, -80.0]])
    shift = np.array([0.05, -0.02, 0.01])
    for stem, pc, ang in (("b", PC, np.zeros(3)), ("c", PC + shift, np.radians([1.8, 0, 0]))):
        XY = plane_readings(fids, Z1, pc, ang, F)
        m = write_csv(
            tmp_path / f"{stem}.csv",
            ["name", "x", "y", "X", "Y"],
            [(f"F{i}", *p, *q) for i, (p, q) in enumerate(zip(fids, XY, strict=True))],
        )
        code, text, err = run(
            [
                "pc",
                "resect",
                "--marks",
                m,
                "--z",
                Z1,
                "--principal-distance",
                F,
                "--json",
                tmp_path / f"{stem}.json",
            ],
            capsys,
        )
        assert code == 0, err
    code, text, err = run(
        [
            "pc",
            "differential",
            "--two-planes",
            a,
            "--reference",
            tmp_path / "b.json",
            "--model",
            tmp_path / "c.json",
            "--json",
            tmp_path / "d.json",
        ],
        capsys,
    )
    assert code == 0, err
    dd = json.loads((tmp_path / "d.json").read_text())
    np.testing.assert_allclose([dd["X0"], dd["Y0"], dd["Z0"]], PC + shift, atol=1e-7)
    np.testing.assert_allclose(dd["delta"], shift, atol=1e-7)
    assert "DIFFERENTIAL" in text


def test_help_lists_pc_procedures(capsys):
    code, text, _ = run(["pc", "--help"], capsys)
    assert code == 0 and "two-planes" in text and "differential" in text


def test_bad_inputs(resection_files, tmp_path, capsys):
    pts, gcp, _, _ = resection_files
    base = ["resect", "--principal-distance", C, "--image-points"]
    # a bad number: one line naming file and line
    bad = tmp_path / "bad.csv"
    bad.write_text("name,x,y\nP0,1.0,2.0\nP1,abc,3.0\n")
    code, out, err = run(base + [bad, "--control", gcp], capsys)
    assert code == 2 and "bad.csv" in err and "line 3" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1
    # a missing column
    bad.write_text("name,x\nP0,1.0\n")
    code, _, err = run(base + [bad, "--control", gcp], capsys)
    assert code == 2 and "lacks column(s) y" in err
    # missing file
    code, _, err = run(base + [tmp_path / "none.csv", "--control", gcp], capsys)
    assert code == 2 and "no such file" in err
    # JSON onto an input
    before = gcp.read_text()
    code, _, err = run(base + [pts, "--control", gcp, "--json", gcp], capsys)
    assert code == 2 and "overwrite" in err and gcp.read_text() == before
    # both / neither principal distance sources
    code, _, err = run(["resect", "--image-points", pts, "--control", gcp], capsys)
    assert code == 2 and "exactly one" in err
    code, _, err = run(
        [
            "resect",
            "--camera",
            "rollei-6006",
            "--principal-distance",
            80,
            "--image-points",
            pts,
            "--control",
            gcp,
        ],
        capsys,
    )
    assert code == 2
    # repeated point name
    bad.write_text("name,x,y\nP0,1.0,2.0\nP0,1.0,2.0\n")
    code, _, err = run(base + [bad, "--control", gcp], capsys)
    assert code == 2 and "repeated" in err
    # collinear control: the named unknowns, one line
    line = tmp_path / "line.csv"
    write_csv(line, ["name", "X", "Y", "Z"], [(f"P{i}", 10.0 * i, 3.0 * i, 0.0) for i in range(9)])
    code, _, err = run(base + [pts, "--control", line], capsys)
    assert code == 2 and "not determined" in err and len(err.strip().splitlines()) == 1
