"""One output rule for every command: an existing output is refused without --overwrite
(and left untouched), an input is never overwritten (even with --overwrite), an output in a
missing folder gets its folder; process and batch resume only what the same settings made."""

from __future__ import annotations

import json

import numpy as np
import pytest

from orientation_helpers import C, aerial_points, photo, stereo_pair
from softplot.camera import load_camera
from softplot.cli import main
from softplot.orientation.absolute import transform


def run(args):
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    return e.value.code


def rows_of(xy, prefix="p"):
    return [(f"{prefix}{i}", *p) for i, p in enumerate(xy)]


def write_csv(path, header, rows):
    with open(path, "w") as fh:
        fh.write(",".join(header) + "\n")
        for r in rows:
            fh.write(",".join(f"{v:.10f}" if isinstance(v, float) else str(v) for v in r) + "\n")
    return path


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Inputs of every command, and per command: argv(out) and the inputs it reads."""
    d = tmp_path_factory.mktemp("outputs")
    rng = np.random.default_rng(0)
    s = stereo_pair(rng, n=12)
    s["xy1"] += rng.normal(0, 0.002, s["xy1"].shape)
    left = write_csv(d / "l.csv", ["name", "x", "y"], rows_of(s["xy1"]))
    right = write_csv(d / "r.csv", ["name", "x", "y"], rows_of(s["xy2"]))
    head = ["photo", "X0", "Y0", "Z0", "omega", "phi", "kappa", "c"]
    photos = write_csv(d / "photos.csv", head,
                       [("L", *s["C1"], *np.degrees(s["a1"]), C),
                        ("R", *s["C2"], *np.degrees(s["a2"]), C)])
    ipts = write_csv(d / "ipts.csv", ["photo", "name", "x", "y"],
                     [("L", f"p{i}", *p) for i, p in enumerate(s["xy1"])]
                     + [("R", f"p{i}", *p) for i, p in enumerate(s["xy2"])])
    free = write_csv(d / "free.csv", ["name", "x1", "y1", "x2", "y2"],
                     rows_of(np.c_[s["xy1"], s["xy2"]]))
    X = aerial_points(rng, 9)
    xy = photo(X, np.array([20.0, -10.0, 1700.0]), np.radians([1.5, -2.0, 95.0]))
    xy += rng.normal(0, 0.002, xy.shape)
    rpts = write_csv(d / "rpts.csv", ["name", "x", "y"], rows_of(xy, "P"))
    gcp = write_csv(d / "gcp.csv", ["name", "X", "Y", "Z"], rows_of(X, "P"))
    m = np.c_[rng.uniform(-50, 50, (8, 2)), rng.uniform(-400, -380, 8)]
    obj = transform(np.array([3.0, 0.02, -0.01, 0.7, 1000.0, 2000.0, 300.0]), m)
    obj += rng.normal(0, 0.01, obj.shape)
    model = write_csv(d / "m.csv", ["name", "x", "y", "z"], rows_of(m, "q"))
    ctrl = write_csv(d / "g.csv", ["name", "X", "Y", "Z"], rows_of(obj, "q"))
    cam = load_camera("rollei-6006")
    det = {"image": "s.tif", "camera": cam.name, "width": 1200, "height": 1200, "marks": [
        {"kind": "reseau", "name": n, "row": int(r), "col": int(c), "x": 600.0 + 20 * x,
         "y": 600.0 - 20 * y, "status": "measured"}
        for n, (r, c), (x, y) in zip(cam.reseau.names(), cam.reseau.row_col(), cam.reseau.film(),
                                     strict=True)]}
    detp = d / "s.det.json"
    detp.write_text(json.dumps(det))
    pix = d / "pix.csv"
    pix.write_text("name,x,y\na,700,500\n")
    cmds = {
        "relor": (lambda o: ["relor", "--principal-distance", C, "--left", left, "--right", right,
                             "--json", o], [left, right]),
        "resect": (lambda o: ["resect", "--principal-distance", C, "--image-points", rpts,
                              "--control", gcp, "--json", o], [rpts, gcp]),
        "intersect": (lambda o: ["intersect", "--photos", photos, "--image-points", ipts,
                                 "--json", o], [photos, ipts]),
        "absor": (lambda o: ["absor", "--model", model, "--control", ctrl, "--json", o],
                  [model, ctrl]),
        "restitute": (lambda o: ["restitute", "--photos", photos, "--mode", "free", "--points",
                                 free, "--out", o], [photos, free]),
        "correct": (lambda o: ["correct", detp, "-c", "rollei-6006", "--points", pix, "--out", o,
                               "-m", "affine"], [detp, pix]),
        "correct-compare": (lambda o: ["correct", "compare", detp, "-c", "rollei-6006",
                                       "--method", "affine", "--json", o], [detp]),
    }
    return d, cmds


COMMANDS = ["relor", "resect", "intersect", "absor", "restitute", "correct", "correct-compare"]


@pytest.mark.parametrize("name", COMMANDS)
def test_one_output_rule(data, name, capsys):
    d, cmds = data
    argv, inputs = cmds[name]
    sub = d / name
    # a missing folder is created
    out = sub / "deeper" / "out.file"
    assert run(argv(out)) == 0, capsys.readouterr().err
    assert out.is_file()
    # an existing output: refused without --overwrite, untouched
    out.write_text("mine")
    assert run(argv(out)) == 2
    err = capsys.readouterr().err
    assert "exists" in err and "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert out.read_text() == "mine"
    # replaced with --overwrite
    assert run([*argv(out), "--overwrite"]) == 0
    assert out.read_text() != "mine"
    # an input is never overwritten, even with --overwrite
    for i in inputs:
        before = i.read_bytes()
        assert run([*argv(i), "--overwrite"]) == 2
        assert "input" in capsys.readouterr().err
        assert i.read_bytes() == before
    # a folder that cannot be made (a file in the way): one line, exit 2
    blocker = sub / "afile"
    blocker.write_text("x")
    assert run(argv(blocker / "out.file")) == 2
    err = capsys.readouterr().err
    assert "afile" in err and len(err.strip().splitlines()) == 1


def test_detect_output_rule(tmp_path, capsys):
    from softplot.synthetic import ScanSpec, write_scan

    img, _ = write_scan(tmp_path, "pentax-645", ScanSpec(dpi=300.0, scene="none"), seed=1,
                        stem="s")
    js = tmp_path / "new" / "dir" / "s.json"
    assert run(["detect", img, "--camera", "pentax-645", "--json", js]) == 0
    assert js.is_file()
    assert run(["detect", img, "--camera", "pentax-645", "--json", js]) == 2
    assert "--overwrite" in capsys.readouterr().err
    before = img.read_bytes()
    assert run(["detect", img, "--camera", "pentax-645", "--json", img, "--overwrite"]) == 2
    assert img.read_bytes() == before


def test_process_and_batch_resume_only_with_the_same_settings(tmp_path, capsys):
    from softplot.synthetic import ScanSpec, write_scan

    src = tmp_path / "scans"
    img, _ = write_scan(src, "pentax-645", ScanSpec(dpi=300.0, scene="none"), seed=2, stem="a")
    out = tmp_path / "out"
    base = ["batch", str(src / "*.tif"), "--camera", "pentax-645", "--out", out, "--quiet",
            "--workers", "1"]
    assert run([*base, "--method", "affine"]) == 0
    r = json.loads((out / "a.json").read_text())
    assert r["settings"]["method"] == "affine" and r["settings"]["camera"] == "pentax-645"
    first = (out / "a.json").read_bytes()
    capsys.readouterr()
    # same settings: resumed (skipped)
    assert run([*base, "--method", "affine"]) == 0
    assert "1 skipped" in capsys.readouterr().out
    # another method: refused, naming the setting; the result is kept
    assert run([*base, "--method", "projective"]) == 2
    err = capsys.readouterr().err
    assert "method='affine'" in err and "method='projective'" in err and "--overwrite" in err
    assert (out / "a.json").read_bytes() == first
    # --overwrite recomputes with the new settings
    assert run([*base, "--method", "projective", "--overwrite"]) == 0
    r = json.loads((out / "a.json").read_text())
    assert r["settings"]["method"] == "projective" and r["method"] == "projective"
    # process: an existing result is refused without --overwrite, replaced with it
    pbase = ["process", img, "--camera", "pentax-645", "--out", out, "--quiet"]
    assert run(pbase) == 2
    assert "--overwrite" in capsys.readouterr().err
    assert run([*pbase, "--overwrite"]) == 0
    assert json.loads((out / "a.json").read_text())["settings"]["method"] is None


def test_plot_export_never_overwrites_its_inputs(tmp_path, capsys):
    """``plot export`` follows the output rule and never replaces a file the session read:
    the operator-input CSV of a trace, the photos file of ``plot new``."""
    photos = tmp_path / "photos.csv"
    photos.write_text(
        "photo,X0,Y0,Z0,omega,phi,kappa,c\nL,0,0,1700,0,0,0,152\nR,900,0,1700,0,0,0,152\n"
    )
    ops = tmp_path / "ops.csv"
    ops.write_text("name,X,Y,px\na,10,5,80\nb,-20,30,85\n")
    folder = tmp_path / "s"
    assert run(["plot", "new", folder, "--photos", photos]) == 0
    assert run(["plot", "trace", folder, "--input", ops, "--code", "SPOT"]) == 0
    capsys.readouterr()
    for i in (ops, photos):
        before = i.read_bytes()
        for extra in ([], ["--overwrite"]):
            assert run(["plot", "export", folder, i, *extra]) == 2
            err = capsys.readouterr().err
            assert "input" in err and len(err.strip().splitlines()) == 1
            assert i.read_bytes() == before
    out = tmp_path / "new" / "f.csv"
    assert run(["plot", "export", folder, out]) == 0 and out.is_file()
    out.write_text("mine")
    assert run(["plot", "export", folder, out]) == 2
    assert "--overwrite" in capsys.readouterr().err and out.read_text() == "mine"
    assert run(["plot", "export", folder, out, "--overwrite"]) == 0
    assert out.read_text().count("\n") >= 3
