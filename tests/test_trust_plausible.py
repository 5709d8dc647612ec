"""Units that cannot be right are refused with the fix: pixel CSVs given as photo mm to relor,
resect, intersect, restitute; control coordinates in mixed units given to absor."""

from __future__ import annotations

import numpy as np
import pytest

from orientation_helpers import C, aerial_points, photo, stereo_pair
from softplot.camera import builtin_names, load_camera
from softplot.cli import main
from softplot.errors import SoftplotError
from softplot.orientation.absolute import transform
from softplot.orientation.plausible import check_model_scale, check_photo_coords

FIX = "softplot correct"


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


def to_px(xy, pixel_mm=0.0212, size=11000):
    """Scan pixel coordinates (origin top-left, y down) of photo mm: what a user mixes up."""
    return np.c_[size / 2 + xy[:, 0] / pixel_mm, size / 2 - xy[:, 1] / pixel_mm]


def _refused(code, err, *words):
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert FIX in lines[0] and "--to photo" in lines[0]
    for w in words:
        assert w in lines[0]


@pytest.mark.parametrize("name", builtin_names())
def test_true_photo_coordinates_pass_at_the_format_corners(name):
    cam = load_camera(name)
    w, h = cam.format_mm
    corners = np.array([[w, h], [-w, h], [w, -h], [-w, -h]]) / 2 * 1.2  # beyond the edge too
    check_photo_coords(corners, cam.c, what="x", format_mm=cam.format_mm, camera=cam.name)
    with pytest.raises(SoftplotError, match="format"):
        check_photo_coords(corners * 2, 1e9, what="x", format_mm=cam.format_mm)


def test_relor_refuses_pixel_coordinates(tmp_path, capsys):
    s = stereo_pair(np.random.default_rng(2), n=12)
    rows = {k: [(f"p{i}", *p) for i, p in enumerate(s[k])] for k in ("xy1", "xy2")}
    ok_l = write_csv(tmp_path / "l.csv", ["name", "x", "y"], rows["xy1"])
    ok_r = write_csv(tmp_path / "r.csv", ["name", "x", "y"], rows["xy2"])
    px_l = write_csv(tmp_path / "lpx.csv", ["name", "x", "y"],
                     [(f"p{i}", *p) for i, p in enumerate(to_px(s["xy1"]))])
    px_r = write_csv(tmp_path / "rpx.csv", ["name", "x", "y"],
                     [(f"p{i}", *p) for i, p in enumerate(to_px(s["xy2"]))])
    code, _, err = run(["relor", "--camera", "wild-rc10", "--left", px_l, "--right", px_r],
                       capsys)
    _refused(code, err, "lpx.csv", "230 x 230 mm", "wild-rc10")
    code, _, err = run(["relor", "--principal-distance", C, "--left", ok_l, "--right", px_r],
                       capsys)
    _refused(code, err, "rpx.csv", "principal distance")
    code, _, err = run(["relor", "--camera", "wild-rc10", "--left", ok_l, "--right", ok_r],
                       capsys)
    assert code == 0, err


def test_resect_refuses_pixel_coordinates(tmp_path, capsys):
    rng = np.random.default_rng(0)
    X = aerial_points(rng, 9, offset=(512000.0, 4987000.0, 200.0))
    xy = photo(X, np.array([512020.0, 4986990.0, 1700.0]), np.radians([1.5, -2.0, 95.0]))
    gcp = write_csv(tmp_path / "gcp.csv", ["name", "X", "Y", "Z"],
                    [(f"P{i}", *p) for i, p in enumerate(X)])
    pts = write_csv(tmp_path / "px.csv", ["name", "x", "y"],
                    [(f"P{i}", *p) for i, p in enumerate(to_px(xy))])
    code, _, err = run(["resect", "--principal-distance", C, "--image-points", pts,
                        "--control", gcp], capsys)
    _refused(code, err, "px.csv")


def test_intersect_refuses_pixel_coordinates(tmp_path, capsys):
    s = stereo_pair(np.random.default_rng(1), n=6)
    photos = write_csv(
        tmp_path / "photos.csv",
        ["photo", "X0", "Y0", "Z0", "omega", "phi", "kappa", "c"],
        [("L", *s["C1"], *np.degrees(s["a1"]), C), ("R", *s["C2"], *np.degrees(s["a2"]), C)],
    )
    rows = [("L", f"p{i}", *p) for i, p in enumerate(s["xy1"])]
    rows += [("R", f"p{i}", *p) for i, p in enumerate(to_px(s["xy2"]))]
    pts = write_csv(tmp_path / "pts.csv", ["photo", "name", "x", "y"], rows)
    code, _, err = run(["intersect", "--photos", photos, "--image-points", pts], capsys)
    _refused(code, err, "photo R")


@pytest.mark.parametrize("mode", ["free", "single", "contour"])
def test_restitute_refuses_pixel_coordinates(tmp_path, capsys, mode):
    s = stereo_pair(np.random.default_rng(1), n=6)
    photos = write_csv(
        tmp_path / "photos.csv",
        ["photo", "X0", "Y0", "Z0", "omega", "phi", "kappa", "c"],
        [("L", *s["C1"], *np.degrees(s["a1"]), C), ("R", *s["C2"], *np.degrees(s["a2"]), C)],
    )
    p1, p2 = to_px(s["xy1"]), to_px(s["xy2"])
    cols = {"free": (["name", "x1", "y1", "x2", "y2"], np.c_[p1, p2]),
            "single": (["name", "x2", "y2", "x1"], np.c_[p2, p1[:, 0]]),
            "contour": (["name", "x2", "y2"], p2)}[mode]
    pts = write_csv(tmp_path / "pts.csv", cols[0], [(f"p{i}", *r) for i, r in enumerate(cols[1])])
    extra = ["--height", 10.0] if mode == "contour" else []
    out = tmp_path / "o.csv"
    code, _, err = run(["restitute", "--photos", photos, "--mode", mode, "--points", pts,
                        "--out", out, *extra], capsys)
    _refused(code, err, "pts.csv")
    assert not out.exists()


def test_absor_refuses_control_in_mixed_units(tmp_path, capsys):
    rng = np.random.default_rng(3)
    truth = np.array([3.0, 0.02, -0.01, 0.7, 1000.0, 2000.0, 300.0])
    m = np.c_[rng.uniform(-50, 50, (8, 2)), rng.uniform(-400, -380, 8)]
    obj = transform(truth, m)
    model = write_csv(tmp_path / "m.csv", ["name", "x", "y", "z"],
                      [(f"p{i}", *p) for i, p in enumerate(m)])
    bad = obj.copy()
    bad[2] *= 1000.0  # one point in millimetres
    gcp = write_csv(tmp_path / "g.csv", ["name", "X", "Y", "Z"],
                    [(f"p{i}", *p) for i, p in enumerate(bad)])
    code, _, err = run(["absor", "--model", model, "--control", gcp], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert "point p2" in err and "one unit" in err
    # a 0.5 m blunder is a blunder, not a unit error: the check lets it through
    blunder = obj.copy()
    blunder[2, 2] += 0.5
    check_model_scale(m, blunder, [f"p{i}" for i in range(8)], what="x")
    gcp = write_csv(tmp_path / "g2.csv", ["name", "X", "Y", "Z"],
                    [(f"p{i}", *p) for i, p in enumerate(blunder)])
    code, _, err = run(["absor", "--model", model, "--control", gcp], capsys)
    assert code == 0, err
