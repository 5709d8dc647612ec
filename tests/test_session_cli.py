"""``softplot plot``: scripted sessions through the CLI, virtual and GRBL-simulated motors."""

from __future__ import annotations

import ezdxf
import numpy as np
import pytest

from softplot.cli import main
from softplot.geometry.collinearity import project
from softplot.motors.simulator import GrblSimulator
from softplot.pipeline.session import Session


def _run(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


@pytest.fixture
def job(tmp_path):
    (tmp_path / "photos.csv").write_text(
        "photo,X0,Y0,Z0,omega,phi,kappa,c\nL,0,0,1700,0,0,0,152\nR,900,0,1700,0.5,-0.3,1,152\n"
    )
    return tmp_path


def _ops(path, P, with_px=False, offset=0.0):
    R = np.deg2rad([0.5, -0.3, 1.0])
    from softplot.geometry.rotation import rotation_matrix

    xy2 = project(P, [900, 0, 1700], rotation_matrix(*R), 152)
    xy1 = project(P, [0, 0, 1700], np.eye(3), 152)
    lines = ["name,X,Y,px" if with_px else "name,X,Y"]
    for i, ((x2, y2), (x1, _)) in enumerate(zip(xy2, xy1, strict=True)):
        row = [f"v{i}", repr(float(x2)), repr(float(y2))]
        if with_px:
            row.append(repr(float(x1 - x2 - offset)))
        lines.append(",".join(row))
    path.write_text("\n".join(lines) + "\n")
    return path


def test_scripted_contour_and_spot_heights(job, capsys):
    t = np.linspace(0, 2 * np.pi, 16, endpoint=False)
    ring = np.c_[450 + 120 * np.cos(t), 30 + 120 * np.sin(t), np.full(16, 310.0)]
    ops = _ops(job / "ring.csv", ring)
    folder = str(job / "s")
    code, out, err = _run(
        [
            "plot",
            "new",
            folder,
            "--photos",
            str(job / "photos.csv"),
            "--mode",
            "contour",
            "--height",
            "310",
        ],
        capsys,
    )
    assert code == 0, err
    code, out, err = _run(
        [
            "plot",
            "trace",
            folder,
            "--input",
            str(ops),
            "--code",
            "C310",
            "--kind",
            "contour",
            "--close",
        ],
        capsys,
    )
    assert code == 0, err
    spots = np.array([[400.0, 10.0, 250.0], [500.0, -40.0, 330.0]])
    ops2 = _ops(job / "spots.csv", spots, with_px=True)
    code, out, err = _run(
        ["plot", "trace", folder, "--input", str(ops2), "--code", "SPOT", "--mode", "single"],
        capsys,
    )
    assert code == 0, err
    s = Session.resume(folder)
    c = s.features[0]
    assert c.kind == "contour" and c.closed
    assert np.max(np.abs(c.vertices[:-1] - ring)) < 1e-6
    assert np.max(np.abs(np.vstack([f.vertices for f in s.features[1:]]) - spots)) < 1e-6
    s.close()
    code, out, err = _run(["plot", "export", folder, str(job / "out.dxf")], capsys)
    assert code == 0, err
    doc = ezdxf.readfile(job / "out.dxf")
    assert not doc.audit().has_errors
    assert sorted(e.dxftype() for e in doc.modelspace()) == [
        "LWPOLYLINE",
        "POINT",
        "POINT",
        "TEXT",
        "TEXT",
    ]
    code, out, err = _run(["plot", "resume", folder], capsys)
    assert code == 0 and "C310" in out and "3 feature(s), 0 fault(s)" in out


def test_scripted_session_on_the_simulated_instrument(job, capsys):
    folder = str(job / "g")
    # the mean x-parallax (~98 mm) sits in the fixed left-plate offset, DX stays small
    _run(
        ["plot", "new", folder, "--photos", str(job / "photos.csv"), "--left-offset", "98", "0"],
        capsys,
    )
    spots = np.array([[450.0, 0.0, 300.0], [460.0, 5.0, 301.0]])
    ops = _ops(job / "spots.csv", spots, with_px=True, offset=98.0)
    with GrblSimulator(time_scale=50) as sim:
        code, out, err = _run(
            ["plot", "trace", folder, "--input", str(ops), "--code", "SPOT", "--port", sim.path],
            capsys,
        )
        assert code == 0, err
        moves = [ln for ln in sim.log if ln.startswith("G90G1")]
        assert len(moves) == 2
        s = Session.resume(folder)
        assert s.motor_state is not None
        # the instrument stands where the last point needs it (0.01 mm steps)
        dx, dy = (v * 0.01 for v in s.motor_state["target_steps"])
        assert sim.pos[:2] == pytest.approx([dx, dy], abs=1e-9)
        s.close()
        sim.inject("alarm@move1")
        code, out, err = _run(
            [
                "plot",
                "trace",
                folder,
                "--input",
                str(ops),
                "--code",
                "SPOT",
                "--port",
                sim.path,
                "--timeout",
                "1",
            ],
            capsys,
        )
    assert code == 2 and "ALARM:1" in err and "session kept" in err and err.count("\n") == 1
    s = Session.resume(folder)
    assert len(s.faults) == 1 and len(s.features) >= 2
    s.close()


def test_plot_cli_errors(job, capsys):
    folder = str(job / "e")
    code, _, err = _run(
        ["plot", "new", folder, "--photos", str(job / "photos.csv"), "--mode", "contour"], capsys
    )
    assert code == 2 and "needs --height" in err
    _run(["plot", "new", folder, "--photos", str(job / "photos.csv")], capsys)
    code, _, err = _run(["plot", "new", folder, "--photos", str(job / "photos.csv")], capsys)
    assert code == 2 and "already holds a session" in err
    code, _, err = _run(
        ["plot", "trace", folder, "--input", str(job / "none.csv"), "--code", "A"], capsys
    )
    assert code == 2 and "cannot read input file" in err
    code, _, err = _run(["plot", "export", folder, str(job / "e" / "journal.jsonl")], capsys)
    assert code == 2 and "overwrite a session file" in err
    code, _, err = _run(["plot", "resume", str(job / "missing")], capsys)
    assert code == 2 and "no session" in err
