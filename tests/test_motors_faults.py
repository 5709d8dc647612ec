"""GrblMotors and ``softplot plot trace`` against the strict simulator's faults: reboots,
power loss, reading without resetting, confirmed points, feed holds, alarms and resets,
limits in machine coordinates, jog stops, failed homing, disconnects (one test per point)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from softplot.motors import AxisConfig, MotorAlarm, MotorFault, MotorPositionLost
from softplot.motors.grbl import GrblMotors
from softplot.motors.simulator import GrblSimulator
from softplot.pipeline.session import Session
from test_session_cli import _ops, _run, job  # noqa: F401 - the CLI helpers and fixture

SPOTS = np.array([[450.0, 0.0, 300.0], [460.0, 5.0, 301.0], [440.0, -8.0, 299.0]])


def _session(job, name, capsys):  # noqa: F811 - job is the imported fixture's value
    folder = str(job / name)
    new = ["plot", "new", folder, "--photos", str(job / "photos.csv"), "--left-offset", "98", "0"]
    assert _run(new, capsys)[0] == 0
    return folder, _ops(job / f"{name}.csv", SPOTS, with_px=True, offset=98.0)


def _trace(folder, ops, port, capsys, *extra):
    return _run(
        ["plot", "trace", folder, "--input", str(ops), "--code", "SPOT", "--port", port, *extra],
        capsys,
    )


# ------------------------------------------------------------------ 1. a reboot is a fault
def test_reboot_mid_stream_stops_and_refuses_motion():
    with GrblSimulator(time_scale=20) as sim, GrblMotors(sim.path, timeout=1) as m:
        m.move_to(1.0, 1.0)
        sim.inject("reboot@move2")
        targets = [(1.0 + 0.3 * i, 1.0 + 0.2 * i) for i in range(1, 11)]
        with pytest.raises(MotorPositionLost, match="restarted by itself"):
            for t in targets:
                m.move_to(*t, wait=False)
            m.wait(5)
        time.sleep(0.5)
        # the stream did not run on in the rebooted controller (it would end on the last
        # target, in a frame shifted by the lost machine position): the driver reset it
        assert np.abs(np.subtract(sim.physical_position(), targets[-1])).max() > 0.5
        assert not sim.moving
        with pytest.raises(MotorPositionLost):
            m.move_to(0.0, 0.0)  # refused until re-referenced
        m.confirm_position()
        m.move_to(0.5, 0.5)
        assert m.position() == pytest.approx((0.5, 0.5))


def test_reboot_during_trace_is_journaled(job, capsys):  # noqa: F811
    folder, ops = _session(job, "r", capsys)
    with GrblSimulator(time_scale=20, faults="reboot@move2") as sim:
        code, out, err = _trace(folder, ops, sim.path, capsys)
    assert code == 2 and "restarted by itself" in err and err.count("\n") == 1
    s = Session.resume(folder)
    try:
        assert len(s.faults) == 1 and "restarted by itself" in s.faults[0]
        assert len(s.features) == 1  # the point before the reboot only
    finally:
        s.close()


# ------------------------------------------------------------------ 2. power loss and resume
def test_power_loss_then_reconnect_needs_homing(tmp_path):
    link = str(tmp_path / "ttyGRBL")
    sim = GrblSimulator(time_scale=20, link=link, settings={22: 1}, reconnect_after=0.2)
    with sim, GrblMotors(link, timeout=1, unlock=True) as m:
        m.home()
        m.move_to(2.43, 1.0)
        sim.inject("power-loss@0s")
        time.sleep(0.1)
        with pytest.raises(MotorPositionLost, match="came back at machine position 0.000,0.000"):
            m.reconnect(timeout=5)
        with pytest.raises(MotorPositionLost):
            m.move_to(0.0, 0.0)
        assert "$X" not in sim.log  # the alarm lock is left to the operator
        m.home()
        m.move_to(2.43, 1.0)  # in the homed frame: machine 1.43, 0.0 (pull-off 1 mm)
        assert sim.physical_position() == pytest.approx((1.43, 0.0))


def test_resume_after_a_reboot_is_refused_until_confirmed(job, capsys):  # noqa: F811
    folder, ops = _session(job, "p", capsys)
    with GrblSimulator(time_scale=20) as sim:
        code, out, err = _trace(folder, ops, sim.path, capsys)
        assert code == 0, err
        code, out, err = _trace(folder, ops, sim.path, capsys)  # same controller: resumes
        assert code == 0, err
        sim.reboot()  # power blip between two runs: machine position back to 0
        time.sleep(0.1)
        code, out, err = _trace(folder, ops, sim.path, capsys)
        assert code == 2 and "not where the session left it" in err and err.count("\n") == 1
        assert "$X" not in sim.log
        s = Session.resume(folder)
        assert len(s.features) == 6 and "not where the session left it" in s.faults[-1]
        s.close()
        code, out, err = _trace(folder, ops, sim.path, capsys, "--confirm-position")
        assert code == 0, err  # the operator vouched for the position


# ------------------------------------------------------------------ 3. reading is not writing
def test_status_does_not_reset_a_moving_controller(capsys):
    with GrblSimulator(time_scale=2) as sim:
        m = GrblMotors(sim.path, timeout=1)
        m.move_to(-3.0, 0.0, wait=False)
        m.wait(0.05)
        m.close()  # the move goes on in the controller
        code, out, err = _run(["motors", "status", sim.path], capsys)
        assert code == 0 and out.startswith("Run "), err
        t_end = time.monotonic() + 5
        while sim.moving and time.monotonic() < t_end:
            time.sleep(0.02)
        assert sim.pos[0] == -3.0 and sim.state == "Idle"  # not aborted (no ALARM:3)


# ------------------------------------------------------------------ 4. completion is checked
def test_trace_records_a_point_only_when_the_carriage_is_on_it(job, capsys):  # noqa: F811
    folder, ops = _session(job, "t", capsys)
    with GrblSimulator(time_scale=0.5) as sim:  # a controller at half clock
        code, out, err = _trace(folder, ops, sim.path, capsys, "--timeout", "0.05")
    assert code == 2 and "did not reach v0 within 0.05 s" in err and err.count("\n") == 1
    s = Session.resume(folder)
    try:
        assert len(s.features) == 0 and len(s.faults) == 1
        assert "did not reach v0" in s.faults[0]
    finally:
        s.close()


# ------------------------------------------------------------------ 5. feed hold
def test_stream_pauses_during_a_feed_hold():
    with GrblSimulator(time_scale=20) as sim, GrblMotors(sim.path, timeout=0.5) as m:
        targets = [(0.05 * i, -0.05 * i) for i in range(1, 41)]
        seen = {}

        def operator():
            time.sleep(0.05)
            m.realtime(b"!")
            time.sleep(1.5)  # three times the driver's timeout
            seen["busy"] = m.busy
            m.realtime(b"~")

        t = threading.Thread(target=operator)
        t.start()
        for tx, ty in targets:
            m.move_to(tx, ty, wait=False)
        t.join()
        assert seen["busy"] is True
        assert m.wait(10)
        assert m.position() == pytest.approx(targets[-1])
        assert sum(ln.startswith("G90G1") for ln in sim.log) == 40


def test_busy_while_held_with_motion_pending():
    ax = AxisConfig(min_mm=-100, max_mm=100)
    with GrblSimulator(time_scale=20) as sim, GrblMotors(sim.path, ax, ax, timeout=0.5) as m:
        m.move_to(-50.0, 0.0, wait=False)
        m.wait(0.05)
        m.realtime(b"!")
        time.sleep(0.2)
        assert m.status().state == "Hold" and m.status().substate == 0
        assert m.busy and not m.wait(0.3)
        m.realtime(b"~")
        assert m.wait(5) and m.position() == pytest.approx((-50.0, 0.0))
        assert sim.pos[0] == -50.0


# ------------------------------------------------------------------ 6. alarms and resets
def test_reset_while_moving_reports_alarm3_and_replies_stay_in_step():
    with GrblSimulator(time_scale=20) as sim, GrblMotors(sim.path, timeout=0.3) as m:
        m.move_to(-15.0, 0.0, wait=False)
        m.wait(0.05)
        m.realtime(b"\x18")  # a reset from outside while moving
        with pytest.raises(MotorAlarm, match=r"ALARM:3 \(reset while in motion"):
            m.wait(5)
        assert m.status().state == "Alarm"
        assert isinstance(m.fault, MotorAlarm) and m.fault.code == 3  # the first cause kept
        m.recover()
        assert any(ln.startswith("[GC:") for ln in m.command("$G"))
        with pytest.raises(MotorPositionLost):
            m.move_to(0.0, 0.0)
        assert sim.state == "Alarm"  # ALARM:3 locked it; nothing unlocked it for us


def test_status_is_retried_across_the_alarm_pause_and_the_reset():
    """At real speed: ALARM:3, 0.5 s of silence, the reset drops the pending '?': the status
    read asks again and gets the report."""
    with GrblSimulator(time_scale=1) as sim, GrblMotors(sim.path, timeout=2) as m:
        m.move_to(-15.0, 0.0, wait=False)
        m.wait(0.3)
        m.realtime(b"\x18")
        time.sleep(0.05)
        assert m.status().state == "Alarm"
        assert isinstance(m.fault, MotorAlarm) and m.fault.code == 3
        assert sim.state == "Alarm"


# ------------------------------------------------------------------ 7. limits, jog stop, homing
def test_stop_during_a_jog_waits_for_the_deceleration():
    with GrblSimulator(time_scale=20) as sim, GrblMotors(sim.path, timeout=1) as m:
        m.command("$J=G91X-100F500")
        time.sleep(0.1)  # 2 s controller time: cruising at 8.3 mm/s
        m.stop()
        pos = m.position()
        assert m.target() == pytest.approx(pos) and m.status().state == "Idle"
        time.sleep(0.1)
        assert sim.pos[:2] == pytest.approx(list(pos))  # it stopped where the driver says
        assert -100.0 < pos[0] < -5.0


@pytest.mark.parametrize("code", [8, 9])
def test_failed_homing_is_one_fault(code):
    sim = GrblSimulator(time_scale=20, settings={22: 1}, faults=f"homing-fail={code}")
    with sim, GrblMotors(sim.path, timeout=1) as m:
        with pytest.raises(MotorAlarm, match=rf"homing failed.*ALARM:{code}") as e:
            m.home()
        assert str(e.value).count("ALARM") == 1
        assert any(ln.startswith("[GC:") for ln in m.command("$G"))  # late ok absorbed
        with pytest.raises(MotorFault):
            m.move_to(1.0, 1.0)
        m.home()
        m.move_to(1.0, 1.0)
        assert m.position() == pytest.approx((1.0, 1.0))


# ------------------------------------------------------------------ 9. disconnect at the end
def test_disconnect_while_waiting_is_journaled_once(job, capsys):  # noqa: F811
    folder, ops = _session(job, "d", capsys)
    with GrblSimulator(time_scale=20, faults="disconnect@move3") as sim:
        code, out, err = _trace(folder, ops, sim.path, capsys)
    assert code == 2 and err.count("\n") == 1
    s = Session.resume(folder)
    try:
        assert len(s.faults) == 1 and len(s.features) == 2
        assert s.faults[0].count("lost") == 1 and "serial line" in s.faults[0]
    finally:
        s.close()
