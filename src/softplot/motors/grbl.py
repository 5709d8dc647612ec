"""GRBL 1.1 backend: the DX, DY stepper axes of a physical instrument on a serial line.

DX is GRBL's X axis, DY its Y axis (Z unused). The driver works in GRBL *work* coordinates
(G54): work mm = motor position in plate mm (backlash compensation is done above, in
:class:`~softplot.motors.base.Motors`). Protocol facts: GRBL 1.1 (docs/motors.md);
design and fault handling: ``docs/motors.md``.

* A reader thread owns the receive side: ``ok`` / ``error:N`` complete the oldest line in
  flight, ``<...>`` status reports are parsed (:func:`parse_status`; ``WPos`` or ``MPos``
  with the last ``WCO`` remembered), ``ALARM:N``, the banner, ``[MSG:..]`` and other push
  messages are recorded. A lost line (SerialException / EOF) fails every waiter with
  :class:`MotorDisconnected`.
* Streaming: ``"char-count"`` (default; at most 127 bytes in flight, each ``ok``/``error``
  frees the oldest line) or ``"send-response"``; EEPROM writes (``$n=``, ``G10``) always go
  send-response.
* Connect: open the port, drop stale input, ask ``?``: a controller that answers is not
  reset (reading is not writing); one that does not (booting, or in a critical alarm) is
  soft-reset (0x18) and its banner awaited. At rest: ``$I`` (1.1 required), ``$$``, and
  ``$100/$101`` (steps/mm), ``$110/$111`` (mm/min) written when they differ. ``$X`` is
  never sent on the user's behalf after a reset or a power cycle.
* Resets: no line is written between a 0x18 and its banner; a banner discards the lines
  written before the reset, and a line that already failed (a critical alarm) absorbs its
  late answer, so no ``ok``/``error`` is matched to the wrong line. A banner nobody asked
  for is a reboot: a fault, the position is lost, the controller is reset again so that
  nothing that reached it runs.
* Position validity: lost on a reboot, a power cycle (a machine position that is not the
  one saved or last seen), an alarm that may lose steps; motion is then refused
  (:class:`~softplot.motors.base.MotorPositionLost`) until :meth:`GrblMotors.home` or
  :meth:`GrblMotors.confirm_position`.
* Faults become :class:`MotorFault` subclasses with one-line messages, the first cause
  kept: ``MotorAlarm`` (``ALARM:N``; a critical alarm needs :meth:`GrblMotors.recover`),
  ``MotorTimeout`` (no answer in time from a controller at rest), ``MotorDisconnected``
  (use :meth:`GrblMotors.reconnect`), ``MotorPositionLost``, ``LostSteps`` (the
  instrument's carriage encoders, read with the optional ``$ENC`` extension when
  ``check_encoders``, disagree with the controller by a step or more).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field

import serial

from softplot.motors.base import (
    AxisConfig,
    LostSteps,
    MotorAlarm,
    MotorCommandError,
    MotorDisconnected,
    MotorError,
    MotorFault,
    MotorLimitError,
    MotorPositionLost,
    Motors,
    MotorTimeout,
)

__all__ = ["GrblMotors", "GrblStatus", "parse_status", "ERROR_CODES", "ALARM_CODES"]

RX_BUFFER = 128

#: GRBL 1.1 error codes (doc/csv/error_codes_en_US.csv), the ones a plotter meets
ERROR_CODES = {
    1: "letter not found",
    2: "bad or missing number",
    3: "'$' command not recognised",
    4: "negative value",
    5: "homing not enabled",
    7: "EEPROM read failed",
    8: "'$' only when idle",
    9: "G-code locked out during alarm or jog",
    10: "soft limits need homing",
    11: "line too long",
    15: "jog target exceeds machine travel",
    16: "invalid jog command",
    20: "unsupported command",
    22: "feed rate undefined",
    24: "two commands need axis words",
    25: "repeated g-code word",
    26: "no axis words",
    33: "invalid target",
}
#: GRBL 1.1 alarm codes
ALARM_CODES = {
    1: "hard limit triggered, position likely lost",
    2: "soft limit: target exceeds travel",
    3: "reset while in motion, position may be lost",
    4: "probe fail",
    5: "probe fail",
    6: "reset during homing",
    7: "door opened during homing",
    8: "homing pull-off failed",
    9: "homing switch not found",
}


@dataclass
class GrblStatus:
    """A parsed ``<...>`` status report (machine mm; ``wco`` is the last one known)."""

    state: str
    substate: int | None = None
    mpos: tuple[float, float, float] | None = None
    wpos: tuple[float, float, float] | None = None
    wco: tuple[float, float, float] | None = None
    buffer: tuple[int, int] | None = None
    feed: float | None = None
    spindle: float | None = None
    pins: str = ""
    overrides: tuple[int, ...] | None = None
    fields: dict = field(default_factory=dict)
    raw: str = ""

    @property
    def moving(self) -> bool:
        return self.state in ("Run", "Jog", "Home") or (self.state == "Hold" and self.substate == 1)


def _vec(text: str) -> tuple[float, ...]:
    return tuple(float(v) for v in text.split(","))


def parse_status(line: str, last_wco=None) -> GrblStatus:
    """Parse a GRBL 1.1 status report ``<State|MPos:x,y,z|...>``.

    Both position flavours are filled in: ``WPos = MPos - WCO`` with the report's own
    ``WCO`` or, when absent, ``last_wco`` (clients must remember it; zero if never seen).
    Fields may come in any order and any of them may be missing but the state.

    Raises
    ------
    MotorError
        If ``line`` is not a status report.
    """
    line = line.strip()
    if not (line.startswith("<") and line.endswith(">")):
        raise MotorError(f"not a GRBL status report: {line!r}")
    parts = line[1:-1].split("|")
    state, _, sub = parts[0].partition(":")
    st = GrblStatus(state=state, substate=int(sub) if sub else None, raw=line)
    for p in parts[1:]:
        key, _, val = p.partition(":")
        st.fields[key] = val
        try:
            if key == "MPos":
                st.mpos = _vec(val)
            elif key == "WPos":
                st.wpos = _vec(val)
            elif key == "WCO":
                st.wco = _vec(val)
            elif key in ("Bf", "Buf"):
                st.buffer = tuple(int(v) for v in val.split(","))
            elif key == "FS":
                st.feed, st.spindle = _vec(val)[:2]
            elif key == "F":
                st.feed = float(val)
            elif key == "Pn":
                st.pins = val
            elif key == "Ov":
                st.overrides = tuple(int(v) for v in val.split(","))
        except ValueError as exc:
            raise MotorError(f"bad field {p!r} in GRBL status {line!r}") from exc
    if st.mpos is None and st.wpos is None:
        raise MotorError(f"GRBL status without a position: {line!r}")
    wco = (
        st.wco if st.wco is not None else (tuple(last_wco) if last_wco is not None else (0.0,) * 3)
    )
    if st.wco is None:
        st.wco = wco
    if st.mpos is None:
        st.mpos = tuple(w + o for w, o in zip(st.wpos, wco, strict=True))
    if st.wpos is None:
        st.wpos = tuple(m - o for m, o in zip(st.mpos, wco, strict=True))
    return st


class _Discarded(MotorFault):
    """A line in flight was thrown away by a controller reset (the banner came first)."""


class _Pending:
    """A line written to the controller and its answer to come.

    ``epoch``: how many soft resets (0x18) had been written before the line. A banner
    discards the lines written before the latest reset (the firmware flushed them); a line
    written after it is answered after the banner.
    """

    __slots__ = ("line", "nbytes", "done", "reply", "info", "epoch")

    def __init__(self, line: str, epoch: int):
        self.line = line
        self.nbytes = len(line) + 1
        self.done = threading.Event()
        self.reply: str | Exception | None = None
        self.info: list[str] = []
        self.epoch = epoch

    def fail(self, err: Exception) -> None:
        if not self.done.is_set():
            self.reply = err
            self.done.set()


#: states in which the controller moves or has motion pending
_BUSY_STATES = ("Run", "Jog", "Home", "Hold")
#: alarms after which GRBL keeps its machine position (soft limit: checked before motion)
_POSITION_KEPT_ALARMS = (2,)


class GrblMotors(Motors):
    """Secondary carriage DX, DY on a GRBL 1.1 controller over a serial line (pyserial).

    Parameters
    ----------
    port : str
        Serial device (``/dev/ttyUSB0``, or the pty path printed by
        ``softplot motors simulate``); any pyserial URL works.
    dx, dy : AxisConfig, optional
        Axis configuration; resolution sets ``$100/$101``, speed ``$110/$111``.
    baudrate : int
        115200 for GRBL 1.1.
    timeout : float
        Seconds to wait for any one answer (``ok``, status, banner) from a controller that
        is not busy (a controller that moves or holds may take longer: see docs/motors.md).
    streaming : {"char-count", "send-response"}
        Flow control for motion lines.
    home_mm : (float, float)
        Plate position (instrument mm) of the homed position, set as the work offset.
    reset : bool
        Soft-reset the controller on connect. By default a running controller is left
        alone (a status query first); it is reset only when it does not answer.
    unlock : bool
        Allow :meth:`recover` to unlock (``$X``) after a soft-limit alarm, the one alarm
        after which GRBL keeps its position. Never used after a reset or a power cycle.
    configure : bool
        Write ``$100/$101/$110/$111`` when they differ from the axis configuration.
    check_encoders : bool
        After each completed wait read the carriage encoders (``$ENC``, an extension a
        stock GRBL lacks) and raise :class:`LostSteps` on a difference of a step or more.
    """

    def __init__(
        self,
        port: str,
        dx: AxisConfig | None = None,
        dy: AxisConfig | None = None,
        *,
        baudrate: int = 115200,
        timeout: float = 2.0,
        streaming: str = "char-count",
        home_mm: tuple[float, float] = (0.0, 0.0),
        reset: bool = False,
        unlock: bool = False,
        configure: bool = True,
        check_encoders: bool = False,
        poll_interval: float = 0.01,
    ):
        super().__init__(dx, dy)
        if streaming not in ("char-count", "send-response"):
            raise MotorError(f"streaming must be char-count or send-response, got {streaming!r}")
        self.port = port
        self.baudrate = baudrate
        self.timeout = float(timeout)
        self.streaming = streaming
        self.home_mm = tuple(float(v) for v in home_mm)
        self.reset_on_connect = reset
        self.unlock = unlock
        self.configure_axes = configure
        self.check_encoders = check_encoders
        self.poll_interval = poll_interval
        self.ser = None
        self._reader = None
        self._cv = threading.Condition()
        self._inflight: deque[_Pending] = deque()
        self._motion: deque[_Pending] = deque()  # streamed motion lines not yet checked
        self._write_lock = threading.Lock()
        self._status: GrblStatus | None = None
        self._status_seq = 0
        self._banner_seq = 0
        self._epoch = 0  # soft resets written
        self._banners_due = 0  # banners still to come from resets (ours or automatic)
        self._connecting = False
        self._booted = False  # a banner nobody asked for was seen while connecting
        self._homing: int | None = None  # ALARM code of a failed homing cycle
        self._wco = (0.0, 0.0, 0.0)
        self._wco_known = False
        self.alarm: int | None = None
        self.messages: deque[str] = deque(maxlen=50)
        self.settings: dict[int, float] = {}
        self.fault: MotorFault | None = None
        self.position_valid = True
        self.homed = False
        self.confirmed = False  # the operator vouched for the present position
        self._last_mpos: tuple[float, float] | None = None  # at the last standstill
        self._lost: Exception | None = None
        self._ready = False  # $I, $$ and the configuration done
        self.connect()

    # ------------------------------------------------------------------ faults
    def _set_fault(self, err: MotorFault) -> MotorFault:
        """Record ``err`` unless a fault is already recorded (the first cause is kept)."""
        with self._cv:
            if self.fault is None:
                self.fault = err
            return self.fault

    def _lose_position(self, why: str) -> None:
        self.position_valid = False
        self.homed = self.confirmed = False
        self._set_fault(MotorPositionLost(why))

    def _check_fault(self):
        if self.fault is not None:
            raise self.fault

    # ------------------------------------------------------------------ connection
    def connect(self) -> None:
        """Open the port and synchronise with the controller (no reset unless it is needed
        or ``reset=True``); read and configure settings when it stands still.

        On failure the port is closed again and the error raised.
        """
        try:
            self._connect()
        except BaseException:
            self.close()
            raise
        finally:
            self._connecting = False

    def _connect(self) -> None:
        try:
            self.ser = serial.Serial(
                self.port,
                self.baudrate,
                timeout=0.05,
                write_timeout=self.timeout,
                exclusive=True,  # one driver per controller (flock)
            )
        except (serial.SerialException, OSError) as exc:
            raise MotorDisconnected(f"cannot open serial port {self.port}: {exc}") from exc
        self._lost = None
        self.fault = None
        self.alarm = None
        self._booted = False
        self._ready = False
        self._wco_known = False
        self._banners_due = 0
        self._connecting = True
        with self._cv:
            self._inflight.clear()
        self._motion.clear()
        self.ser.reset_input_buffer()
        self._reader = threading.Thread(target=self._read_loop, name="grbl-reader", daemon=True)
        self._reader.start()
        st = None
        if not self.reset_on_connect:
            try:  # reading is not writing: a running controller is not reset
                st = self.status(timeout=min(self.timeout, 1.0))
            except MotorTimeout:
                st = None
            self.fault = None
        if st is None:
            self.soft_reset()
        st = self.status()
        if st.state not in _BUSY_STATES:
            self._prepare()
            st = self.status()
        else:
            self._need_wco()
        if st.state == "Alarm":  # locked (power-up with homing, an alarm): GRBL wants $H
            self.position_valid = False
        self._sync_target(st)

    def _prepare(self) -> None:
        """``$I`` handshake, ``$$``, axis configuration (needs a controller at rest)."""
        self._handshake()
        self.read_settings()
        if self.configure_axes:
            self._configure()
        self._need_wco()
        self._ready = True

    def _need_wco(self) -> None:
        for _ in range(32):  # WCO comes with the first report after a reset or every <= 30
            if self._wco_known:
                return
            self.status()

    def _sync_target(self, st: GrblStatus) -> None:
        self._motion.clear()
        with self._lock:
            self._dir = [1, 1]
            self._target = list(self._steps_of(st))
        if st.state not in _BUSY_STATES:
            self._last_mpos = tuple(st.mpos[:2])

    def close(self) -> None:
        ser, self.ser = self.ser, None
        if ser is not None:
            try:
                ser.close()
            except Exception:  # noqa: BLE001 - closing a dead port
                pass
        if self._reader is not None:
            self._reader.join(timeout=1)
            self._reader = None

    def reconnect(self, timeout: float = 5.0) -> None:
        """Re-open the port after a lost line (retrying for ``timeout`` s) and re-sync.

        The controller's position is trusted again only if it is where it was (same
        machine position and work offset, no reboot seen); otherwise
        :class:`MotorPositionLost` is raised and kept until :meth:`home` or
        :meth:`confirm_position`.
        """
        before = (self._last_mpos, self._machine_target(), self._wco, self.position_valid)
        self.close()
        t_end = time.monotonic() + timeout
        while True:
            try:
                self.connect()
                break
            except MotorDisconnected:
                if time.monotonic() > t_end:
                    raise
                time.sleep(0.05)
        last, target, wco, valid = before
        st = self.status()
        here = tuple(st.mpos[:2])
        same = any(
            p is not None
            and all(abs(a - b) < 0.5 * r for a, b, r in zip(here, p, self.resolution, strict=True))
            for p in (last, target)
        ) and all(abs(a - b) < 1e-6 for a, b in zip(self._wco[:2], wco[:2], strict=True))
        if not valid or not self.position_valid or not same or self._booted:
            self._lose_position(
                f"controller on {self.port} came back at machine position "
                f"{here[0]:.3f},{here[1]:.3f} mm"
                + ("" if last is None else f" (it was at {last[0]:.3f},{last[1]:.3f} mm)")
                + ": reset or power-cycled, position lost; home the axes or confirm the "
                "position"
            )
            raise self.fault

    def recover(self) -> None:
        """Clear a fault: soft reset (clears a critical alarm) and re-sync the target.

        After a soft-limit alarm (``ALARM:2``, GRBL keeps its position) the alarm lock is
        lifted with ``$X`` when ``unlock=True``. After any fault that loses the position
        (reboot, power loss, hard limit, reset while moving, failed homing) motion stays
        refused (:class:`MotorPositionLost`) until :meth:`home` or :meth:`confirm_position`.
        """
        alarm = self.alarm if isinstance(self.fault, MotorAlarm) else None
        self.fault = None
        self.alarm = None
        if alarm not in (1, 2):
            self._halt()  # a reset while moving would raise ALARM:3: stop first
        self.soft_reset()
        st = self.status()
        if st.state == "Alarm" and alarm in _POSITION_KEPT_ALARMS and self.unlock:
            self.command("$X")
            st = self.status()
        if not self.position_valid:
            self._lose_position(
                f"controller on {self.port}: position lost; home the axes or confirm the position"
            )
        self._sync_target(st)

    def confirm_position(self) -> None:
        """The operator vouches for the controller's present position (e.g. checked against
        a reference mark): unlock an alarm lock (``$X``), trust the position again."""
        self.fault = None
        st = self.status()
        if st.state == "Alarm":
            self.command("$X")
            st = self.status()
        self.position_valid = True
        self.confirmed = True
        self.alarm = None
        self._sync_target(st)

    # ------------------------------------------------------------------ reader
    def _read_loop(self):
        ser = self.ser
        part = b""  # a line cut by the read timeout, waiting for its end
        while ser is self.ser and ser is not None:
            try:
                raw = ser.readline()
            except (serial.SerialException, OSError, TypeError, AttributeError) as exc:
                self._line_lost(exc)
                return
            if not raw:
                continue
            part += raw
            if not part.endswith(b"\n"):
                continue
            line = part.decode("ascii", "replace").strip()
            part = b""
            if line:
                self._dispatch(line)

    def _line_lost(self, exc):
        if self.ser is None:
            return  # closed on purpose
        with self._cv:
            self._lost = exc
            err = self._set_fault(MotorDisconnected(f"serial line to {self.port} lost: {exc}"))
            while self._inflight:
                self._inflight.popleft().fail(err)
            self._cv.notify_all()

    def _dispatch(self, line: str):
        with self._cv:
            if line == "ok" or line.startswith("error:"):
                if self._inflight:
                    p = self._inflight.popleft()
                    if not p.done.is_set():  # a line already failed absorbs its late answer
                        p.reply = line
                        p.done.set()
                else:
                    self.messages.append(line)
            elif line.startswith("<"):
                try:
                    st = parse_status(line, self._wco)
                except MotorError:
                    self.messages.append(line)
                else:
                    if "WCO" in st.fields:
                        self._wco_known = True
                    self._wco = st.wco
                    self._status = st
                    self._status_seq += 1
            elif line.startswith("ALARM:"):
                self._on_alarm(line)
            elif line.startswith("Grbl "):
                self._on_banner()
            elif line.startswith("$") and "=" in line and line[1:2].isdigit():
                k, _, v = line[1:].partition("=")
                try:
                    self.settings[int(k)] = float(v)
                except ValueError:
                    self.messages.append(line)
            else:
                self.messages.append(line)
                if line.startswith("["):
                    for p in self._inflight:
                        if not p.done.is_set():
                            p.info.append(line)
                            break
            self._cv.notify_all()

    def _on_alarm(self, line: str):
        try:
            code = int(line[6:])
        except ValueError:
            code = -1
        self.alarm = code
        text = f"GRBL ALARM:{code} ({ALARM_CODES.get(code, 'unknown alarm')}) on {self.port}"
        if self._homing is not None and code in (6, 7, 8, 9):
            # a failed homing cycle: GRBL answers $H late, then resets itself
            self._homing = code
            self._epoch += 1
            self._banners_due += 1
            self.position_valid = False
            return
        err = self._set_fault(MotorAlarm(text, code))
        if code not in _POSITION_KEPT_ALARMS:
            self.position_valid = False
            self.homed = self.confirmed = False
        if code in (1, 2):  # critical: nothing is answered until a reset
            for p in self._inflight:  # kept in line: a late answer must not shift the rest
                p.fail(err)

    def _on_banner(self):
        self._banner_seq += 1
        if self._banners_due > 0 or self._connecting:
            if self._banners_due > 0:
                self._banners_due -= 1
            elif self._connecting:
                self._booted = True
            err = _Discarded(f"controller on {self.port} reset; line discarded")
            kept = deque(p for p in self._inflight if p.epoch >= self._epoch)
            for p in self._inflight:
                if p.epoch < self._epoch:
                    p.fail(err)
            self._inflight = kept
            return
        # nobody asked: the controller restarted (reset button, power blip, USB)
        err = self._set_fault(
            MotorPositionLost(
                f"controller on {self.port} restarted by itself (unrequested banner): "
                "machine position lost, motion stopped; home the axes or confirm the position"
            )
        )
        self.position_valid = False
        self.homed = self.confirmed = False
        while self._inflight:
            self._inflight.popleft().fail(err)
        # lines that reached the rebooted controller must not run: reset it
        self._epoch += 1
        self._banners_due += 1
        try:
            with self._write_lock:
                self.ser.write(b"\x18")
        except Exception:  # noqa: BLE001 - the line may be going away with the power
            self._banners_due -= 1

    # ------------------------------------------------------------------ sending
    def _write(self, data: bytes):
        if self._lost is not None or self.ser is None:
            raise MotorDisconnected(f"serial line to {self.port} lost: {self._lost}")
        try:
            with self._write_lock:
                self.ser.write(data)
        except (serial.SerialException, OSError) as exc:
            self._line_lost(exc)
            raise MotorDisconnected(f"serial line to {self.port} lost: {exc}") from exc

    def realtime(self, byte: bytes) -> None:
        """Send a real-time command (``b"?"``, ``b"!"``, ``b"~"``, ``b"\\x18"``, ``b"\\x85"``)."""
        self._write(byte)

    def _controller_busy(self) -> bool:
        """A fresh status says the controller moves, holds or homes (its answers may be
        legitimately late: a full planner, a feed hold, a sync line)."""
        try:
            return self.status().state in _BUSY_STATES
        except MotorFault:
            return False

    def send(self, line: str, *, sync: bool | None = None) -> _Pending:
        """Queue a line under the streaming protocol; returns its pending reply.

        ``sync=True`` waits until nothing else is in flight first (send-response). No line
        is written while a reset's banner is due. While the controller is busy (moving,
        holding: GRBL reads no line during a feed hold) the wait does not time out.
        """
        sync = (self.streaming == "send-response") if sync is None else sync
        t_end = time.monotonic() + self.timeout
        while True:
            with self._cv:
                while True:
                    if self._lost is not None:
                        raise MotorDisconnected(f"serial line to {self.port} lost: {self._lost}")
                    used = sum(q.nbytes for q in self._inflight)
                    room = (not self._inflight) if sync else (used + len(line) + 1 < RX_BUFFER)
                    if room and self._banners_due == 0:
                        p = _Pending(line, self._epoch)
                        self._inflight.append(p)
                        break
                    left = t_end - time.monotonic()
                    if left <= 0:
                        p = None
                        break
                    self._cv.wait(min(left, 0.1))
            if p is not None:
                break
            if self._banners_due == 0 and self._controller_busy():
                t_end = time.monotonic() + self.timeout  # paused, not stuck
                continue
            raise self._set_fault(
                MotorTimeout(
                    f"GRBL on {self.port} did not acknowledge {len(self._inflight)} line(s) "
                    f"within {self.timeout} s"
                )
            )
        try:
            self._write((line + "\n").encode("ascii"))
        except MotorDisconnected as exc:
            p.fail(exc)
            raise
        return p

    def _result(self, p: _Pending, timeout: float | None, *, patient: bool = True) -> list[str]:
        """Wait for the answer to ``p``. ``patient``: a controller that is busy (moving,
        holding) is given more time (GRBL answers a line behind a full planner, a sync
        line or a feed hold only later)."""
        timeout = self.timeout if timeout is None else timeout
        while not p.done.wait(timeout):
            if patient and self._controller_busy():
                continue
            if p.done.is_set():
                break
            err = MotorTimeout(f"GRBL on {self.port}: no answer to {p.line!r} within {timeout} s")
            raise self._set_fault(err)
        if isinstance(p.reply, Exception):
            raise p.reply
        if p.reply.startswith("error:"):
            code = int(p.reply[6:]) if p.reply[6:].isdigit() else -1
            raise MotorCommandError(
                f"GRBL error:{code} ({ERROR_CODES.get(code, 'unknown error')}) for {p.line!r}",
                code,
            )
        return p.info

    def command(self, line: str, timeout: float | None = None, *, sync: bool = True) -> list[str]:
        """Send one line and wait for its ``ok``; returns the ``[...]`` lines it printed.

        Raises :class:`MotorCommandError` on ``error:N``, :class:`MotorTimeout`,
        :class:`MotorAlarm` or :class:`MotorDisconnected`.
        """
        return self._result(self.send(line, sync=sync), timeout)

    def status(self, timeout: float | None = None) -> GrblStatus:
        """Ask for a status report (``?``) and return it parsed.

        The query is repeated (every 0.25 s at least) until ``timeout``: GRBL drops a
        pending ``?`` at a reset and answers nothing for 0.5 s after an alarm. On a
        critical alarm (nothing is answered until a reset) the alarm is raised; otherwise
        the first recorded fault is kept and raised, or :class:`MotorTimeout`.
        """
        timeout = self.timeout if timeout is None else timeout
        t_end = time.monotonic() + timeout
        while True:
            with self._cv:
                seq = self._status_seq
            self.realtime(b"?")
            t_retry = min(time.monotonic() + max(0.25, timeout / 4), t_end)
            with self._cv:
                while self._status_seq == seq:
                    if self._lost is not None:
                        raise MotorDisconnected(f"serial line to {self.port} lost: {self._lost}")
                    left = t_retry - time.monotonic()
                    if left <= 0:
                        break
                    self._cv.wait(min(left, 0.05))
                else:
                    return self._status
            if time.monotonic() >= t_end:
                break
        if self.alarm in (1, 2):
            raise self._set_fault(
                MotorAlarm(
                    f"GRBL ALARM:{self.alarm} ({ALARM_CODES[self.alarm]}) on {self.port}; "
                    "reset to continue",
                    self.alarm,
                )
            )
        raise self._set_fault(
            MotorTimeout(f"GRBL on {self.port}: no status report within {timeout} s")
        )

    def soft_reset(self, timeout: float | None = None) -> None:
        """Send 0x18 and wait for the ``Grbl 1.1`` banner (lines wait meanwhile)."""
        timeout = self.timeout if timeout is None else timeout
        with self._cv:
            self._epoch += 1
            self._banners_due += 1
        try:
            self.realtime(b"\x18")
        except MotorDisconnected:
            with self._cv:
                self._banners_due = 0
            raise
        t_end = time.monotonic() + timeout + 0.5  # + the firmware's pause after ALARM:3
        with self._cv:
            while self._banners_due > 0:
                if self._lost is not None:
                    raise MotorDisconnected(f"serial line to {self.port} lost: {self._lost}")
                left = t_end - time.monotonic()
                if left <= 0:
                    self._banners_due = 0
                    raise MotorTimeout(f"no GRBL banner from {self.port} within {timeout} s")
                self._cv.wait(left)
        if self.alarm in (1, 2):
            self.alarm = None

    def _handshake(self, attempts: int = 4) -> list[str]:
        """``$I`` until it is answered; returns its ``[VER:..]``/``[OPT:..]`` lines.

        A line lost outright (a controller still booting) is sent again, once, after
        ``timeout``; a banner that discards ``$I`` (the controller restarted) sends it again.
        """
        timeouts = 0
        for i in range(attempts):
            p = self.send("$I", sync=True)
            try:
                info = self._result(p, None, patient=False)
            except (_Discarded, MotorTimeout) as exc:
                with self._cv:
                    if p in self._inflight:
                        self._inflight.remove(p)
                timeouts += isinstance(exc, MotorTimeout)
                if i == attempts - 1 or timeouts > 1:
                    raise
                self.fault = None
                continue
            ver = [ln for ln in info if ln.startswith("[VER:")]
            if ver and not ver[0].startswith("[VER:1.1"):
                raise MotorError(f"{self.port}: GRBL 1.1 expected, controller says {ver[0]}")
            return info
        return []

    def read_settings(self) -> dict[int, float]:
        """``$$``: the controller's settings (also kept in :attr:`settings`)."""
        self.command("$$")
        return dict(self.settings)

    def _configure(self):
        want = {}
        for i, ax in enumerate(self.axes):
            want[100 + i] = 1.0 / ax.resolution_mm
            want[110 + i] = ax.max_speed_mm_s * 60.0
        for k, v in want.items():
            if (
                abs(self.settings.get(k, float("nan")) - v) > 1e-6 * max(1.0, v)
                or k not in self.settings
            ):
                self.command(f"${k}={v:.3f}")  # EEPROM write: send-response
                self.settings[k] = v

    # ------------------------------------------------------------------ Motors hooks
    def _steps_of(self, st: GrblStatus) -> tuple[int, int]:
        return tuple(int(round(st.wpos[i] / ax.resolution_mm)) for i, ax in enumerate(self.axes))

    def _machine_target(self) -> tuple[float, float]:
        """The commanded motor position in machine mm (work target + work offset)."""
        with self._lock:
            motor = [
                s if d > 0 else s - ax.backlash_steps
                for s, d, ax in zip(self._target, self._dir, self.axes, strict=True)
            ]
        return tuple(
            m * ax.resolution_mm + o
            for m, ax, o in zip(motor, self.axes, self._wco[:2], strict=True)
        )

    def _check_travel(self, x: float, y: float) -> None:
        """GRBL's soft limits (``$20=1``): machine targets in ``[-$130, 0]``, ``[-$131, 0]``."""
        if not self.settings.get(20):
            return
        for i, (name, w) in enumerate((("DX", x), ("DY", y))):
            m = w + self._wco[i]
            travel = self.settings.get(130 + i)
            if travel is None:
                continue
            if not -travel - 1e-9 <= m <= 1e-9:
                raise MotorLimitError(
                    f"{name} target {w:.3f} mm is machine {m:.3f} mm, outside the "
                    f"controller's soft limits [{-travel:g}, 0] mm ($13{i}, $20=1)"
                )

    def _start_move(self, motor_steps, speed_mm_s):
        self._check_fault()
        if not self.position_valid:
            raise self._set_fault(
                MotorPositionLost(
                    f"controller on {self.port}: position not valid (reset, power cycle or "
                    "alarm); home the axes or confirm the position"
                )
            )
        self._check_motion_replies()
        if not self._ready:
            if not self.wait(max(self.timeout, 30.0)):
                raise self._set_fault(MotorTimeout(f"controller on {self.port} stays busy"))
            self._prepare()
        x, y = (s * ax.resolution_mm for s, ax in zip(motor_steps, self.axes, strict=True))
        self._check_travel(x, y)
        feed = min(speed_mm_s) * 60.0
        p = self.send(f"G90G1X{x:.3f}Y{y:.3f}F{feed:.0f}")
        if self.streaming == "send-response":
            self._result(p, None)
        else:  # char-count: the ok is collected later (next move, wait, busy)
            self._motion.append(p)

    def _check_motion_replies(self, timeout: float | None = 0.0) -> bool:
        """Collect the replies of streamed motion lines; raise on ``error:N`` (which also
        becomes the fault: the plate is not where the target says). Returns True when every
        motion line has been answered within ``timeout`` seconds."""
        t_end = None if timeout is None else time.monotonic() + timeout
        while self._motion:
            p = self._motion[0]
            left = None if t_end is None else max(t_end - time.monotonic(), 0.0)
            if not p.done.wait(left):
                return False
            self._motion.popleft()
            try:
                self._result(p, 0.0)
            except MotorCommandError as exc:
                self._motion.clear()
                raise self._set_fault(MotorFault(f"motion line rejected: {exc}")) from exc
        return True

    def _busy(self):
        self._check_fault()
        st = self.status()
        return st.state in _BUSY_STATES or bool(self._motion) or bool(self._inflight)

    def wait(self, timeout: float | None = None) -> bool:
        """Block until every line is answered and the controller stands still (``Idle``);
        False if ``timeout`` seconds passed first (a feed hold counts as not finished).
        A fault raises."""
        t_end = None if timeout is None else time.monotonic() + timeout
        while not self._check_motion_replies(min(self.timeout, timeout or self.timeout)):
            self._check_fault()
            if t_end is not None and time.monotonic() >= t_end:
                return False
        while True:
            self._check_fault()
            st = self.status()
            if st.state == "Alarm":
                raise self._set_fault(MotorAlarm(f"GRBL in alarm state on {self.port}", self.alarm))
            if st.state not in _BUSY_STATES and not self._inflight:
                self._check_fault()  # a banner or an alarm that came before this report
                break
            if t_end is not None and time.monotonic() >= t_end:
                return False
            time.sleep(self.poll_interval)
        self._last_mpos = tuple(st.mpos[:2])
        if self.check_encoders:
            self.verify_encoders(st)
        return True

    def verify_encoders(self, st: GrblStatus | None = None) -> tuple[float, float]:
        """Read the carriage encoders (``$ENC``, an extension of instruments with encoders)
        and compare with the controller position.

        Returns
        -------
        (float, float)
            Encoder DX, DY, machine mm.

        Raises
        ------
        LostSteps
            If they differ by one step or more (the motors stopped first).
        MotorError
            The controller has no ``$ENC`` extension (a stock GRBL answers ``error:2``).
        """
        st = st or self.status()
        try:
            info = self.command("$ENC")
        except MotorCommandError as exc:
            raise MotorError(
                f"controller on {self.port} has no encoder read-out ($ENC answered "
                f"error:{exc.code}); catch lost steps by homing or probing a reference"
            ) from exc
        enc = None
        for line in info:
            if line.startswith("[ENC:"):
                enc = _vec(line[5:-1])
        if enc is None:
            raise MotorError(f"controller on {self.port} printed no [ENC:...] line")
        for i, (name, ax) in enumerate(zip(("DX", "DY"), self.axes, strict=True)):
            diff = enc[i] - st.mpos[i]
            if abs(diff) >= ax.resolution_mm * (1 - 1e-6):
                raise self._set_fault(
                    LostSteps(
                        f"lost steps on {name}: controller at {st.mpos[i]:.3f} mm, encoder "
                        f"{enc[i]:.3f} mm ({diff / ax.resolution_mm:+.0f} steps)"
                    )
                )
        return enc[0], enc[1]

    def _wait_state(self, ok, limit: float) -> GrblStatus:
        t_end = time.monotonic() + limit
        st = self.status()
        while not ok(st) and time.monotonic() < t_end:
            time.sleep(self.poll_interval)
            st = self.status()
        return st

    def _halt(self):
        if self._lost is not None:
            return
        try:
            st = self.status()
            if st.state == "Jog":
                self.realtime(b"\x85")  # jog cancel: decelerate, flush the jogs
                self._wait_state(lambda s: s.state != "Jog", max(self.timeout, 10.0))
            elif st.state in ("Run", "Hold"):
                self.realtime(b"!")
                self._wait_state(
                    lambda s: (
                        s.state in ("Idle", "Alarm") or (s.state == "Hold" and s.substate == 0)
                    ),
                    max(self.timeout, 10.0),
                )
                self.soft_reset()  # flushes the planner; no alarm after a completed hold
            with self._cv:
                for p in self._inflight:
                    p.fail(_Discarded(f"stopped on {self.port}"))
            self._motion.clear()
        except MotorFault:
            pass

    def _motor_steps(self):
        return self._steps_of(self.status())

    def home(self, *, timeout: float | None = None) -> None:
        """Home (``$H``, needs ``$22=1``), set the work offset so that the homed position
        is plate ``home_mm``, go to plate (0, 0). Re-establishes a lost position.

        Raises
        ------
        MotorAlarm
            The homing cycle failed (``ALARM:6..9``; GRBL answers ``$H`` late and resets
            itself): one fault naming the alarm; the position stays lost.
        """
        if isinstance(self.fault, MotorAlarm) and self.fault.code in (1, 2):
            self.soft_reset()  # a critical alarm answers nothing until a reset
        if isinstance(self.fault, (MotorPositionLost, MotorAlarm)):
            self.fault = None
        self._check_fault()
        if not self._ready:
            self._prepare()
        self._homing = 0
        try:
            try:
                self.command("$H", timeout=max(self.timeout, 60.0 if timeout is None else timeout))
            except (_Discarded, MotorCommandError) as exc:
                if not self._homing:
                    raise
                del exc
            code = self._homing
            if code:
                with self._cv:  # the automatic reset's banner
                    t_end = time.monotonic() + self.timeout + 0.5
                    while self._banners_due > 0 and time.monotonic() < t_end:
                        self._cv.wait(0.05)
                self.fault = None
                self.alarm = code
                raise self._set_fault(
                    MotorAlarm(
                        f"homing failed on {self.port}: GRBL ALARM:{code} "
                        f"({ALARM_CODES.get(code, 'unknown alarm')}); the controller reset "
                        "itself and stays locked: check the limit switches, then home again",
                        code,
                    )
                )
        finally:
            self._homing = None
        self.homed = True
        self.position_valid = True
        self.alarm = None
        with self._lock:
            self._dir = [1, 1]
        hx, hy = self.home_mm
        self.command(f"G10L20P1X{hx:.3f}Y{hy:.3f}")
        self.status()
        feed = min(self._speeds) * 60.0
        self.command(f"G90G1X0Y0F{feed:.0f}")
        with self._lock:
            self._target = [0, 0]
        if not self.wait(timeout):
            raise self._set_fault(MotorTimeout(f"homing not finished within {timeout} s"))

    def zero_here(self) -> None:
        """Make the present position plate (0, 0) (``G10 L20 P1 X0 Y0``), e.g. without homing."""
        self.command("G10L20P1X0Y0")
        self.status()
        with self._lock:
            self._target = [0, 0]
            self._dir = [1, 1]

    def ping(self) -> float:
        """Round-trip time (s) of one status query."""
        t0 = time.perf_counter()
        self.status()
        return time.perf_counter() - t0

    # ------------------------------------------------------------------ sessions
    def _reference(self) -> dict:
        """The frame of the saved target: machine target and work offset (machine mm)."""
        return {
            "machine_target": list(self._machine_target()),
            "wco": list(self._wco[:2]),
            "homed": self.homed,
        }

    def _check_reference(self, state: dict) -> None:
        """A saved state is valid on this controller if its machine position and work
        offset are those saved (the same controller session) or it was homed since.
        Raises :class:`MotorPositionLost` otherwise (and keeps refusing motion)."""
        ref = state.get("controller")
        self._check_fault()
        if not self.position_valid:
            raise self._set_fault(
                MotorPositionLost(
                    f"controller on {self.port} has no valid position (reset or power cycle "
                    "since the session was saved); home the axes or confirm the position"
                )
            )
        if ref is None or self.homed or self.confirmed:
            return  # re-referenced since: the saved target is driven to in this frame
        st = self.status()
        here = st.mpos[:2]
        want = ref.get("machine_target")
        wco = ref.get("wco")
        bad = []
        if want is not None and any(
            abs(a - b) >= 0.5 * r for a, b, r in zip(here, want, self.resolution, strict=True)
        ):
            bad.append(
                f"machine position {here[0]:.3f},{here[1]:.3f} mm, saved "
                f"{want[0]:.3f},{want[1]:.3f} mm"
            )
        if wco is not None and any(
            abs(a - b) > 1e-6 for a, b in zip(self._wco[:2], wco, strict=True)
        ):
            bad.append(
                f"work offset {self._wco[0]:.3f},{self._wco[1]:.3f} mm, saved "
                f"{wco[0]:.3f},{wco[1]:.3f} mm"
            )
        if bad:
            self.position_valid = False
            raise self._set_fault(
                MotorPositionLost(
                    f"controller on {self.port} is not where the session left it ("
                    + "; ".join(bad)
                    + "): reset or power-cycled since; home the axes or confirm the position"
                )
            )
