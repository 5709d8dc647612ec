"""PhotoModeler text export in: its camera model reproduced exactly, --control, aspect."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.cli import main
from softplot.geometry.rotation import from_radians
from softplot.orientation.bundle import _Model, _State, bundle_adjust
from softplot.orientation.bundle_init import initialize
from softplot.orientation.bundle_io import read_project
from softplot.orientation.interchange.photomodeler import read_photomodeler
from softplot.synthetic.testfield import make_testfield

W, H = 4000, 3000
FW, FH = 36.0, 27.0
# PhotoModeler camera: C, XP, YP (from the top-left, downwards), K1..K3, P1, P2 (correction)
PM = dict(c=24.5, xp=18.1, yp=13.35, K=(2.1e-4, -3.5e-7, 1e-10), P=(-2e-5, 3e-5))


def pm_correct(m, K, P):
    """PhotoModeler's correction of measured points m (mm, y up, reduced to the PP)."""
    x, y = m[:, 0], m[:, 1]
    r2 = x * x + y * y
    dr = K[0] * r2 + K[1] * r2**2 + K[2] * r2**3
    return np.column_stack(
        [
            x + x * dr + P[0] * (r2 + 2 * x * x) + 2 * P[1] * x * y,
            y + y * dr + P[1] * (r2 + 2 * y * y) + 2 * P[0] * x * y,
        ]
    )


def make_export(path, net, aspect=0.0, control=True):
    """A PhotoModeler export of a test field seen by the PM camera (exact marked points)."""
    X0, M = net.X0_true, net.M_true
    lines = ["synthetic", f"0.0001 20 {W} {H}", "0.001 0.001 0.01 1 1", "", ""]
    cam = f"{PM['c']} {PM['xp']} {PM['yp']} {FW} {FH} {' '.join(map(str, PM['K']))} "
    cam += " ".join(map(str, PM["P"]))
    ang = from_radians(net.angles_true, "deg")
    for f, name in enumerate(net.photo_names):
        o, p_, k = ang[f]
        lines += [
            f"{f} {name}.jpg",
            f"{f} " + " ".join(repr(float(v)) for v in [*X0[f], k, p_, o]),
            f"{f} 0 0 0 0 0 0",
            f"{f}",
            f"{f} {cam}",
            f"{f} 0.01 0.01 0.01 {0.001 if aspect else 0} 0 1e-6 1e-9 1e-12 1e-7 1e-7",
        ]
    lines.append("")
    ctl = [j for j in range(len(net.point_names)) if j % 3 == 0]
    for j in ctl if control else []:
        X = net.XYZ_true[j]
        lines.append(f"{j + 1} {float(X[0])!r} {float(X[1])!r} {float(X[2])!r} 0 0 0")
    lines.append("")
    for j, X in enumerate(net.XYZ_true):
        Xa = X + 0.01
        lines.append(f"{j + 1} {float(Xa[0])!r} {float(Xa[1])!r} {float(Xa[2])!r} 0 0 0")
    lines.append("")
    rows = []
    for f in range(len(net.photo_names)):
        u = (net.XYZ_true - X0[f]) @ M[f].T
        pin = -PM["c"] * u[:, :2] / u[:, 2:3]
        m = pin.copy()  # solve corrected(m) = pinhole by fixed point iteration
        with np.errstate(all="ignore"):  # points far outside the format diverge: dropped
            for _ in range(200):
                m = m - (pm_correct(m, PM["K"], PM["P"]) - pin)
        # DBAT's aspect: the measured x scaled by 1 + b1 before the correction
        m[:, 0] /= 1.0 + aspect
        col = (m[:, 0] + PM["xp"]) * W / FW
        row = (PM["yp"] - m[:, 1]) * H / FH
        with np.errstate(invalid="ignore"):
            ok = (col > 0) & (col < W) & (row > 0) & (row < H) & (u[:, 2] < 0)
        for j in np.flatnonzero(ok):
            rows.append(f"{f} {j + 1} {float(col[j])!r} {float(row[j])!r} 0 0")
    lines += rows + [""]
    path.write_text("\n".join(lines) + "\n")
    return path


def _residual_mm(d, net, a=0.0):
    model = _Model(d, np.ones((len(d.point_names), 3), bool))
    idx = [int(n) - 1 for n in d.point_names]
    intr = np.array([c.values for c in d.cameras])
    intr[:, 10] = a
    st = _State(net.X0_true.copy(), net.M_true.copy(), intr, net.XYZ_true[idx])
    return model.unwhiten(model.evaluate(st, False).r)


@pytest.mark.parametrize("aspect", [0.0, 2e-3])
def test_photomodeler_camera_reproduced_exactly(tmp_path, aspect):
    net = make_testfield(n_photos=6, seed=2)
    d = read_photomodeler(make_export(tmp_path / "pm.txt", net, aspect))
    assert d.cameras[0].model == "inverse"
    v = d.cameras[0].values
    assert v[0] == PM["c"] and v[1] == pytest.approx(PM["xp"] - FW / 2)
    assert v[2] == pytest.approx(FH / 2 - PM["yp"]) and v[3] == -PM["K"][0]
    assert (v[6], v[7]) == (-PM["P"][0], -PM["P"][1])
    assert np.isinf(d.cameras[0].sigma[10]) == bool(aspect)  # estimated format width: a free
    e = np.abs(_residual_mm(d, net, aspect)).max() / (FW / W)
    assert e < 1e-9, e  # pixels
    assert np.abs(d.X0 - net.X0_true).max() < 1e-9  # the orientations kept (consistent)


def test_photomodeler_adjustment_with_control_file(tmp_path, capsys):
    net = make_testfield(n_photos=8, seed=4)
    exp = make_export(tmp_path / "pm.txt", net, aspect=1.5e-3, control=False)
    ctl = tmp_path / "fixed.txt"
    ctl.write_text(
        "# id X Y Z\n"
        + "".join(
            f"{j + 1}, {float(X[0])!r}, {float(X[1])!r}, {float(X[2])!r}\n"
            for j, X in enumerate(net.XYZ_true)
        )
    )
    with pytest.raises(SystemExit) as e:
        main(
            [
                "import",
                "photomodeler",
                str(exp),
                "--control",
                str(ctl),
                "--out",
                str(tmp_path / "p"),
            ]
        )
    assert e.value.code == 0, capsys.readouterr().err
    d = read_project(tmp_path / "p")
    assert np.isfinite(d.control).all() and np.all(d.control_sigma == 0)
    initialize(d)
    res = bundle_adjust(d)
    assert res.converged and res.rms_image_um()["xy"] < 1e-4
    assert res.intrinsics[0, 10] == pytest.approx(1.5e-3, abs=1e-9)  # the aspect recovered
    assert res.intrinsics[0, 0] == pytest.approx(PM["c"], abs=1e-8)


def test_photomodeler_bad_input(tmp_path):
    p = tmp_path / "bad.txt"
    p.write_text("t\n0.1 10\n0.001\n24 18 12 36 24 0 0 0 0\n0 0 0 0 0 0 0 0 0\n0 a\n")
    with pytest.raises(Exception, match="image size"):
        read_photomodeler(p)


def test_cli_import_photomodeler_errors(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["import", "photomodeler", str(tmp_path / "none.txt"), "--out", str(tmp_path / "p")])
    assert e.value.code == 2 and "not found" in capsys.readouterr().err
    assert not (tmp_path / "p").exists()
