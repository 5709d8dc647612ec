"""Blunder detection as the tour runs it: every adjustment's JSON names its ``blunders`` (most
likely first) and its ``snooping_test``; without an a priori precision the test is Pope's tau
against the a posteriori sigma0, which catches a 0.5 m control blunder that the w-test against
an assumed 1 m missed."""

from __future__ import annotations

import json

import numpy as np
import pytest

from orientation_helpers import C, photo, stereo_pair
from softplot.cli import main
from softplot.orientation.absolute import transform


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


def _keys(d, test):
    assert set(d["snooping_test"]) >= {"test", "critical_value", "alpha0", "sigma0"}
    assert d["snooping_test"]["test"] == test
    assert d["snooping_test"]["critical_value"] > 0
    assert isinstance(d["blunders"], list)


def _absor_files(tmp_path, blunder, sigma=None):
    rng = np.random.default_rng(7)
    truth = np.array([12.0, 0.01, -0.02, 0.4, 512000.0, 4987000.0, 300.0])
    m = np.c_[rng.uniform(-40, 40, (10, 2)), rng.uniform(-2, 5, 10)]
    obj = transform(truth, m) + rng.normal(0, 0.003, (10, 3))
    obj[4, 2] += blunder
    model = write_csv(tmp_path / "m.csv", ["name", "x", "y", "z"],
                      [(f"p{i}", *p) for i, p in enumerate(m)])
    if sigma is None:
        gcp = write_csv(tmp_path / "g.csv", ["name", "X", "Y", "Z"],
                        [(f"p{i}", *p) for i, p in enumerate(obj)])
    else:
        gcp = write_csv(tmp_path / "g.csv", ["name", "X", "Y", "Z", "sX", "sY", "sZ"],
                        [(f"p{i}", *p, sigma, sigma, sigma) for i, p in enumerate(obj)])
    return model, gcp


def test_absor_tau_flags_half_a_metre(tmp_path, capsys):
    model, gcp = _absor_files(tmp_path, 0.5)
    out = tmp_path / "ao.json"
    code, text, err = run(["absor", "--model", model, "--control", gcp, "--json", out], capsys)
    assert code == 0, err
    d = json.loads(out.read_text())
    _keys(d, "pope-tau")
    assert d["blunders"][0] == "p4"
    assert "tau" in text and "p4" in text
    # the same control without the blunder: nothing flagged
    model, gcp = _absor_files(tmp_path, 0.0)
    out.unlink()
    code, _, err = run(["absor", "--model", model, "--control", gcp, "--json", out], capsys)
    d = json.loads(out.read_text())
    _keys(d, "pope-tau")
    assert d["blunders"] == []


def test_absor_w_test_when_the_precision_is_given(tmp_path, capsys):
    model, gcp = _absor_files(tmp_path, 0.05, sigma=0.003)
    out = tmp_path / "ao.json"
    code, _, err = run(["absor", "--model", model, "--control", gcp, "--json", out], capsys)
    assert code == 0, err
    d = json.loads(out.read_text())
    _keys(d, "baarda-w")
    assert d["blunders"][0] == "p4"


def test_resect_names_the_blunder(tmp_path, capsys):
    rng = np.random.default_rng(0)
    X = np.c_[rng.uniform(-500, 500, (12, 2)), rng.uniform(0, 60, 12)]
    xy = photo(X, np.array([20.0, -10.0, 1700.0]), np.radians([1.5, -2.0, 95.0]))
    xy += rng.normal(0, 0.002, xy.shape)
    xy[5, 0] += 0.04
    pts = write_csv(tmp_path / "p.csv", ["name", "x", "y"],
                    [(f"P{i}", *p) for i, p in enumerate(xy)])
    gcp = write_csv(tmp_path / "g.csv", ["name", "X", "Y", "Z"],
                    [(f"P{i}", *p) for i, p in enumerate(X)])
    out = tmp_path / "eo.json"
    code, _, err = run(["resect", "--principal-distance", C, "--image-points", pts,
                        "--control", gcp, "--json", out], capsys)
    assert code == 0, err
    d = json.loads(out.read_text())
    _keys(d, "pope-tau")
    assert d["blunders"][0] == "P5"
    out.unlink()
    code, _, err = run(["resect", "--principal-distance", C, "--image-points", pts,
                        "--control", gcp, "--json", out, "--sigma-image", 0.002], capsys)
    d = json.loads(out.read_text())
    _keys(d, "baarda-w")
    assert d["blunders"][0] == "P5"


def test_relor_names_the_blunder(tmp_path, capsys):
    rng = np.random.default_rng(4)
    s = stereo_pair(rng, n=20)
    xy1 = s["xy1"] + rng.normal(0, 0.002, s["xy1"].shape)
    xy2 = s["xy2"] + rng.normal(0, 0.002, s["xy2"].shape)
    xy2[7, 1] += 0.05  # a y-parallax blunder
    left = write_csv(tmp_path / "l.csv", ["name", "x", "y"],
                     [(f"p{i}", *p) for i, p in enumerate(xy1)])
    right = write_csv(tmp_path / "r.csv", ["name", "x", "y"],
                      [(f"p{i}", *p) for i, p in enumerate(xy2)])
    out = tmp_path / "ro.json"
    code, text, err = run(["relor", "--principal-distance", C, "--left", left, "--right", right,
                           "--json", out], capsys)
    assert code == 0, err
    d = json.loads(out.read_text())
    _keys(d, "pope-tau")
    assert d["blunders"][0] == "p7"
    assert "most likely blunder: p7" in text


def test_intersect_names_the_blunder(tmp_path, capsys):
    rng = np.random.default_rng(5)
    s = stereo_pair(rng, n=10)
    C3, a3 = np.array([300.0, 400.0, 1520.0]), np.array([0.01, 0.02, 0.5])
    xy3 = photo(s["X"], C3, a3)
    obs = [s["xy1"], s["xy2"], xy3]
    obs = [o + rng.normal(0, 0.002, o.shape) for o in obs]
    obs[2][3, 0] += 0.05
    photos = write_csv(
        tmp_path / "photos.csv",
        ["photo", "X0", "Y0", "Z0", "omega", "phi", "kappa", "c"],
        [("A", *s["C1"], *np.degrees(s["a1"]), C), ("B", *s["C2"], *np.degrees(s["a2"]), C),
         ("D", *C3, *np.degrees(a3), C)],
    )
    rows = [(ph, f"p{i}", *p) for ph, o in zip("ABD", obs, strict=True) for i, p in enumerate(o)]
    pts = write_csv(tmp_path / "pts.csv", ["photo", "name", "x", "y"], rows)
    out = tmp_path / "xyz.json"
    code, _, err = run(["intersect", "--photos", photos, "--image-points", pts, "--json", out],
                       capsys)
    assert code == 0, err
    d = json.loads(out.read_text())
    _keys(d, "pope-tau")
    assert d["blunders"][0] == "p3"


def test_pc_two_planes_and_resect_name_the_blunder(tmp_path, capsys):
    from softplot.orientation.two_planes import plane_readings

    rng = np.random.default_rng(6)
    F, PC, Z1, Z2 = 152.3, np.array([100.2, 200.3, 350.0]), 100.0, 250.0
    g = np.arange(-80.0, 81.0, 40.0)
    grid = np.array([(x, y) for x in g for y in g])
    R1 = plane_readings(grid, Z1, PC, np.zeros(3), F) + rng.normal(0, 0.002, (len(grid), 2))
    R2 = plane_readings(grid, Z2, PC, np.zeros(3), F) + rng.normal(0, 0.002, (len(grid), 2))
    R1[6, 0] += 0.05
    rd = write_csv(tmp_path / "rd.csv", ["name", "X1", "Y1", "X2", "Y2", "x", "y"],
                   [(f"g{i}", *a, *b, *c) for i, (a, b, c) in enumerate(zip(R1, R2, grid,
                                                                            strict=True))])
    a = tmp_path / "a.json"
    code, _, err = run(["pc", "two-planes", "--readings", rd, "--z1", Z1, "--z2", Z2,
                        "--json", a], capsys)
    assert code == 0, err
    d = json.loads(a.read_text())
    assert d["snooping_test"]["test"] in ("baarda-w", "pope-tau")
    assert d["blunders"][0] == "g6"
    fids = np.array([[-80.0, 0.0], [80.0, 0.0], [0.0, 80.0], [0.0, -80.0], [40.0, 40.0],
                     [-40.0, -40.0], [40.0, -40.0], [-40.0, 40.0]])
    XY = plane_readings(fids, Z1, PC, np.zeros(3), F) + rng.normal(0, 0.002, (8, 2))
    XY[2, 1] += 0.05
    m = write_csv(tmp_path / "m.csv", ["name", "x", "y", "X", "Y"],
                  [(f"F{i}", *p, *q) for i, (p, q) in enumerate(zip(fids, XY, strict=True))])
    code, _, err = run(["pc", "resect", "--marks", m, "--z", Z1, "--principal-distance", F,
                        "--json", tmp_path / "b.json"], capsys)
    assert code == 0, err
    d = json.loads((tmp_path / "b.json").read_text())
    assert d["snooping_test"]["test"] in ("baarda-w", "pope-tau")
    assert d["blunders"][0] == "F2"


def _testfield(tmp_path, capsys, row, extra=()):
    """A synthetic test-field project with a 30 um (15 sigma) blunder in x of observation ``row``;
    returns the project folder and the blundered observation's ``PHOTO/POINT``."""
    proj = tmp_path / "tf"
    code, _, err = run(["calibrate", proj, "--make-synthetic", "--photos", "8", *extra], capsys)
    assert code == 0, err
    lines = (proj / "observations.csv").read_text().splitlines()
    f = lines[row + 1].split(",")
    f[2] = repr(float(f[2]) + 0.030)
    lines[row + 1] = ",".join(f)
    (proj / "observations.csv").write_text("\n".join(lines) + "\n")
    return proj, f"{f[0]}/{f[1]}"


def test_bundle_and_calibrate_name_the_blunder(tmp_path, capsys):
    proj, obs = _testfield(tmp_path, capsys, 77)
    for cmd in (["calibrate", proj, "--free", "c,x0,y0,k1"],
                ["bundle", proj, "--free", "c,x0,y0,k1"]):
        js = tmp_path / f"{cmd[0]}.json"
        code, _, err = run([*cmd, "--json", js], capsys)
        assert code == 0, err
        d = json.loads(js.read_text())
        _keys(d, "baarda-w")
        assert d["snooping_test"]["critical_value"] == pytest.approx(3.29, abs=0.01)
        assert d["blunders"][0] == obs
        assert len(d["blunders"]) == d["flagged"]
    # no redundancy numbers, no test: said so, nothing named
    js = tmp_path / "interior.json"
    code, _, err = run(["bundle", proj, "--free", "c,x0,y0,k1", "--covariance", "interior",
                        "--json", js], capsys)
    assert code == 0, err
    d = json.loads(js.read_text())
    assert d["snooping_test"]["test"] == "none" and d["blunders"] == []


def test_calibrate_series_names_the_blunder_per_series(tmp_path, capsys):
    proj, obs = _testfield(tmp_path, capsys, 5, ["--n-series", "2"])
    js = tmp_path / "ser.json"
    code, _, err = run(["calibrate", proj, "--series", "--free", "c,x0,y0,k1", "--json", js],
                       capsys)
    assert code == 0, err
    ser = json.loads(js.read_text())["series"]
    for s in ser:
        _keys(s, "baarda-w")
    assert obs in ser[0]["blunders"][:1] + ser[1]["blunders"][:1]


def test_bundle_without_a_stated_precision_uses_the_tau_test(tmp_path, capsys):
    """A project that states no image precision (no ``sigma_image_um``, no ``sx, sy``) whose
    measurements are 3x worse than the 2 um default: the w-test against the default would flag
    a good part of them; Pope's tau test against the a posteriori sigma0 names the blunder."""
    proj, obs = _testfield(tmp_path, capsys, 40)
    cams = proj / "cameras.toml"
    cams.write_text("\n".join(ln for ln in cams.read_text().splitlines()
                              if not ln.startswith("sigma_image_um")) + "\n")
    rng = np.random.default_rng(3)
    lines = (proj / "observations.csv").read_text().splitlines()
    out = ["photo,name,x,y"]
    for ln in lines[1:]:
        f = ln.split(",")
        x, y = float(f[2]) + rng.normal(0, 0.006), float(f[3]) + rng.normal(0, 0.006)
        if f"{f[0]}/{f[1]}" == obs:
            x += 0.100  # 0.13 mm in all: about 20 sigma
        out.append(f"{f[0]},{f[1]},{x!r},{y!r}")
    (proj / "observations.csv").write_text("\n".join(out) + "\n")
    js = tmp_path / "b.json"
    code, stdout, err = run(["bundle", proj, "--free", "c,x0,y0,k1", "--json", js], capsys)
    assert code == 0, err
    d = json.loads(js.read_text())
    assert d["snooping_test"]["test"] == "pope-tau"
    assert 2.0 < d["snooping_test"]["sigma0"] < 5.0  # a posteriori, in units of the default
    assert d["blunders"][0] == obs
    assert len(d["blunders"]) <= 3, d["blunders"]
    assert "tau" in stdout
    # the same project with the precision stated as 2 um: the w-test, which now flags many
    cams.write_text(cams.read_text().replace('lens = "', 'sigma_image_um = 2.0\nlens = "'))
    js = tmp_path / "w.json"
    code, _, err = run(["bundle", proj, "--free", "c,x0,y0,k1", "--json", js], capsys)
    assert code == 0, err
    d = json.loads(js.read_text())
    assert d["snooping_test"]["test"] == "baarda-w"
    assert len(d["blunders"]) > 10
