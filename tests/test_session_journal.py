"""Sessions: fsync'd journal, resume (MODEL RESUME), torn records, kill -9 in the middle."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from session_helpers import affine_scan_map, corner_camera
from softplot.errors import SoftplotError
from softplot.export.features import Feature
from softplot.motors import AxisConfig, MotorAlarm, VirtualMotors
from softplot.pipeline.session import Session
from softplot.stereo import OrientedPhoto, PlotterHalted, StereoModel
from softplot.synthetic.stereo import aerial_pair

FINE = AxisConfig(resolution_mm=1e-6, min_mm=-150, max_mm=150, max_speed_mm_s=1e9)


def _model(seed=21, corrections=True):
    """The aerial pair; with ``corrections`` its film deformation is a film correction stored
    as data (an affine fitted to four fiducials, exact to rounding)."""
    t = aerial_pair(seed=seed, deform=corrections)
    t.x0[:] = 0.0  # the film correction reduces to the principal point
    t.y0[:] = 0.0
    photos = []
    for k in range(2):
        f2p = p2f = None
        if corrections:
            m = affine_scan_map(corner_camera(t.c[k]), t.deform[k])
            f2p, p2f = m, m.inverse
        photos.append(
            OrientedPhoto(t.X0[k], t.angles[k], t.c[k], t.x0[k], t.y0[k], f2p, p2f, name=f"p{k}")
        )
    return t, StereoModel(*photos)


def test_record_and_resume_restores_everything(tmp_path):
    t, model = _model()
    folder = tmp_path / "job"
    mot = VirtualMotors(FINE, FINE)
    with Session.create(folder, model, mode="contour", height=300.0) as s:
        pl = s.plotter(mot)
        C = t.contour_truth(300.0, 12)
        pl.begin("C300")
        for X, Y in t.film(1, C):
            pl.cycle(X, Y)
            pl.vertex()
        pl.end(close=True)
        s.set_mode("single")
        pl.set_mode("single")
        P = t.sample_points(3, seed=1)
        for (X, Y), (x1f, _) in zip(t.film(1, P), t.film(0, P), strict=True):
            pl.cycle(X, Y, px=x1f - X)
            pl.record_point("SPOT", name="p")
        saved_state = mot.state()
    mot2 = VirtualMotors(FINE, FINE)
    r = Session.resume(folder, motors=mot2)
    assert [f.kind for f in r.features] == ["contour", "point", "point", "point"]
    assert np.array_equal(r.features[0].vertices, s.features[0].vertices)  # exact floats
    assert r.mode == "single"
    assert mot2.position_steps() == tuple(saved_state["target_steps"])
    assert mot2.encoders() == pytest.approx(saved_state["main"])
    # orientation and film corrections restored without measuring again: same restitution
    P = t.sample_points(5, seed=8)
    film = t.film(0, P)
    assert np.array_equal(r.model.left.film_to_photo(film), model.left.film_to_photo(film))
    assert np.allclose(r.model.left.angles, model.left.angles, rtol=0, atol=0)
    pl2 = r.plotter(mot2)
    X, Y = t.film(1, P)[0]
    cyc = pl2.cycle(X, Y, px=film[0, 0] - X)
    assert np.max(np.abs(np.array(cyc.XYZ) - P[0])) < 1e-6
    r.close()


def test_torn_last_record_is_dropped(tmp_path):
    _, model = _model(corrections=False)
    s = Session.create(tmp_path / "j", model)
    s.record(Feature("A", "point", [1.0, 2.0, 3.0]))
    s.close()
    with open(tmp_path / "j" / "journal.jsonl", "ab") as fh:
        fh.write(b'{"type":"feature","feature":{"code":"B","ki')  # crash mid-write
    r = Session.resume(tmp_path / "j")
    assert [f.code for f in r.features] == ["A"]
    r.record(Feature("C", "point", [1.0, 2.0, 4.0]))
    r.close()
    assert [f.code for f in Session.resume(tmp_path / "j").features] == ["A", "C"]


def test_session_errors(tmp_path):
    _, model = _model(corrections=False)
    Session.create(tmp_path / "s", model).close()
    with pytest.raises(SoftplotError, match="already holds a session"):
        Session.create(tmp_path / "s", model)
    with pytest.raises(SoftplotError, match="no session"):
        Session.resume(tmp_path / "nothing")
    (tmp_path / "s" / "journal.jsonl").write_text("not json\n")
    with pytest.raises(SoftplotError, match="line 1 is not JSON"):
        Session.resume(tmp_path / "s")
    bad = StereoModel(
        OrientedPhoto([0, 0, 10], [0, 0, 0], 50, to_photo=lambda xy: xy),
        OrientedPhoto([5, 0, 10], [0, 0, 0], 50),
    )
    with pytest.raises(SoftplotError, match="stores film corrections as data"):
        Session.create(tmp_path / "lam", bad)


class _AlarmMotors(VirtualMotors):
    armed = False

    def _start_move(self, motor_steps, speed):
        if self.armed:
            raise MotorAlarm("GRBL ALARM:1 (hard limit triggered, position likely lost)", 1)
        super()._start_move(motor_steps, speed)


def test_motor_fault_is_journaled_and_session_kept(tmp_path):
    t, model = _model(corrections=False)
    mot = _AlarmMotors(FINE, FINE)
    s = Session.create(tmp_path / "f", model, mode="contour", height=300.0)
    pl = s.plotter(mot)
    pts = t.film(1, t.contour_truth(300.0, 6))
    pl.begin("C300")
    for X, Y in pts[:2]:
        pl.cycle(X, Y)
        pl.vertex()
    pl.end()
    mot.armed = True
    with pytest.raises(PlotterHalted, match="ALARM:1"):
        pl.cycle(*pts[2])
    s.close()
    r = Session.resume(tmp_path / "f")
    assert len(r.features) == 1
    assert len(r.faults) == 1 and "motors stopped" in r.faults[0]


def test_export_from_session(tmp_path):
    _, model = _model(corrections=False)
    s = Session.create(tmp_path / "e", model)
    s.record(Feature("SPOT", "point", [1.0, 2.0, 3.0]))
    s.record(Feature("EDGE", "line", [[0, 0, 1], [1, 1, 2]]))
    for ext in ("dxf", "geojson", "csv"):
        assert s.export(tmp_path / f"out.{ext}").stat().st_size > 0
    with pytest.raises(SoftplotError, match="unknown export format"):
        s.export(tmp_path / "out.shp")
    s.close()


WRITER = textwrap.dedent(
    """
    import sys
    from softplot.export.features import Feature
    from softplot.pipeline.session import Session
    from softplot.stereo import OrientedPhoto, StereoModel
    model = StereoModel(OrientedPhoto([0, 0, 1000], [0, 0, 0], 150),
                        OrientedPhoto([400, 0, 1000], [0, 0, 0], 150))
    s = Session.create(sys.argv[1], model)
    i = 0
    while True:
        s.record(Feature("SPOT", "point", [float(i), 2.0 * i, 100.0 + i],
                         {"pad": "x" * (i % 300)}))
        print(i, flush=True)
        i += 1
    """
)


def test_journal_survives_kill_9(tmp_path):
    folder = tmp_path / "killed"
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(folder)], stdout=subprocess.PIPE, text=True
    )
    last = -1
    try:
        for line in proc.stdout:
            last = int(line)
            if last >= 150:
                break
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    assert proc.returncode == -signal.SIGKILL
    assert last >= 150
    s = Session.resume(folder)
    n = len(s.features)
    # every record whose call returned (and was printed) is there, in order
    assert n >= last + 1
    for i, f in enumerate(s.features):
        assert f.vertices.tolist() == [[float(i), 2.0 * i, 100.0 + i]]
    lines = (folder / "journal.jsonl").read_bytes().splitlines()
    assert all(json.loads(ln) for ln in lines)
    s.close()
