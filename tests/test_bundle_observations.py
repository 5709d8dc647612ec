"""Observations: 2x2 covariances in the engine and the files, one point column, IO from a
detection JSON alone."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from softplot.camera import load_camera
from softplot.cli import main
from softplot.orientation.bundle import bundle_adjust
from softplot.orientation.bundle_io import read_project, write_project
from softplot.synthetic.testfield import make_testfield

FREE = ("c", "x0", "y0", "k1")


def _correlated(n, rng):
    """Per observation sx, sy (mm) and covariance sxy: ellipses 1.5-4 um, rho up to 0.9."""
    sx = rng.uniform(1.5, 4.0, n) / 1000
    sy = rng.uniform(1.5, 4.0, n) / 1000
    rho = rng.uniform(-0.9, 0.9, n)
    return sx, sy, rho * sx * sy


def _noisy(net, sx, sy, sxy, rng):
    z = rng.standard_normal((sx.size, 2))
    l21 = sxy / sx
    l22 = np.sqrt(sy**2 - l21**2)
    return net.xy_true + np.column_stack([sx * z[:, 0], l21 * z[:, 0] + l22 * z[:, 1]])


def test_correlated_observations_weighted_by_their_covariance():
    """GLS with the 2x2 covariances: sigma0 ~ 1 and the reported std match the spread."""
    net = make_testfield(n_photos=8, noise_um=0.0, control_sigma_m=0.0, seed=2)
    rng = np.random.default_rng(5)
    sx, sy, sxy = _correlated(net.xy_true.shape[0], rng)
    z2, s0 = [], []
    for _ in range(100):
        d = net.to_bundle_data(free=FREE)
        d.xy = _noisy(net, sx, sy, sxy, rng)
        d.sigma_xy = np.column_stack([sx, sy])
        d.cov_xy = sxy
        res = bundle_adjust(d)
        z2.append(((res.intrinsics[0, :4] - net.intr_true[0, :4]) / res.intrinsics_std[0, :4]) ** 2)
        s0.append(res.sigma0)
    # the cost is the generalised one: 0.5 sum v' Sigma^-1 v of the reported residuals
    v = res.residuals_mm
    det = sx**2 * sy**2 - sxy**2
    q = (sy**2 * v[:, 0] ** 2 - 2 * sxy * v[:, 0] * v[:, 1] + sx**2 * v[:, 1] ** 2) / det
    assert abs(0.5 * q.sum() - res.cost) < 1e-9 * res.cost
    # unit-weight variance ~ 1; parameter errors consistent with their std (400 values)
    assert abs(np.mean(np.square(s0)) - 1.0) < 0.05
    assert 0.8 < np.mean(z2) < 1.22, np.mean(z2)


def test_covariance_must_be_positive_definite():
    net = make_testfield(n_photos=4, seed=0)
    d = net.to_bundle_data()
    d.cov_xy = np.full(d.obs_photo.size, 1.0)  # |rho| >> 1
    with pytest.raises(Exception, match="correlation"):
        d.__post_init__()


def test_project_files_name_column_sxy_and_old_point_header(tmp_path):
    net = make_testfield(n_photos=6, seed=1)
    d = net.to_bundle_data(free=FREE)
    rng = np.random.default_rng(0)
    sx, sy, sxy = _correlated(d.obs_photo.size, rng)
    d.sigma_xy = np.column_stack([sx, sy])
    d.cov_xy = sxy
    write_project(tmp_path / "p", d)
    hdr = (tmp_path / "p" / "observations.csv").read_text().splitlines()[0]
    assert hdr == "photo,name,x,y,sx,sy,sxy"
    assert (tmp_path / "p" / "control.csv").read_text().startswith("name,")
    a = read_project(tmp_path / "p")
    np.testing.assert_array_equal(a.cov_xy, sxy)
    np.testing.assert_array_equal(a.sigma_xy, d.sigma_xy)
    # the older header 'point' is still read, in both files
    for f in ("observations.csv", "control.csv"):
        p = tmp_path / "p" / f
        lines = p.read_text().splitlines()
        lines[0] = lines[0].replace("name", "point", 1)
        p.write_text("\n".join(lines) + "\n")
    b = read_project(tmp_path / "p")
    assert b.point_names == a.point_names
    np.testing.assert_array_equal(b.control, a.control)
    np.testing.assert_array_equal(b.xy, a.xy)
    ra, rb = bundle_adjust(_init(a)), bundle_adjust(_init(b))
    assert ra.sigma0 == pytest.approx(rb.sigma0, rel=1e-12)


def _init(d):
    from softplot.orientation.bundle_init import initialize

    return initialize(d)


def _run(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in argv])
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def test_interior_orientation_from_a_detection_json_alone(tmp_path, capsys):
    """`softplot correct DET.json --camera C --points ...`: no scan, its size from the JSON."""
    cam = load_camera("rollei-6006")
    R = cam.reseau
    film = R.film().reshape(R.rows, R.cols, 2)
    ps, ang = 25.4 / 800.0, np.deg2rad(0.7)
    rot = np.array([[np.cos(ang), -np.sin(ang)], [np.sin(ang), np.cos(ang)]])
    W, H = 2100, 2150

    def to_px(f):  # film mm (y up) -> pixel (row down), an exact similarity
        q = f @ rot.T / ps
        return np.column_stack([W / 2 + q[:, 0], H / 2 - q[:, 1]])

    px = to_px(film.reshape(-1, 2)).reshape(R.rows, R.cols, 2)
    det = {
        "camera": cam.name,
        "width": W,
        "height": H,
        "marks": [
            {
                "kind": "reseau",
                "name": f"R{r}C{c}",
                "row": r,
                "col": c,
                "x": float(px[r, c, 0]),
                "y": float(px[r, c, 1]),
                "status": "measured",
            }
            for r in range(R.rows)
            for c in range(R.cols)
        ],
    }
    dj = tmp_path / "scan.det.json"
    dj.write_text(json.dumps(det))
    pts = np.random.default_rng(0).uniform(-20, 20, (30, 2))
    inp = tmp_path / "in.csv"
    with inp.open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["name", "x", "y"])
        for i, (x, y) in enumerate(to_px(pts)):
            w.writerow([f"p{i}", repr(float(x)), repr(float(y))])
        w.writerow(["far", "-400", "10"])
    out = tmp_path / "out.csv"
    code, so, se = _run(
        ["correct", dj, "--camera", cam.name, "--points", inp, "--out", out], capsys
    )
    assert code == 0, se
    rows = list(csv.DictReader(out.open()))
    xy = np.array([[float(r["x"]), float(r["y"])] for r in rows[:-1]])
    assert np.abs(xy - pts).max() < 2e-6  # mm (6 decimals in the CSV)
    assert rows[-1]["flag"] == "outside-image"  # the scan's size came from the JSON
    code, _, se = _run(
        ["correct", dj, "--camera", cam.name, "--resample", tmp_path / "x.tif"], capsys
    )
    assert code == 2 and "needs the scan" in se


def test_redundancy_numbers_and_w_with_correlated_observations():
    """Redundancy numbers diag(Qvv P) sum to the redundancy; Baarda's w with the full weight
    matrix finds a blunder along the direction the covariance makes unlikely."""
    net = make_testfield(n_photos=10, noise_um=0.0, control_sigma_m=0.0, seed=6)
    rng = np.random.default_rng(2)
    n = net.xy_true.shape[0]
    sx = np.full(n, 0.002)
    sy = np.full(n, 0.002)
    sxy = 0.95 * sx * sy  # errors along the (1, 1) diagonal; (1, -1) is 6x more precise
    d = net.to_bundle_data(free=FREE)
    d.xy = _noisy(net, sx, sy, sxy, rng)
    d.xy[7] += np.array([1.0, -1.0]) * 0.0025  # a blunder across the error ellipse
    d.sigma_xy = np.column_stack([sx, sy])
    d.cov_xy = sxy
    res = bundle_adjust(d)
    r = res.redundancy_numbers
    assert np.all((r > 0) & (r < 1))
    assert r.sum() == pytest.approx(res.redundancy, rel=1e-9)
    wmax = np.nanmax(np.abs(res.w), axis=1)
    assert int(np.argmax(wmax)) == 7 and res.flagged[7]
    assert res.flagged.sum() <= 3


def test_w_and_redundancy_numbers_match_dense_generalised_formulas():
    """Against full matrices: Qvv = Sigma - A Q A', r = diag(Qvv P),
    w = P v / sqrt(diag(P Qvv P))."""
    import scipy.linalg

    from test_bundle_engine import dense_system

    net = make_testfield(n_photos=5, noise_um=0.0, control_sigma_m=0.0, seed=8)
    rng = np.random.default_rng(3)
    sx, sy, sxy = _correlated(net.xy_true.shape[0], rng)
    d = net.to_bundle_data(free=FREE)
    d.xy = _noisy(net, sx, sy, sxy, rng)
    d.sigma_xy = np.column_stack([sx, sy])
    d.cov_xy = sxy
    res = bundle_adjust(d)
    it = res._internals
    J, _, ev = dense_system(it["model"], it["state"])
    st = it["model"].structure
    free = np.concatenate([np.ones(st.n_cam, bool), st.point_free.ravel()])
    A = J[: 2 * d.obs_photo.size][:, free]  # whitened design matrix
    Sigma = scipy.linalg.block_diag(
        *[[[a * a, c], [c, b * b]] for a, b, c in zip(sx, sy, sxy, strict=True)]
    )
    L = np.linalg.cholesky(Sigma)
    Au = L @ A  # unwhitened (mm per unknown)
    P = np.linalg.inv(Sigma)
    Q = np.linalg.inv(Au.T @ P @ Au)
    Qvv = Sigma - Au @ Q @ Au.T
    v = res.residuals_mm.ravel()
    r = np.diag(Qvv @ P)
    w = (P @ v) / np.sqrt(np.diag(P @ Qvv @ P))
    np.testing.assert_allclose(res.redundancy_numbers.ravel(), r, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(res.w.ravel(), w, rtol=1e-5, atol=1e-6)
