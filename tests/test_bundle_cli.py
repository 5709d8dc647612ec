"""CLI: softplot bundle / calibrate / triangulate (project folders, BAL, errors)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from softplot.cli import main


def run(args, capsys):
    with pytest.raises(SystemExit) as e:
        main(args)
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def test_calibrate_synthetic_project_end_to_end(tmp_path, capsys):
    proj = tmp_path / "tf"
    code, _, _ = run(["calibrate", str(proj), "--make-synthetic", "--photos", "16"], capsys)
    assert code == 0
    for f in ("cameras.toml", "photos.csv", "observations.csv", "control.csv", "truth.json"):
        assert (proj / f).is_file()
    js, plots = tmp_path / "out.json", tmp_path / "plots"
    code, out, _ = run(
        ["calibrate", str(proj), "--free", "c,x0,y0,k1", "--json", str(js), "--plots", str(plots)],
        capsys,
    )
    assert code == 0 and "Test-field calibration" in out and "sigma0" in out
    res = json.loads(js.read_text())
    truth = json.loads((proj / "truth.json").read_text())["intrinsics"]
    c = res["cameras"][0]["parameters"]["c"]
    assert abs(c["value"] - truth[0]) < 4 * c["std"]
    assert res["rms_image_um"]["xy"] == pytest.approx(2.0 * np.sqrt(2), rel=0.15)
    assert (plots / "residual_histogram.png").stat().st_size > 1000
    # the same project through `softplot bundle`
    code, out, _ = run(["bundle", str(proj), "--free", "c,x0,y0,k1", "--angle-unit", "gon"], capsys)
    assert code == 0 and "Bundle adjustment" in out


def test_calibrate_series_cli(tmp_path, capsys):
    proj = tmp_path / "ser"
    run(["calibrate", str(proj), "--make-synthetic", "--photos", "8", "--n-series", "3"], capsys)
    js = tmp_path / "ser.json"
    code, out, _ = run(
        ["calibrate", str(proj), "--series", "--free", "c,x0,y0,k1", "--json", str(js)], capsys
    )
    assert code == 0 and "repeatability" in out
    assert len(json.loads(js.read_text())["series"]) == 3


def test_triangulate_synthetic_block_both_methods(tmp_path, capsys):
    proj = tmp_path / "blk"
    code, out, _ = run(
        ["triangulate", str(proj), "--make-synthetic", "--strips", "2", "--photos-per-strip", "6"],
        capsys,
    )
    assert code == 0
    js = tmp_path / "b.json"
    code, out, _ = run(["triangulate", str(proj), "--json", str(js)], capsys)
    assert code == 0 and "Check points" in out
    b = json.loads(js.read_text())
    assert b["check_points_rms"]["n"] > 5 and b["check_points_rms"]["Z"] < 0.5
    code, out, _ = run(
        ["triangulate", str(proj), "--method", "independent-models", "--pc-tie", "z"], capsys
    )
    assert code == 0 and "tied in Z" in out and "check points" in out


def test_bundle_bal_cli(tmp_path, capsys):
    from test_bundle_engine import synthetic_bal

    prob, _ = synthetic_bal(n_cam=4, n_pts=30, noise=0.5, seed=2)
    f = tmp_path / "p.txt"
    lines = [f"{prob.n_cameras} {prob.n_points} {prob.n_observations}"]
    lines += [
        f"{c} {p} {float(x)!r} {float(y)!r}"
        for c, p, (x, y) in zip(prob.cam_index, prob.point_index, prob.xy, strict=True)
    ]
    lines += [repr(float(v)) for v in prob.cameras.ravel()]
    lines += [repr(float(v)) for v in prob.points.ravel()]
    f.write_text("\n".join(lines) + "\n")
    js = tmp_path / "bal.json"
    code, out, _ = run(["bundle", "--bal", str(f), "--json", str(js)], capsys)
    assert code == 0 and "final_cost" in out
    r = json.loads(js.read_text())
    for k in ("initial_cost", "final_cost", "iterations", "seconds"):
        assert k in r
    assert r["final_cost"] < 0.05 * r["initial_cost"]


@pytest.mark.parametrize(
    "args,msg",
    [
        (["bundle"], "either a PROJECT"),
        (["bundle", "nowhere_dir_xyz"], "project folder not found"),
        (["bundle", "--bal", "missing_file.txt"], "BAL file not found"),
        (["calibrate", "nowhere_dir_xyz"], "project folder not found"),
        (["triangulate", "nowhere_dir_xyz", "--method", "independent-models"], "not found"),
    ],
)
def test_bad_input_is_one_line_exit_2(args, msg, capsys):
    code, _, err = run(args, capsys)
    assert code == 2
    assert msg in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_bad_project_files_are_named(tmp_path, capsys):
    proj = tmp_path / "bad"
    run(["calibrate", str(proj), "--make-synthetic", "--photos", "6"], capsys)
    obs = proj / "observations.csv"
    txt = obs.read_text().splitlines()
    txt[3] = txt[3].replace(txt[3].split(",")[2], "abc", 1)
    obs.write_text("\n".join(txt) + "\n")
    code, _, err = run(["calibrate", str(proj)], capsys)
    assert code == 2 and "observations.csv row 4" in err
    # never overwrite an input
    code, _, err = run(["bundle", str(proj), "--json", str(proj / "photos.csv")], capsys)
    assert code == 2 and "refusing to overwrite" in err
    # synthetic generation refuses to overwrite a project
    code, _, err = run(["calibrate", str(proj), "--make-synthetic"], capsys)
    assert code == 2 and "not overwriting" in err
