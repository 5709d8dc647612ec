"""Plotting sessions record what was measured: no spot height in contour mode, ``plot trace
--mode`` for that trace only, and a point the carriage did not reach (outside its travel or
the model, or a carriage that stopped short) is not recorded, said in one line."""

from __future__ import annotations

import numpy as np
import pytest

from session_helpers import affine_scan_map, corner_camera
from softplot.cli import main
from softplot.errors import SoftplotError
from softplot.geometry.collinearity import project
from softplot.geometry.rotation import rotation_matrix
from softplot.motors import AxisConfig, VirtualMotors
from softplot.motors.simulator import GrblSimulator
from softplot.pipeline.session import Session
from softplot.stereo.model import OrientedPhoto, StereoModel
from softplot.stereo.plotter import NotReached, Plotter
from softplot.synthetic.stereo import aerial_pair

FINE = AxisConfig(resolution_mm=1e-7, min_mm=-150, max_mm=150, max_speed_mm_s=1e9)
SLOW = AxisConfig(resolution_mm=1e-3, min_mm=-150, max_mm=150, max_speed_mm_s=1.0)


def run(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in argv])
    out = capsys.readouterr()
    return e.value.code, out.out, out.err


def _pair(seed):
    """The synthetic aerial pair with its principal points at 0 (the scans' correction)."""
    t = aerial_pair(seed=seed, deform=False)
    t.x0[:] = 0.0
    t.y0[:] = 0.0
    return t


def _model(t, scans=False):
    photos = []
    for k in range(2):
        f2p = p2f = None
        if scans:  # 300 mm square scans, identity film correction
            m = affine_scan_map(corner_camera(t.c[k]))
            f2p, p2f = m, m.inverse
        photos.append(OrientedPhoto(t.X0[k], t.angles[k], t.c[k], 0.0, 0.0, f2p, p2f))
    return StereoModel(*photos)


@pytest.fixture
def job(tmp_path):
    (tmp_path / "photos.csv").write_text(
        "photo,X0,Y0,Z0,omega,phi,kappa,c\nL,0,0,1700,0,0,0,152\nR,900,0,1700,0.5,-0.3,1,152\n"
    )
    return tmp_path


def _ops(path, P, with_px=True, px_shift=None, offset=0.0):
    """Operator input over the ``job`` pair reaching object points ``P`` (right film X, Y and
    the true x-parallax, minus the left-plate ``offset``; ``px_shift`` added per row)."""
    xy2 = project(P, [900, 0, 1700], rotation_matrix(*np.deg2rad([0.5, -0.3, 1.0])), 152)
    xy1 = project(P, [0, 0, 1700], np.eye(3), 152)
    shift = np.zeros(len(P)) if px_shift is None else np.asarray(px_shift, float)
    lines = ["name,X,Y,px" if with_px else "name,X,Y"]
    for i, ((x2, y2), (x1, _)) in enumerate(zip(xy2, xy1, strict=True)):
        row = [f"v{i}", repr(float(x2)), repr(float(y2))]
        if with_px:
            row.append(repr(float(x1 - x2 - offset + shift[i])))
        lines.append(",".join(row))
    path.write_text("\n".join(lines) + "\n")
    return path


SPOTS = np.array([[400.0, 10.0, 250.0], [500.0, -40.0, 330.0], [450.0, 20.0, 290.0]])


def test_no_spot_height_in_contour_mode():
    """In contour mode the mark is held at Z = H whatever the terrain: a spot height there is
    refused; a point the mark was driven to, and spot heights in single mode, are the model
    point under the mark."""
    t = _pair(31)
    pl = Plotter(_model(t), VirtualMotors(FINE, FINE), mode="contour", height=300.0)
    P = t.sample_points(2, seed=4)
    X, Y = t.film(1, P)[0]
    pl.cycle(X, Y)
    with pytest.raises(SoftplotError, match="not measured in contour mode"):
        pl.record_point("SPOT")
    assert pl.features == []
    pl.drive_to(*P[1])
    f = pl.record_point("SPOT")
    assert np.max(np.abs(f.vertices[0] - P[1])) < 1e-6
    pl.set_mode("single")
    pl.cycle(X, Y, px=t.film(0, P)[0, 0] - X)
    f = pl.record_point("SPOT")
    assert np.max(np.abs(f.vertices[0] - P[0])) < 1e-6  # the terrain, not Z = 300


def test_cli_refuses_spot_heights_in_contour_mode(job, capsys):
    folder = job / "s"
    assert run(["plot", "new", folder, "--photos", job / "photos.csv", "--mode", "contour",
                "--height", "310"], capsys)[0] == 0
    ops = _ops(job / "spots.csv", SPOTS, with_px=False)
    code, _, err = run(["plot", "trace", folder, "--input", ops, "--code", "SPOT"], capsys)
    assert code == 2 and "contour mode" in err and len(err.strip().splitlines()) == 1
    s = Session.resume(folder)
    assert s.features == []
    s.close()


def test_trace_mode_is_for_that_trace_only(job, capsys):
    folder = job / "s"
    assert run(["plot", "new", folder, "--photos", job / "photos.csv"], capsys)[0] == 0
    t = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    ring = np.c_[450 + 100 * np.cos(t), 30 + 100 * np.sin(t), np.full(8, 310.0)]
    code, out, err = run(["plot", "trace", folder, "--input", _ops(job / "ring.csv", ring, False),
                          "--code", "C310", "--kind", "contour", "--mode", "contour",
                          "--height", "310", "--close"], capsys)
    assert code == 0, err
    assert "for this trace" in out and "single" in out
    s = Session.resume(folder)
    assert s.mode == "single" and s.height is None
    assert np.max(np.abs(s.features[0].vertices[:, 2] - 310.0)) < 1e-9
    s.close()
    # the next trace runs in the session's own mode (single: the px column)
    code, _, err = run(["plot", "trace", folder, "--input", _ops(job / "spots.csv", SPOTS),
                        "--code", "SPOT"], capsys)
    assert code == 0, err
    code, out, _ = run(["plot", "resume", folder], capsys)
    assert code == 0 and out.startswith("mode single")
    # `plot mode` changes the session's mode for good
    assert run(["plot", "mode", folder, "contour", "--height", "300"], capsys)[0] == 0
    s = Session.resume(folder)
    assert (s.mode, s.height) == ("contour", 300.0)
    assert np.max(np.abs(np.vstack([f.vertices for f in s.features[1:]]) - SPOTS)) < 1e-6
    s.close()
    code, _, err = run(["plot", "mode", folder, "contour"], capsys)  # keeps its height
    assert code == 0
    code, _, err = run(["plot", "mode", job / "s", "free"], capsys)
    assert code == 0 and Session.resume(folder).mode == "free"


def test_rows_outside_the_travel_are_not_recorded(job, capsys):
    folder = job / "s"
    run(["plot", "new", folder, "--photos", job / "photos.csv"], capsys)
    ops = _ops(job / "spots.csv", SPOTS, px_shift=[0.0, 700.0, 0.0])  # v1: DX beyond 500 mm
    code, out, err = run(["plot", "trace", folder, "--input", ops, "--code", "SPOT"], capsys)
    assert code == 0, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "v1" in lines[0] and "not recorded" in lines[0]
    assert "travel" in lines[0]
    assert "1 row(s) not recorded" in out
    s = Session.resume(folder)
    assert [f.attributes["name"] for f in s.features] == ["v0", "v2"]
    s.close()


def test_grbl_rows_outside_the_travel_are_not_recorded(job, capsys):
    """On the simulated GRBL instrument (+-20 mm travel) a row the carriage cannot reach is
    not recorded: the plate never moved for it."""
    folder = job / "g"
    run(["plot", "new", folder, "--photos", job / "photos.csv", "--left-offset", "98", "0"],
        capsys)
    ops = _ops(job / "spots.csv", SPOTS[:2], offset=98.0, px_shift=[0.0, 35.0])
    with GrblSimulator(time_scale=50) as sim:
        code, out, err = run(["plot", "trace", folder, "--input", ops, "--code", "SPOT",
                              "--port", sim.path], capsys)
        moves = [ln for ln in sim.log if ln.startswith("G90G1")]
    assert code == 0, err
    assert len(moves) == 1
    assert "v1: not recorded" in err and "travel" in err
    s = Session.resume(folder)
    assert [f.attributes["name"] for f in s.features] == ["v0"]
    assert np.max(np.abs(s.features[0].vertices[0] - SPOTS[0])) < 0.05
    s.close()


class _StuckMotors(VirtualMotors):
    """A carriage that takes its orders and never moves (a stalled motor, a cut cable)."""

    def _start_move(self, motor_steps, speed_mm_s):
        self.moves += 1


def test_a_point_the_carriage_did_not_reach_is_not_recorded():
    t = _pair(32)
    P = t.sample_points(1, seed=6)
    (X, Y), (x1f, _) = t.film(1, P)[0], t.film(0, P)[0]
    for mot, msg in ((_StuckMotors(FINE, FINE), "stands at"),
                     # still on its way (1 mm/s) when the point is recorded
                     (VirtualMotors(SLOW, SLOW, simulate_time=True), "did not reach")):
        pl = Plotter(_model(t), mot, mode="single", reach_timeout=0.05)
        pl.cycle(X, Y, px=x1f - X)
        with pytest.raises(NotReached, match=msg):
            pl.record_point("SPOT")
        pl.begin("ROAD", "line")
        with pytest.raises(NotReached, match=msg):
            pl.vertex()
        assert pl.features == [] and pl.end() is None
    # the same point on a carriage that gets there is recorded
    pl = Plotter(_model(t), VirtualMotors(FINE, FINE), mode="single")
    pl.cycle(X, Y, px=x1f - X)
    assert np.max(np.abs(pl.record_point("SPOT").vertices[0] - P[0])) < 1e-6


def test_a_mark_outside_the_model_is_not_recorded():
    """Off a scan, or rays meeting behind the cameras: not a model point."""
    t = _pair(33)
    mot = VirtualMotors(AxisConfig(resolution_mm=1e-7, min_mm=-400, max_mm=400,
                                   max_speed_mm_s=1e9),
                        AxisConfig(resolution_mm=1e-7, min_mm=-400, max_mm=400,
                                   max_speed_mm_s=1e9))
    pl = Plotter(_model(t, scans=True), mot, mode="single")
    P = t.sample_points(1, seed=7)
    (X, Y), (x1f, _) = t.film(1, P)[0], t.film(0, P)[0]
    pl.cycle(X, Y, px=x1f - X)
    pl.record_point("SPOT")  # on both scans
    pl.cycle(X, Y, px=x1f - X + 250.0)  # the left film point 250 mm away: off the scan
    with pytest.raises(NotReached, match="off the left scan"):
        pl.record_point("SPOT")
    pl.cycle(X + 200.0, Y, px=x1f - X)  # the main carriage off the right scan
    with pytest.raises(NotReached, match="off the right scan"):
        pl.record_point("SPOT")
    # no scans: rays that meet behind the cameras (x-parallax of the wrong sign)
    pl = Plotter(_model(t), mot, mode="single")
    base = x1f - X
    pl.cycle(X, Y, px=-base)
    with pytest.raises(NotReached, match="behind"):
        pl.record_point("SPOT")
    assert len(pl.features) == 0
