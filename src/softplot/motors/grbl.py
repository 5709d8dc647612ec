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
* Connect: open the port, drop stale input, soft reset (0x18) and wait for the
  ``Grbl 1.1`` banner, read ``$$``, set ``$100/$101`` (steps/mm) and ``$110/$111`` (mm/min)
  when they differ from the axis configuration, unlock (``$X``) an alarm lock if asked.
* Faults become :class:`MotorFault` subclasses with one-line messages: ``MotorAlarm``
  (``ALARM:N``; a critical alarm needs :meth:`GrblMotors.recover`), ``MotorTimeout`` (no
  answer in time), ``MotorDisconnected`` (use :meth:`GrblMotors.reconnect`), ``LostSteps``
  (the instrument's carriage encoders, read with the ``$ENC`` extension when
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


class _Discarded(MotorError):
    """A line in flight was thrown away by a controller reset (banner seen)."""


class _Pending:
    """A line written to the controller and its answer to come.

    ``outlives_banner``: the line was written after a soft reset whose banner may still be on
    its way (the connect handshake); the controller reads it after the 0x18 and answers it
    after that banner, so banners do not discard it (a line lost in a reboot times out).
    """

    __slots__ = ("line", "nbytes", "done", "reply", "info", "outlives_banner")

    def __init__(self, line: str, outlives_banner: bool = False):
        self.line = line
        self.nbytes = len(line) + 1
        self.done = threading.Event()
        self.reply: str | Exception | None = None
        self.info: list[str] = []
        self.outlives_banner = outlives_banner


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
        Seconds to wait for any one answer (``ok``, status, banner).
    streaming : {"char-count", "send-response"}
        Flow control for motion lines.
    home_mm : (float, float)
        Plate position (instrument mm) of the homed position, set as the work offset.
    unlock : bool
        Send ``$X`` when the controller reports an alarm lock on connect/recover.
    configure : bool
        Write ``$100/$101/$110/$111`` when they differ from the axis configuration.
    check_encoders : bool
        After each completed wait read the carriage encoders (``$ENC``) and raise
        :class:`LostSteps` if they disagree with the controller by a step or more.
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
        unlock: bool = True,
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
        self._wco = (0.0, 0.0, 0.0)
        self.alarm: int | None = None
        self.messages: deque[str] = deque(maxlen=50)
        self.settings: dict[int, float] = {}
        self.fault: MotorFault | None = None
        self._lost: Exception | None = None
        self.connect()

    def connect(self) -> None:
        """Open the port, soft-reset, wait for the banner, read/configure settings.

        On failure the port is closed again and the error raised.
        """
        try:
            self._connect()
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ connection
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
        self.ser.reset_input_buffer()
        self._reader = threading.Thread(target=self._read_loop, name="grbl-reader", daemon=True)
        self._reader.start()
        self.soft_reset()
        self._handshake()
        self.read_settings()
        if self.configure_axes:
            self._configure()
        st = self.status()
        if st.state == "Alarm" and self.unlock:
            self.command("$X")
            st = self.status()
        self._sync_target(st)

    def _sync_target(self, st: GrblStatus) -> None:
        self._motion.clear()
        with self._lock:
            self._dir = [1, 1]
            self._target = list(self._steps_of(st))

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
        """Re-open the port after a lost line (retrying for ``timeout`` s) and re-sync."""
        self.close()
        t_end = time.monotonic() + timeout
        while True:
            try:
                self.connect()
                return
            except MotorDisconnected:
                if time.monotonic() > t_end:
                    raise
                time.sleep(0.05)

    def recover(self) -> None:
        """Clear a fault: soft reset (clears a critical alarm), unlock if asked, re-sync."""
        self.fault = None
        self.alarm = None
        self.soft_reset()
        st = self.status()
        if st.state == "Alarm" and self.unlock:
            self.command("$X")
            st = self.status()
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
            err = MotorDisconnected(f"serial line to {self.port} lost: {exc}")
            self.fault = err
            while self._inflight:
                p = self._inflight.popleft()
                p.reply = err
                p.done.set()
            self._cv.notify_all()

    def _dispatch(self, line: str):
        with self._cv:
            if line == "ok" or line.startswith("error:"):
                if self._inflight:
                    p = self._inflight.popleft()
                    p.reply = line
                    p.done.set()
            elif line.startswith("<"):
                try:
                    st = parse_status(line, self._wco)
                except MotorError:
                    self.messages.append(line)
                else:
                    self._wco = st.wco
                    self._status = st
                    self._status_seq += 1
            elif line.startswith("ALARM:"):
                try:
                    self.alarm = int(line[6:])
                except ValueError:
                    self.alarm = -1
                code = self.alarm
                err = MotorAlarm(
                    f"GRBL ALARM:{code} ({ALARM_CODES.get(code, 'unknown alarm')}) on {self.port}",
                    code,
                )
                self.fault = err
                if code in (1, 2):  # critical: nothing is answered until a reset
                    while self._inflight:
                        p = self._inflight.popleft()
                        p.reply = err
                        p.done.set()
            elif line.startswith("Grbl "):
                self._banner_seq += 1
                err = _Discarded(f"controller on {self.port} reset; line discarded")
                kept: deque[_Pending] = deque()
                while self._inflight:
                    p = self._inflight.popleft()
                    if p.outlives_banner:
                        kept.append(p)
                    else:
                        p.reply = err
                        p.done.set()
                self._inflight.extend(kept)
            elif line.startswith("$") and "=" in line:
                k, _, v = line[1:].partition("=")
                try:
                    self.settings[int(k)] = float(v)
                except ValueError:
                    self.messages.append(line)
            else:
                self.messages.append(line)
                if self._inflight and line.startswith("["):
                    self._inflight[0].info.append(line)
            self._cv.notify_all()

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

    def send(
        self, line: str, *, sync: bool | None = None, outlives_banner: bool = False
    ) -> _Pending:
        """Queue a line under the streaming protocol; returns its pending reply.

        ``sync=True`` waits until nothing else is in flight first (send-response).
        ``outlives_banner=True``: a banner does not discard the line (see
        :meth:`_handshake`).
        """
        p = _Pending(line, outlives_banner)
        sync = (self.streaming == "send-response") if sync is None else sync
        t_end = time.monotonic() + self.timeout
        with self._cv:
            while True:
                if self._lost is not None:
                    raise MotorDisconnected(f"serial line to {self.port} lost: {self._lost}")
                used = sum(q.nbytes for q in self._inflight)
                if (not self._inflight) if sync else (used + p.nbytes < RX_BUFFER):
                    break
                left = t_end - time.monotonic()
                if left <= 0:
                    raise MotorTimeout(
                        f"GRBL on {self.port} did not acknowledge {len(self._inflight)} line(s) "
                        f"within {self.timeout} s"
                    )
                self._cv.wait(left)
            self._inflight.append(p)
        self._write((line + "\n").encode("ascii"))
        return p

    def _result(self, p: _Pending, timeout: float | None) -> list[str]:
        timeout = self.timeout if timeout is None else timeout
        if not p.done.wait(timeout):
            err = MotorTimeout(f"GRBL on {self.port}: no answer to {p.line!r} within {timeout} s")
            self.fault = err
            raise err
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
        """Ask for a status report (``?``) and return it parsed."""
        timeout = self.timeout if timeout is None else timeout
        with self._cv:
            seq = self._status_seq
        self.realtime(b"?")
        t_end = time.monotonic() + timeout
        with self._cv:
            while self._status_seq == seq:
                if self._lost is not None:
                    raise MotorDisconnected(f"serial line to {self.port} lost: {self._lost}")
                left = t_end - time.monotonic()
                if left <= 0:
                    if self.alarm in (1, 2):
                        raise MotorAlarm(
                            f"GRBL ALARM:{self.alarm} ({ALARM_CODES[self.alarm]}); "
                            "reset to continue",
                            self.alarm,
                        )
                    err = MotorTimeout(f"GRBL on {self.port}: no status report within {timeout} s")
                    self.fault = err
                    raise err
                self._cv.wait(min(left, 0.05))
            return self._status

    def soft_reset(self, timeout: float | None = None) -> None:
        """Send 0x18 and wait for the ``Grbl 1.1`` banner."""
        timeout = self.timeout if timeout is None else timeout
        with self._cv:
            seq = self._banner_seq
        self.realtime(b"\x18")
        t_end = time.monotonic() + timeout
        with self._cv:
            while self._banner_seq == seq:
                if self._lost is not None:
                    raise MotorDisconnected(f"serial line to {self.port} lost: {self._lost}")
                left = t_end - time.monotonic()
                if left <= 0:
                    raise MotorTimeout(f"no GRBL banner from {self.port} within {timeout} s")
                self._cv.wait(left)
            self._inflight.clear()
        self.alarm = None

    def _handshake(self, attempts: int = 4) -> list[str]:
        """``$I`` until it is answered; returns its ``[VER:..]``/``[OPT:..]`` lines.

        The banner :meth:`soft_reset` waited for may be a stale one (the power-up banner
        still in the line when the port was opened); the reset's own banner then arrives
        after ``$I`` was written. The controller answers ``$I`` anyway (it reads the 0x18
        first), so that banner must not discard it: were ``$I`` sent again, the first
        answer would be taken for the second and every later ``ok`` for the line before
        it, and char-count streaming would overfill the 128-byte buffer. Only a line lost
        outright (a controller still booting) is sent again, once, after ``timeout``.
        """
        timeouts = 0
        for i in range(attempts):
            p = self.send("$I", sync=True, outlives_banner=True)
            try:
                info = self._result(p, None)
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

    def _check_fault(self):
        if self.fault is not None:
            raise self.fault

    def _start_move(self, motor_steps, speed_mm_s):
        self._check_fault()
        self._check_motion_replies()
        x, y = (s * ax.resolution_mm for s, ax in zip(motor_steps, self.axes, strict=True))
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
                self.fault = MotorFault(f"motion line rejected: {exc}")
                raise self.fault from exc
        return True

    def _busy(self):
        self._check_fault()
        return self.status().moving or bool(self._inflight)

    def wait(self, timeout: float | None = None) -> bool:
        t_end = None if timeout is None else time.monotonic() + timeout
        if not self._check_motion_replies(self.timeout if timeout is None else timeout):
            return False
        while True:
            self._check_fault()
            st = self.status()
            if st.state == "Alarm":
                raise MotorAlarm(f"GRBL in alarm state on {self.port}", self.alarm)
            if not st.moving and not self._inflight and st.state != "Hold":
                break
            if t_end is not None and time.monotonic() >= t_end:
                return False
            time.sleep(self.poll_interval)
        if self.check_encoders:
            self.verify_encoders(st)
        return True

    def verify_encoders(self, st: GrblStatus | None = None) -> tuple[float, float]:
        """Read the carriage encoders (``$ENC``) and compare with the controller position.

        Returns
        -------
        (float, float)
            Encoder DX, DY, machine mm.

        Raises
        ------
        LostSteps
            If they differ by one step or more (the motors stopped first).
        """
        st = st or self.status()
        info = self.command("$ENC")
        enc = None
        for line in info:
            if line.startswith("[ENC:"):
                enc = _vec(line[5:-1])
        if enc is None:
            raise MotorError(f"controller on {self.port} printed no [ENC:...] line")
        for i, (name, ax) in enumerate(zip(("DX", "DY"), self.axes, strict=True)):
            diff = enc[i] - st.mpos[i]
            if abs(diff) >= ax.resolution_mm * (1 - 1e-6):
                err = LostSteps(
                    f"lost steps on {name}: controller at {st.mpos[i]:.3f} mm, encoder "
                    f"{enc[i]:.3f} mm ({diff / ax.resolution_mm:+.0f} steps)"
                )
                self.fault = err
                raise err
        return enc[0], enc[1]

    def _halt(self):
        if self._lost is not None:
            return
        try:
            st = self.status()
            if st.state == "Jog":
                self.realtime(b"\x85")
            elif st.moving:
                self.realtime(b"!")
                t_end = time.monotonic() + self.timeout
                while self.status().state not in ("Hold", "Idle") or (
                    self._status.state == "Hold" and self._status.substate == 1
                ):
                    if time.monotonic() > t_end:
                        break
                    time.sleep(self.poll_interval)
                self.soft_reset()  # flushes the planner; no alarm after a completed hold
            with self._cv:
                self._inflight.clear()
            self._motion.clear()
        except MotorFault:
            pass

    def _motor_steps(self):
        return self._steps_of(self.status())

    def _home(self):
        self._check_fault()
        self.command("$H", timeout=max(self.timeout, 60.0))
        hx, hy = self.home_mm
        self.command(f"G10L20P1X{hx:.3f}Y{hy:.3f}")
        feed = min(self._speeds) * 60.0
        self.command(f"G90G1X0Y0F{feed:.0f}")

    def zero_here(self) -> None:
        """Make the present position plate (0, 0) (``G10 L20 P1 X0 Y0``), e.g. without homing."""
        self.command("G10L20P1X0Y0")
        with self._lock:
            self._target = [0, 0]
            self._dir = [1, 1]

    def ping(self) -> float:
        """Round-trip time (s) of one status query."""
        t0 = time.perf_counter()
        self.status()
        return time.perf_counter() - t0
