"""Projects in and out: COLMAP and BAL round trips reproduce the image points to 1e-9 px."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from scipy.spatial.transform import Rotation

from softplot.adjust.bal import BALModel, read_bal
from softplot.cli import cli
from softplot.geometry.rotation import rotation_matrix
from softplot.orientation.bundle import _Model, _State
from softplot.orientation.bundle_io import read_project, write_project
from softplot.orientation.interchange.bal import read_bal_project, write_bal_project
from softplot.orientation.interchange.colmap import read_colmap, write_colmap
from test_bundle_engine import synthetic_bal

W, H = 3000, 2000
CAMS = {
    1: ("OPENCV", [2410.0, 2390.0, 1512.3, 987.6, -0.12, 0.05, 0.0012, -0.0008]),
    2: ("FULL_OPENCV", [1800.0, 1800.0, 1490.0, 1010.0, 0.08, -0.02, -0.0005, 0.0009, 0.01]),
    3: ("PINHOLE", [2000.0, 2050.0, 1500.0, 1000.0]),
    4: ("SIMPLE_RADIAL", [2200.0, 1505.0, 995.0, -0.07]),
}


def _opencv(model, p):
    """K and OpenCV distortion (k1, k2, p1, p2, k3) of a COLMAP camera."""
    if model == "SIMPLE_RADIAL":
        f, cx, cy, k = p
        return np.array([[f, 0, cx], [0, f, cy], [0, 0, 1.0]]), np.array([k, 0, 0, 0, 0.0])
    fx, fy, cx, cy = p[:4]
    d = np.zeros(5)
    if len(p) >= 8:
        d[:4] = p[4:8]
    if len(p) >= 9:
        d[4] = p[8]
    return np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]), d


def make_colmap(folder: Path, seed=0):
    """A COLMAP text model with exact image points projected by OpenCV (cv2.projectPoints)."""
    rng = np.random.default_rng(seed)
    X = rng.uniform([-4, -3, 8], [4, 3, 14], (60, 3))
    cams, imgs, obs = [], [], {}
    for cid, (model, p) in CAMS.items():
        pars = list(p) + ([0.0, 0.0, 0.0] if model == "FULL_OPENCV" else [])
        cams.append(f"{cid} {model} {W} {H} " + " ".join(repr(v) for v in pars))
    for i in range(8):
        cid = 1 + i % 4
        K, dist = _opencv(*CAMS[cid])
        R = Rotation.from_rotvec(rng.normal(0, 0.15, 3)).as_matrix()
        C = np.array([rng.uniform(-2, 2), rng.uniform(-1, 1), rng.uniform(-1, 1)])
        t = -R @ C
        uv, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K, dist)
        uv = uv[:, 0, :]
        q = Rotation.from_matrix(R).as_quat()
        nums = " ".join(repr(float(v)) for v in [q[3], q[0], q[1], q[2], *t])
        imgs.append(f"{i + 1} {nums} {cid} im{i}.jpg")
        keep = rng.random(60) < 0.9
        items = []
        for j in np.flatnonzero(keep):
            items.append(f"{float(uv[j, 0])!r} {float(uv[j, 1])!r} {j + 1}")
            obs.setdefault(j, []).append((i + 1, len(items) - 1))
        imgs.append(" ".join(items))
    pts = [
        f"{j + 1} {float(X[j, 0])!r} {float(X[j, 1])!r} {float(X[j, 2])!r} 0 0 0 0 "
        + " ".join(f"{a} {b}" for a, b in obs.get(j, []))
        for j in range(60)
    ]
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "cameras.txt").write_text("# c\n" + "\n".join(cams) + "\n")
    (folder / "images.txt").write_text("# i\n" + "\n".join(imgs) + "\n")
    (folder / "points3D.txt").write_text("# p\n" + "\n".join(pts) + "\n")
    return folder


def _colmap_projections(folder: Path) -> dict:
    """(image name, point id) -> projected pixel, computed by OpenCV from a COLMAP model."""
    cams = {}
    for ln in (folder / "cameras.txt").read_text().splitlines():
        if ln.startswith("#") or not ln.strip():
            continue
        t = ln.split()
        p = [float(v) for v in t[4:]]
        cams[t[0]] = _opencv(t[1], p[:9] if t[1] == "FULL_OPENCV" else p)
    X = {}
    for ln in (folder / "points3D.txt").read_text().splitlines():
        if ln.startswith("#") or not ln.strip():
            continue
        t = ln.split()
        X[t[0]] = np.array([float(v) for v in t[1:4]])
    lines = [
        ln for ln in (folder / "images.txt").read_text().splitlines() if not ln.startswith("#")
    ]
    out, meas = {}, {}
    for i in range(0, len(lines) - 1, 2):
        t = lines[i].split()
        q = [float(v) for v in t[1:5]]
        R = Rotation.from_quat([q[1], q[2], q[3], q[0]]).as_matrix()
        tt = np.array([float(v) for v in t[5:8]])
        K, dist = cams[t[8]]
        p2 = lines[i + 1].split()
        ids = p2[2::3]
        P = np.array([X[k] for k in ids])
        uv, _ = cv2.projectPoints(P, cv2.Rodrigues(R)[0], tt, K, dist)
        for k, a, b, u in zip(ids, p2[0::3], p2[1::3], uv[:, 0, :], strict=True):
            out[(t[9], k)] = u
            meas[(t[9], k)] = np.array([float(a), float(b)])
    return out, meas


def _residual_px(data):
    """softplot's residuals (predicted - measured) at the data's values, in pixels."""
    model = _Model(data, np.ones((len(data.point_names), 3), bool))
    M = rotation_matrix(data.angles[:, 0], data.angles[:, 1], data.angles[:, 2])
    intr = np.array([c.values for c in data.cameras])
    ev = model.evaluate(_State(data.X0, M, intr, data.XYZ), False)
    pix = np.array([c.pixel_size_mm for c in data.cameras])[data.photo_camera[data.obs_photo]]
    return model.unwhiten(ev.r) / pix[:, None]


@pytest.mark.parametrize("pixel_um", [1.0, 4.3])
def test_colmap_import_reproduces_opencv_image_points(tmp_path, pixel_um):
    d = read_colmap(make_colmap(tmp_path / "sparse"), pixel_size_um=pixel_um)
    assert {c.model for c in d.cameras} == {"forward"}
    assert d.obs_photo.size > 400
    assert np.abs(_residual_px(d)).max() < 1e-9


def test_colmap_round_trip_through_a_project(tmp_path):
    src = make_colmap(tmp_path / "sparse")
    d = read_colmap(src, pixel_size_um=3.0)
    write_project(tmp_path / "proj", d)
    d2 = read_project(tmp_path / "proj")
    assert np.abs(_residual_px(d2)).max() < 1e-9  # the project file keeps every digit
    write_colmap(d2, tmp_path / "out")
    proj, meas = _colmap_projections(tmp_path / "out")
    proj0, meas0 = _colmap_projections(src)
    assert proj.keys() == proj0.keys()
    e = max(np.abs(proj[k] - proj0[k]).max() for k in proj)
    m = max(np.abs(meas[k] - meas0[k]).max() for k in meas)
    assert e < 1e-9 and m < 1e-9, (e, m)
    with pytest.raises(Exception, match="exists"):
        write_colmap(d2, tmp_path / "out")


def test_colmap_refuses_rational_and_unknown_models(tmp_path):
    src = make_colmap(tmp_path / "s")
    txt = (src / "cameras.txt").read_text().replace(" 0.01 0.0 0.0 0.0", " 0.01 0.2 0.0 0.0")
    (src / "cameras.txt").write_text(txt)
    with pytest.raises(Exception, match="rational"):
        read_colmap(src)
    (src / "cameras.txt").write_text(f"1 FISHEYE {W} {H} 1 2 3 4 5\n")
    with pytest.raises(Exception, match="not supported"):
        read_colmap(src)


def test_bal_round_trip(tmp_path):
    prob, _ = synthetic_bal(n_cam=6, n_pts=50, seed=3)
    f = tmp_path / "p.txt"
    L = [f"{prob.n_cameras} {prob.n_points} {prob.n_observations}"]
    L += [
        f"{c} {p} {float(x)!r} {float(y)!r}"
        for c, p, (x, y) in zip(prob.cam_index, prob.point_index, prob.xy, strict=True)
    ]
    L += [repr(float(v)) for v in prob.cameras.ravel()] + [
        repr(float(v)) for v in prob.points.ravel()
    ]
    f.write_text("\n".join(L) + "\n")
    r0 = BALModel(prob).evaluate((prob.cameras, prob.points), False).r
    d = read_bal_project(f, pixel_size_um=2.0)
    assert np.abs(_residual_px(d) - r0).max() < 1e-9
    write_bal_project(d, tmp_path / "q.txt")
    q = read_bal(tmp_path / "q.txt")
    r1 = BALModel(q).evaluate((q.cameras, q.points), False).r
    assert np.abs(r1 - r0).max() < 1e-9


def test_cli_import_export(tmp_path):
    src = make_colmap(tmp_path / "sparse")
    run = CliRunner()
    r = run.invoke(cli, ["import", "colmap", str(src), "--out", str(tmp_path / "p")])
    assert r.exit_code == 0, r.output
    assert "8 photos" in r.output
    r = run.invoke(cli, ["export", "colmap", str(tmp_path / "p"), str(tmp_path / "o")])
    assert r.exit_code == 0, r.output
    proj, meas = _colmap_projections(tmp_path / "o")
    proj0, _ = _colmap_projections(src)
    assert max(np.abs(proj[k] - proj0[k]).max() for k in proj) < 1e-9
    r = run.invoke(cli, ["export", "bal", str(tmp_path / "p"), str(tmp_path / "x.txt")])
    assert r.exit_code != 0 and "BAL has only" in str(r.exception or r.output)
    assert json.dumps({"ok": True})
