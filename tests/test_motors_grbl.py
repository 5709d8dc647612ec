"""GrblMotors against the simulated GRBL 1.1 controller on a real pty (pyserial end to end)."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from softplot.motors import (
    AxisConfig,
    LostSteps,
    MotorAlarm,
    MotorCommandError,
    MotorDisconnected,
    MotorError,
    MotorFault,
    MotorLimitError,
    MotorPositionLost,
    MotorTimeout,
)
from softplot.motors.grbl import GrblMotors, parse_status
from softplot.motors.simulator import GrblSimulator, parse_faults


@pytest.fixture
def sim():
    s = GrblSimulator(time_scale=20)
    s.start()
    yield s
    s.stop()


# --------------------------------------------------------------------------- parsing
def test_parse_status_variants():
    st = parse_status("<Idle|MPos:1.500,-2.250,0.000|FS:0,0|WCO:1.000,1.000,0.000>")
    assert st.state == "Idle" and st.mpos == (1.5, -2.25, 0.0)
    assert st.wpos == (0.5, -3.25, 0.0) and not st.moving
    st = parse_status("<Run|WPos:0.500,0.000,0.000|Bf:15,128|FS:169,0>", last_wco=(1.0, 2.0, 0.0))
    assert st.mpos == (1.5, 2.0, 0.0) and st.buffer == (15, 128) and st.feed == 169 and st.moving
    st = parse_status("<Hold:1|MPos:0.000,0.000,0.000|Pn:XZ|Ov:100,100,100>")
    assert st.state == "Hold" and st.substate == 1 and st.moving and st.pins == "XZ"
    assert parse_status("<Jog|MPos:1,2,3|F:500>").feed == 500
    with pytest.raises(MotorError, match="not a GRBL status"):
        parse_status("ok")
    with pytest.raises(MotorError, match="without a position"):
        parse_status("<Idle|FS:0,0>")
    with pytest.raises(MotorError, match="bad field"):
        parse_status("<Idle|MPos:1,a,3>")


def test_fault_spec_parsing():
    plan = parse_faults("slow=0.2, alarm@move3,lost-steps=5@move2,disconnect@1.5s")
    kinds = [(f.kind, f.value, f.at_move, f.at_time) for f in plan.faults]
    assert kinds == [
        ("slow", 0.2, None, None),
        ("alarm", 0.0, 3, None),
        ("lost-steps", 5.0, 2, None),
        ("disconnect", 0.0, None, 1.5),
    ]
    assert plan.slow == 0.2
    for bad in ("bogus", "alarm", "slow", "lost-steps=2"):
        with pytest.raises(MotorError):
            parse_faults(bad)


# --------------------------------------------------------------------------- normal use
def test_connect_move_home_and_position():
    sim = GrblSimulator(time_scale=20, settings={22: 1})  # homing on: locked at power-up
    with sim, GrblMotors(sim.path, timeout=2) as m:
        assert m.status().state == "Alarm" and "$X" not in sim.log  # never unlocked for us
        with pytest.raises(MotorPositionLost, match="home the axes or confirm"):
            m.move_to(1.0, 1.0)
        m.home()  # $H, work offset so that the homed position is plate (0, 0)
        assert m.position() == (0.0, 0.0)
        assert m.status().mpos[:2] == pytest.approx((-1.0, -1.0))  # pull-off
        assert m.status().wco[:2] == pytest.approx((-1.0, -1.0))
        m.move_to(1.23, -2.5)
        assert m.position() == pytest.approx((1.23, -2.5))
        assert sim.pos[:2] == pytest.approx([0.23, -3.5])
        m.move_to(0.5, 0.5, wait=False)
        assert m.wait(timeout=5)
        assert m.position() == pytest.approx((0.5, 0.5))
        m.move_to(2.0, 3.0)
        assert sim.pos[:2] == pytest.approx([1.0, 2.0])
        assert m.position() == pytest.approx((2.0, 3.0))
        assert "$X" not in sim.log


def test_wpos_reports_and_remembered_wco():
    with GrblSimulator(time_scale=20, settings={10: 0}) as s, GrblMotors(s.path) as m:
        m.command("G10L20P1X0Y0")  # here is (0, 0)
        m.move_to(-1.0, 4.0)
        st = m.status()
        assert "WPos" in st.fields and "MPos" not in st.fields
        assert m.position() == pytest.approx((-1.0, 4.0))
        for _ in range(12):  # most reports carry no WCO: the remembered one is used
            assert m.position() == pytest.approx((-1.0, 4.0))


def test_configures_steps_per_mm_and_rate():
    ax = AxisConfig(resolution_mm=0.005, max_speed_mm_s=5.0)
    with GrblSimulator(time_scale=20) as s, GrblMotors(s.path, ax, ax) as m:
        assert s.settings[100] == 200.0 and s.settings[111] == 300.0
        m.move_to(0.125, 0.0)
        assert m.position_steps() == (25, 0)


@pytest.mark.parametrize("streaming", ["char-count", "send-response"])
def test_streaming_many_moves(sim, streaming):
    with GrblMotors(sim.path, streaming=streaming, timeout=5) as m:
        targets = [(0.01 * i, -0.02 * i) for i in range(1, 41)]
        for tx, ty in targets:
            m.move_to(tx, ty, wait=False)
        assert m.wait(timeout=20)
        assert m.position() == pytest.approx(targets[-1])
        moves = [ln for ln in sim.log if ln.startswith("G90G1")]
        assert len(moves) == 40  # nothing lost or mangled in the 128-byte buffer


def test_stale_power_up_banner_keeps_replies_in_step(sim):
    """The power-up banner still in the line when the port opens: soft_reset takes it for the
    reset's, writes ``$I``, then the reset's own banner arrives. The controller answers that
    ``$I`` (it read the 0x18 first); were it sent again, every later ``ok`` would be taken for
    the line before it and char-count streaming would overfill the 128-byte buffer."""
    from softplot.motors.simulator import BANNER

    reset, line = sim._reset, sim._line
    seen = {"reset": 0, "$I": 0}

    def late_reset():
        if not seen["reset"]:
            os.write(sim.master, f"\r\n{BANNER}\r\n".encode())  # the stale power-up banner
            time.sleep(0.05)  # the host writes $I meanwhile
        seen["reset"] += 1
        reset()

    def slow_first_info(text):
        if text.strip().upper() == "$I" and not seen["$I"]:
            seen["$I"] += 1
            time.sleep(0.1)  # answered after the host had time to send $I again
        return line(text)

    t_end = time.monotonic() + 2
    while sim._out and time.monotonic() < t_end:
        time.sleep(0.01)  # the simulator's own power-up banner: in the pty, flushed at open
    time.sleep(0.05)
    sim._reset, sim._line = late_reset, slow_first_info
    with GrblMotors(sim.path, timeout=5, reset=True) as m:
        assert seen == {"reset": 1, "$I": 1}
        assert any(ln.startswith("[VER:") for ln in m.command("$I"))
        assert any(ln.startswith("[GC:") for ln in m.command("$G")) and not m._inflight
        targets = [(0.01 * i, -0.02 * i) for i in range(1, 41)]
        for tx, ty in targets:
            m.move_to(tx, ty, wait=False)
        assert m.wait(timeout=20)
        assert m.position() == pytest.approx(targets[-1])
    assert sum(ln.startswith("G90G1") for ln in sim.log) == 40
    assert sum(ln.strip().upper() == "$I" for ln in sim.log) == 2  # handshake + the check


@pytest.mark.parametrize("lost", [1, 9])
def test_handshake_resends_a_lost_info_line_once(sim, lost):
    """A ``$I`` the controller never answers (lost while it boots) is sent again once after
    the timeout; a controller that answers neither fails the connect with a timeout."""
    line, seen = sim._line, {"n": 0}

    def lossy(text):
        if text.strip().upper() == "$I" and seen["n"] < lost:
            seen["n"] += 1
            return None  # no answer at all
        return line(text)

    sim._line = lossy
    if lost == 1:
        with GrblMotors(sim.path, timeout=0.5) as m:
            assert any(ln.startswith("[VER:") for ln in m.command("$I")) and not m._inflight
        assert sum(ln.strip().upper() == "$I" for ln in sim.log) == 3
    else:
        with pytest.raises(MotorTimeout, match=r"\$I"):
            GrblMotors(sim.path, timeout=0.5)
        assert sum(ln.strip().upper() == "$I" for ln in sim.log) == 2  # sent twice, not 4x


def test_a_line_cut_by_the_read_timeout_is_joined(sim):
    """pyserial's readline returns what it has when its 0.05 s timeout runs out; the two
    halves of a slow line are one line (an ``ok`` cut in two would be lost)."""
    with GrblMotors(sim.path, timeout=5) as m:
        os.write(sim.master, b"[MSG:cut ")
        time.sleep(0.2)
        os.write(sim.master, b"in two]\r\n")
        t_end = time.monotonic() + 2
        while "[MSG:cut in two]" not in m.messages and time.monotonic() < t_end:
            time.sleep(0.01)
        assert "[MSG:cut in two]" in m.messages
        assert not any(ln.startswith("[MSG:cut") and ln != "[MSG:cut in two]" for ln in m.messages)


def test_error_codes_become_one_line_errors(sim):
    with GrblMotors(sim.path) as m:
        with pytest.raises(MotorCommandError, match=r"error:20 \(unsupported command\)") as e:
            m.command("G0Q1")
        assert e.value.code == 20
        with pytest.raises(MotorCommandError, match="error:22"):
            m.command("G1X1")  # feed rate undefined after reset
        with pytest.raises(MotorCommandError, match="error:2"):
            m.command("foo")
        m.move_to(0.1, 0.1)  # still usable


def test_stop_during_a_long_move(sim):
    ax = AxisConfig(max_speed_mm_s=1.0)
    with GrblMotors(sim.path, ax, ax) as m:
        m.move_to(15.0, 0.0, wait=False)  # 15 s at 1 mm/s, 0.75 s simulated
        time.sleep(0.1)
        m.stop()
        assert m.status().state == "Idle"
        dx, _ = m.position()
        assert 0.0 < dx < 15.0
        assert m.target()[0] == pytest.approx(dx)
        m.move_to(0.0, 0.0)  # no alarm after a completed feed hold
        assert m.position() == (0.0, 0.0)


def test_soft_limit_alarm_needs_a_reset():
    with GrblSimulator(time_scale=20, settings={20: 1, 22: 1}) as s:
        ax = AxisConfig(min_mm=-100, max_mm=100)
        with GrblMotors(s.path, ax, ax, timeout=0.5, unlock=True) as m:
            m.home()
            with pytest.raises(MotorLimitError, match=r"machine 4.000 mm.*\[-200, 0\]"):
                m.move_to(5.0, 0.0)  # machine travel is [-200, 0]: refused before sending
            with pytest.raises(MotorAlarm, match="ALARM:2"):
                m.command("G90G0X5")  # sent anyway: the controller's critical alarm
            with pytest.raises(MotorAlarm, match="ALARM:2"):
                m.status()  # nothing answered, not even '?'
            m.recover()  # reset; the soft limit kept the position, so $X (unlock=True)
            assert any(ln.startswith("[GC:") for ln in m.command("$G"))  # the late ok absorbed
            m.move_to(-1.0, -1.0)
            assert m.position() == pytest.approx((-1.0, -1.0))


# --------------------------------------------------------------------------- injected faults
def test_fault_alarm_during_move(sim):
    with GrblMotors(sim.path, timeout=1) as m:
        m.move_to(1.0, 1.0)
        sim.inject("alarm@move1")
        with pytest.raises(MotorAlarm, match=r"ALARM:1 \(hard limit"):
            m.move_to(3.0, 3.0)
        with pytest.raises(MotorAlarm):
            m.move_to(0.0, 0.0)  # the fault sticks until recovered
        m.recover()
        with pytest.raises(MotorPositionLost):
            m.move_to(0.0, 0.0)  # a hard limit loses the position: home or confirm
        m.confirm_position()
        assert m.position() == pytest.approx((2.0, 2.0))  # where the alarm stopped it
        m.move_to(0.0, 0.0)
        assert m.position() == (0.0, 0.0)


def test_fault_lost_steps_detected_by_encoders(sim):
    with GrblMotors(sim.path) as m:  # a stock controller has no encoder read-out
        with pytest.raises(MotorError, match=r"no encoder read-out \(\$ENC answered error:2\)"):
            m.verify_encoders()
    sim.stop()
    sim = GrblSimulator(time_scale=20, encoders=True)  # an instrument with encoders
    with sim, GrblMotors(sim.path, check_encoders=True) as m:
        m.move_to(1.0, 0.0)
        assert m.verify_encoders() == pytest.approx((1.0, 0.0))
        sim.inject("lost-steps=5@move1")
        with pytest.raises(LostSteps, match=r"lost steps on DX.*-5 steps"):
            m.move_to(2.0, 0.0)
        assert sim.physical_position()[0] == pytest.approx(1.95)
    with GrblSimulator(time_scale=20, faults="lost-steps=3@move1") as s:
        with GrblMotors(s.path) as m:  # without encoder checks the loss goes unnoticed
            m.move_to(1.0, 0.0)
            assert m.position() == pytest.approx((1.0, 0.0))
            assert s.physical_position()[0] == pytest.approx(0.97)


def test_fault_slow_replies():
    with GrblSimulator(time_scale=20, faults="slow=0.3") as s:
        with pytest.raises(MotorTimeout, match="within 0.1 s"):
            GrblMotors(s.path, timeout=0.1)
        with GrblMotors(s.path, timeout=2) as m:
            t0 = time.monotonic()
            m.command("$G")
            assert time.monotonic() - t0 >= 0.29
            m.move_to(0.2, 0.1)
            assert m.position() == pytest.approx((0.2, 0.1))
            time.sleep(0.6)  # the answers to earlier status queries arrive meanwhile
            m.timeout = 0.1
            with pytest.raises(MotorTimeout, match="within 0.1 s"):
                m.status()


def test_fault_disconnect_and_reconnect(tmp_path):
    link = str(tmp_path / "ttyGRBL")
    with GrblSimulator(time_scale=20, link=link, reconnect_after=0.3) as s:
        with GrblMotors(link, timeout=1) as m:
            m.move_to(1.0, 1.0)
            first = s.slave_path
            s.inject("disconnect@move1")
            with pytest.raises(MotorDisconnected, match="lost"):
                m.move_to(2.0, 2.0)
                m.move_to(2.5, 2.5)
            with pytest.raises(MotorDisconnected):
                m.position()
            m.reconnect(timeout=5)
            assert os.path.realpath(link) == s.slave_path
            assert s.slave_path is not None and first is not None
            m.move_to(0.5, 0.5)
            assert m.position() == pytest.approx((0.5, 0.5))


def test_unreachable_port():
    with pytest.raises(MotorDisconnected, match="cannot open serial port"):
        GrblMotors("/nonexistent/ttyX", timeout=0.2)


# --------------------------------------------------------------------------- the CLI
def test_cli_simulate_serves_a_pty():
    exe = [sys.executable, "-m", "softplot.cli.__init__"]
    exe = [sys.executable, "-c", "from softplot.cli import main; main()"]
    proc = subprocess.Popen(
        exe + ["motors", "simulate", "--duration", "20", "--time-scale", "20"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        path = proc.stdout.readline().strip()
        assert path.startswith("/dev/")
        with GrblMotors(path, timeout=2) as m:
            m.move_to(0.3, -0.4)
            assert m.position() == pytest.approx((0.3, -0.4))
        out = subprocess.run(
            exe + ["motors", "status", path], capture_output=True, text=True, timeout=30
        )
        assert out.returncode == 0 and "DX=0.300 DY=-0.400" in out.stdout
        bad = subprocess.run(
            exe + ["motors", "status", "/nonexistent/tty"],
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert bad.returncode == 2 and bad.stderr.count("\n") == 1
        assert "cannot open serial port" in bad.stderr and "Traceback" not in bad.stderr
    finally:
        proc.terminate()
        proc.wait(timeout=10)


def test_one_driver_per_controller(sim):
    with GrblMotors(sim.path) as m:
        with pytest.raises(MotorDisconnected, match="cannot open serial port"):
            GrblMotors(sim.path, timeout=0.5)
        m.move_to(0.1, 0.0)  # the first driver is undisturbed
        assert m.position() == pytest.approx((0.1, 0.0))


def test_streamed_motion_line_rejected_becomes_a_fault(sim):
    with GrblMotors(sim.path, timeout=2) as m:
        m.command("$J=G91X5F60")  # a long jog: G-code is locked out meanwhile (error:9)
        m.move_to(0.2, 0.2, wait=False)  # char-count: returns before the reply
        with pytest.raises(MotorFault, match=r"motion line rejected.*error:9"):
            m.wait(timeout=2)
        with pytest.raises(MotorFault):
            m.move_to(0.3, 0.3)  # the fault sticks
        m.realtime(b"\x85")  # jog cancel
        m.recover()
        m.move_to(0.3, 0.3)
        assert m.position() == pytest.approx((0.3, 0.3))
