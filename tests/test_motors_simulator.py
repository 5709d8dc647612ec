"""The simulated GRBL 1.1h controller tells the truth about the firmware (raw bytes on the pty,
no driver in between): defaults, reports, timing, holds, alarms, reboots."""

from __future__ import annotations

import os
import select
import time

import pytest

from softplot.motors.simulator import BANNER, BYTE_TIME, GrblSimulator, _Block

SCALE = 10.0  # controller time runs 10x faster than real time


class Raw:
    """A bare serial client on the simulator's pty: bytes out, ``\\r\\n`` lines in."""

    def __init__(self, sim: GrblSimulator):
        self.sim = sim
        self.fd = os.open(sim.path, os.O_RDWR | os.O_NOCTTY)
        self.buf = b""
        time.sleep(0.05)
        self.drain()

    def close(self):
        os.close(self.fd)

    def send(self, data: bytes | str):
        os.write(self.fd, data.encode() if isinstance(data, str) else data)

    def line(self, timeout: float = 2.0) -> str | None:
        t_end = time.monotonic() + timeout
        while b"\r\n" not in self.buf:
            left = t_end - time.monotonic()
            if left <= 0:
                return None
            r, _, _ = select.select([self.fd], [], [], left)
            if r:
                self.buf += os.read(self.fd, 4096)
        ln, _, self.buf = self.buf.partition(b"\r\n")
        return ln.decode()

    def until(self, pred, timeout: float = 3.0) -> list[str]:
        """Lines up to and including the first that satisfies ``pred`` (non-empty only)."""
        out, t_end = [], time.monotonic() + timeout
        while time.monotonic() < t_end:
            ln = self.line(t_end - time.monotonic())
            if ln is None:
                break
            if ln:
                out.append(ln)
                if pred(ln):
                    return out
        raise AssertionError(f"no matching line; got {out}")

    def cmd(self, line: str, timeout: float = 3.0) -> list[str]:
        self.send(line + "\n")
        return self.until(lambda s: s == "ok" or s.startswith("error:"), timeout)

    def status(self, timeout: float = 1.0) -> str | None:
        self.send(b"?")
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            ln = self.line(t_end - time.monotonic())
            if ln and ln.startswith("<"):
                return ln
        return None

    def drain(self):
        while self.line(0.02) is not None:
            pass


@pytest.fixture
def raw():
    sim = GrblSimulator(time_scale=SCALE)
    sim.start()
    r = Raw(sim)
    yield r
    r.close()
    sim.stop()


def _open(**kw):
    sim = GrblSimulator(time_scale=SCALE, **kw)
    sim.start()
    return sim, Raw(sim)


def test_defaults_info_offsets_startup_lines(raw):
    s = {ln.split("=")[0]: ln.split("=")[1] for ln in raw.cmd("$$") if ln.startswith("$")}
    assert (s["$22"], s["$20"], s["$10"]) == ("0", "0", "1")
    assert float(s["$100"]) == 250 and float(s["$110"]) == 500 and float(s["$120"]) == 10
    assert float(s["$130"]) == 200 and float(s["$27"]) == 1
    assert raw.cmd("$I") == ["[VER:1.1h.20190830:]", "[OPT:V,15,128]", "ok"]  # no vendor
    raw.cmd("G10L2P2X1Y2")
    got = raw.cmd("$#")
    names = [ln[1:].split(":")[0] for ln in got[:-1]]
    assert names == ["G54", "G55", "G56", "G57", "G58", "G59", "G28", "G30", "G92", "TLO", "PRB"]
    assert got[1] == "[G55:1.000,2.000,0.000]"
    assert raw.cmd("$N") == ["$N0=", "$N1=", "ok"]
    assert raw.cmd("$ENC") == ["error:2"]  # no encoder extension on a stock controller
    assert raw.cmd("$H") == ["error:5"]  # homing off by default
    assert raw.cmd("X" * 79 + "1")[-1] == "error:11"  # 80 characters
    assert raw.cmd("G0 X0 " + " " * 90 + "Y0") == ["ok"]  # spaces do not count


def test_encoder_extension_is_opt_in():
    sim, r = _open(encoders=True)
    try:
        assert r.cmd("$ENC") == ["[ENC:0.000,0.000]", "ok"]
    finally:
        r.close()
        sim.stop()


def test_check_mode_and_its_reset(raw):
    assert raw.cmd("$C") == ["[MSG:Enabled]", "ok"]
    assert raw.status().startswith("<Check|")
    assert raw.cmd("G0X-5") == ["ok"]
    assert raw.sim.pos[0] == 0.0  # parsed, not run
    got = raw.cmd("$C")
    assert got == ["[MSG:Disabled]", "ok"]
    assert BANNER in raw.until(lambda s: s.startswith("Grbl"))  # leaving it resets
    assert raw.status().startswith("<Idle|")


def test_acceleration_profile():
    blk = _Block([10.0, 0.0, 0.0], 500.0)  # F600 capped at $110=500 mm/min
    blk.plan([0.0, 0.0, 0.0], 0.0, lambda i: 10.0)
    assert blk.t3 == pytest.approx(2.0333, abs=1e-3)  # not 10 / (500 / 60) = 1.2 s
    assert blk.sv(blk.t3 / 2)[0] == pytest.approx(5.0)
    short = _Block([0.1, 0.0, 0.0], 500.0)
    short.plan([0.0, 0.0, 0.0], 0.0, lambda i: 10.0)
    assert short.t3 == pytest.approx(2 * (0.1 / 10.0) ** 0.5)  # a triangle


def test_a_move_takes_its_accelerated_time(raw):
    raw.cmd("G1F600")
    t0 = raw.sim.now()
    raw.cmd("G1X-10")
    raw.cmd("G4P0")  # answered after the motion
    dt = raw.sim.now() - t0
    assert 2.03 <= dt <= 3.0  # controller seconds; 1.2 s at constant feed
    assert raw.sim.pos[0] == -10.0


def test_feed_hold_decelerates_and_holds_lines(raw):
    raw.cmd("$120=2")  # a gentle ramp: the deceleration lasts long enough to be seen
    raw.cmd("G1F500")
    raw.cmd("G1X-50")
    time.sleep(0.2)  # 2 s controller time: accelerating, 4 mm/s
    raw.send(b"!")
    assert raw.status().startswith("<Hold:1|")  # decelerating (2 s controller time)
    t_end = time.monotonic() + 3.0  # 0.2 s at the simulator's pace; more on a loaded machine
    st = raw.status()
    while not st.startswith("<Hold:0|") and time.monotonic() < t_end:
        time.sleep(0.05)
        st = raw.status()
    assert st.startswith("<Hold:0|") and "FS:0," in st
    raw.send("G1X-1\n$$\n")
    time.sleep(0.2)
    assert raw.line(0.05) is None  # no ok, no settings while held
    raw.send(b"~")
    assert [raw.line(1.0), raw.line(1.0)] == ["ok", "error:8"]  # read now; $$ not while Run


def test_planner_holds_the_sixteenth_ok(raw):
    raw.cmd("G1F100")
    for i in range(20):
        raw.send(f"G1X-{10 * (i + 1)}\n")
    oks = []
    t_end = time.monotonic() + 0.3
    while time.monotonic() < t_end:
        ln = raw.line(0.05)
        if ln == "ok":
            oks.append(ln)
    assert len(oks) == 15  # 15 blocks planned; the rest wait for room


def test_eeprom_writes_wait_for_motion(raw):
    raw.cmd("G1F500")
    raw.cmd("G1X-5")
    t0 = raw.sim.now()
    assert raw.cmd("G10L20P1X0") == ["ok"]
    assert raw.sim.now() - t0 > 1.0 and raw.sim.pos[0] == -5.0
    raw.cmd("G1X-10")
    t0 = raw.sim.now()
    assert raw.cmd("$27=2") == ["ok"]
    assert raw.sim.now() - t0 > 1.0


def test_soft_limit_alarm_pause_late_ok_and_reset():
    sim, r = _open(settings={20: 1, 22: 1})
    try:
        r.cmd("$X")
        r.send("G0X5\n")
        assert r.line(1.0) == "ALARM:2"
        assert r.until(lambda s: s.startswith("[MSG"))[-1] == "[MSG:Reset to continue]"
        # the firmware pauses after every ALARM: timed on the controller's own clock (when
        # each line was emitted), not on when this test got round to reading them
        due = {text: t for t, text in sim.emitted}
        assert due["[MSG:Reset to continue]"] - due["ALARM:2"] >= 0.5
        assert r.status(0.3) is None  # a critical alarm answers nothing
        r.send(b"\x18")
        got = r.until(lambda s: s.startswith("[MSG"))
        assert got == ["ok", BANNER, "[MSG:'$H'|'$X' to unlock]"]  # the late ok first
    finally:
        r.close()
        sim.stop()


def test_reset_while_moving_alarm3_drops_a_pending_status(raw):
    raw.cmd("G1F500")
    raw.cmd("G1X-20")
    time.sleep(0.05)
    raw.send(b"\x18")
    assert raw.line(1.0) == "ALARM:3"
    raw.send(b"?")  # during the pause: dropped by the reset
    got = raw.until(lambda s: s.startswith("[MSG"))
    assert got == [BANNER, "[MSG:'$H'|'$X' to unlock]"]
    assert raw.line(0.2) is None
    assert raw.status().startswith("<Alarm|")


def test_failed_homing_alarm_late_ok_automatic_reset():
    sim, r = _open(settings={22: 1}, faults="homing-fail=9")
    try:
        r.send("$H\n")
        got = r.until(lambda s: s.startswith("[MSG"))
        assert got == ["ALARM:9", "ok", BANNER, "[MSG:'$H'|'$X' to unlock]"]
        assert r.status().startswith("<Alarm|")
        assert r.cmd("$H") == ["ok"]  # the second cycle finds the switches
        assert r.status().startswith("<Idle|MPos:-1.000,-1.000,-1.000")
    finally:
        r.close()
        sim.stop()


def test_reboot_loses_machine_position_keeps_eeprom(raw):
    raw.cmd("G10L20P1X0Y0")
    raw.cmd("G1F500X-2Y-3")
    raw.cmd("G10L20P1X0Y0")  # work zero at machine -2, -3 (EEPROM)
    raw.sim.reboot()
    assert raw.until(lambda s: s.startswith("Grbl")) == [BANNER]  # nobody asked
    st = raw.status()
    assert "MPos:0.000,0.000,0.000" in st and "WCO:-2.000,-3.000,0.000" in st
    assert raw.sim.physical_position() == (-2.0, -3.0)  # the carriage did not move


def test_hard_limit_pin_and_bytes_at_baud_rate(raw):
    t0 = raw.sim.now()
    got = raw.cmd("$$")
    nbytes = sum(len(ln) + 2 for ln in got)
    assert raw.sim.now() - t0 >= nbytes * BYTE_TIME  # 115200 baud, 10 bits a byte
    raw.sim.inject("alarm@move1")
    raw.cmd("G1F500X-5")
    assert raw.line(1.0) == "ALARM:1"
    raw.until(lambda s: s == "[MSG:Reset to continue]")
    raw.send(b"\x18")
    raw.until(lambda s: s.startswith("[MSG"))
    assert "|Pn:X" in raw.status()  # the limit switch is still pressed
