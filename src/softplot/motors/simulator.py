"""A GRBL-1.1h-compatible simulated controller on a pseudo-terminal, with injectable faults.

``GrblSimulator().start()`` opens a pty (:func:`os.openpty`), puts it in raw mode and serves
the GRBL 1.1 serial protocol on the master side from a background thread; any serial client
(pyserial included) opens the *slave* path (:attr:`GrblSimulator.path`, or a stable symlink
given as ``link``) exactly as it would open ``/dev/ttyUSB0``. The real serial path of
:class:`~softplot.motors.grbl.GrblMotors` is thus exercised end to end.

The simulator is meant to be as strict as the firmware (the GRBL 1.1 protocol as
docs/motors.md); what it does, as GRBL 1.1h does:

* settings as 1.1h ships them (``DEFAULTS_GENERIC``: ``$22=0`` no homing, ``$100=250``
  steps/mm, ``$110=500`` mm/min, ``$120=10`` mm/s², ``$130=200`` mm);
* lines end with ``\\n`` or ``\\r``; one ``ok`` / ``error:N`` per line, ``\\r\\n`` endings;
  115200-baud byte timing both ways; a 128-byte RX buffer (overflowing bytes are dropped);
  error:11 from 80 characters (after spaces and comments are stripped); a 15-block planner
  (the ``ok`` of a motion line is held back while it is full);
* motion with acceleration (trapezoidal speed profile per block, ``$120/$121``, starting
  and ending at rest), jogs (``$J=``), a feed hold that decelerates (``Hold:1``) before it
  completes (``Hold:0``); during a hold *no* line is read (not even ``$$``) until ``~``;
  jog cancel (0x85) decelerates, then flushes the jogs;
* real-time bytes ``?`` ``!`` ``~`` 0x18 0x85; 0x18 while moving raises ALARM:3 (ALARM:6
  while homing); after every ``ALARM:N`` the firmware pauses 0.5 s (it waits for the
  message to leave), and a reset arriving meanwhile drops a pending ``?``;
* soft limits (``$20=1``) in machine coordinates ``[-$130, 0]``: ALARM:2 on G0/G1 (critical:
  nothing is answered, not even ``?``, until 0x18; the line that raised it gets a late
  ``ok`` after the reset), error:15 on a jog;
* ``G0``/``G1`` (``F`` modal), ``G4 P`` (``ok`` after all motion and the dwell),
  ``G90/G91``, ``G20/G21``, ``G54``-``G59``, ``G10 L2/L20`` and ``$x=`` (EEPROM writes:
  answered only after motion has ended), ``G28.1/G30.1``, ``$H`` (homing toward +,
  machine position ``-$27`` afterwards; needs ``$22=1``), ``$X``, ``$$``, ``$I`` (no
  vendor build string), ``$G``, ``$#`` (G54-G59, G28, G30, G92, TLO, PRB), ``$N`` /
  ``$Nx=line`` (startup lines, run at boot as ``>line:ok``), ``$C`` (check mode; turning
  it off resets the controller);
* status ``<State|MPos:..|Bf:..|FS:..|Pn:..|WCO:..|Ov:..>`` following ``$10`` and the WCO rules;
* reboot and power loss: machine position lost (back to 0), EEPROM (settings, G54-G59,
  startup lines) kept, an unrequested banner; with ``$22=1`` the controller comes up
  alarm-locked;
* the ``$ENC`` encoder read-out is an *opt-in* extension (``encoders=True``):
  ``[ENC:dx,dy]`` is the physical carriage position (differs from MPos after lost steps
  or a reboot); a stock controller answers ``error:2``.

Time: every duration of the controller (motion, dwell, homing, the alarm pause, the baud
rate) runs ``time_scale`` times faster than real time; ``slow`` replies, ``reconnect_after``
and ``@Ts`` triggers are real seconds.

Faults (:class:`FaultPlan`, CLI ``--faults``): comma-separated ``NAME[=VALUE][@WHEN]`` with
``WHEN`` = ``moveN`` (when the N-th motion block starts, 1-based) or ``Ts`` (T seconds after
start):

* ``disconnect@...`` - the line goes away (pty closed); it comes back after
  ``reconnect_after`` seconds on a new pty (the ``link`` symlink is updated). The controller
  keeps its state (separately powered).
* ``alarm@...`` - hard limit: motion stops, ALARM:1, ``[MSG:Reset to continue]``.
* ``lost-steps=K@...`` - the X motor (DX) loses K steps during that move: MPos does not know,
  ``$ENC`` does.
* ``reboot@...`` - the controller restarts (reset button, power blip): machine position
  lost, an unrequested banner, the line stays.
* ``power-loss@...`` - as reboot, and the USB line goes away and comes back.
* ``homing-fail=N`` - the next homing cycle fails with ALARM:N (8 or 9; default 9).
* ``slow=S`` - every reply (ok, error, status, messages) leaves S seconds late.
"""

from __future__ import annotations

import errno
import math
import os
import re
import select
import threading
import time
import tty
from collections import deque
from dataclasses import dataclass, field

from softplot.motors.base import MotorError

__all__ = ["GrblSimulator", "FaultPlan", "parse_faults", "BANNER", "DEFAULT_SETTINGS"]

BANNER = "Grbl 1.1h ['$' for help]"
RX_BUFFER = 128
PLANNER_BLOCKS = 15
LINE_MAX = 80  # LINE_BUFFER_SIZE: a line of 80 characters or more is error:11
BAUD = 115200
BYTE_TIME = 10.0 / BAUD  # 8-N-1: ten bits a byte
ALARM_PAUSE = 0.5  # report_alarm_message(): delay_ms(500)
CRITICAL = (1, 2)

#: GRBL 1.1h DEFAULTS_GENERIC, as ``$$`` prints them after ``$RST=$``
DEFAULT_SETTINGS = {
    0: 10,
    1: 25,
    2: 0,
    3: 0,
    4: 0,
    5: 0,
    6: 0,
    10: 1,
    11: 0.010,
    12: 0.002,
    13: 0,
    20: 0,
    21: 0,
    22: 0,
    23: 0,
    24: 25.0,
    25: 500.0,
    26: 250,
    27: 1.0,
    30: 1000,
    31: 0,
    32: 0,
    100: 250.0,
    101: 250.0,
    102: 250.0,
    110: 500.0,
    111: 500.0,
    112: 500.0,
    120: 10.0,
    121: 10.0,
    122: 10.0,
    130: 200.0,
    131: 200.0,
    132: 200.0,
}


@dataclass
class Fault:
    """One injected fault (kinds: see the module docstring)."""

    kind: str
    value: float = 0.0
    at_move: int | None = None
    at_time: float | None = None
    fired: bool = False


@dataclass
class FaultPlan:
    """The faults a :class:`GrblSimulator` injects."""

    faults: list[Fault] = field(default_factory=list)

    @property
    def slow(self) -> float:
        return sum(f.value for f in self.faults if f.kind == "slow")


_KINDS = "disconnect|alarm|lost-steps|slow|reboot|power-loss|homing-fail"
_FAULT_RE = re.compile(
    rf"^(?P<kind>{_KINDS})(?:=(?P<val>[-+0-9.eE]+))?"
    r"(?:@(?:move(?P<move>\d+)|(?P<t>[0-9.]+)s))?$"
)


def parse_faults(spec: str | None) -> FaultPlan:
    """Parse a fault spec such as ``"slow=0.2,alarm@move3,lost-steps=5@move2"``.

    Raises
    ------
    MotorError
        On an unknown fault or a missing trigger (one line naming the bad item).
    """
    plan = FaultPlan()
    if not spec:
        return plan
    for item in (s.strip() for s in spec.split(",")):
        if not item:
            continue
        m = _FAULT_RE.match(item)
        if not m:
            raise MotorError(
                f"bad fault {item!r}: use disconnect@WHEN, alarm@WHEN, lost-steps=K@WHEN, "
                "reboot@WHEN, power-loss@WHEN, homing-fail[=8|9] or slow=SECONDS, "
                "WHEN = moveN or Ts"
            )
        kind = m["kind"]
        default = {"lost-steps": 1.0, "homing-fail": 9.0}.get(kind, 0.0)
        val = float(m["val"]) if m["val"] else default
        at_move = int(m["move"]) if m["move"] else None
        at_time = float(m["t"]) if m["t"] else None
        if kind not in ("slow", "homing-fail") and at_move is None and at_time is None:
            raise MotorError(f"fault {item!r} needs a trigger @moveN or @Ts")
        if kind == "slow" and not val > 0:
            raise MotorError(f"fault {item!r}: slow needs a delay in seconds > 0, e.g. slow=0.2")
        if kind == "homing-fail" and val not in (8, 9):
            raise MotorError(f"fault {item!r}: homing-fail is ALARM 8 or 9")
        plan.faults.append(Fault(kind, val, at_move, at_time))
    return plan


@dataclass
class _Block:
    """One planner block: a straight move (machine mm) with a trapezoidal speed profile."""

    target: list[float]  # machine mm, 3 axes
    feed: float  # mm/min
    jog: bool = False
    move_no: int = 0
    start: list[float] | None = None  # set when the block starts executing
    t0: float = 0.0  # sim time of the start
    length: float = 0.0
    accel: float = 1.0  # mm/s² along the block
    vmax: float = 0.0  # mm/s
    t1: float = 0.0  # end of the ramp up
    t2: float = 0.0  # end of the cruise
    t3: float = 0.0  # end of the block
    vp: float = 0.0  # peak speed
    stopping: tuple[float, float, float] | None = None  # (t, s, v) of a hold / jog cancel

    def plan(self, pos, now, accel_of):
        self.start = list(pos)
        self.t0 = now
        d = [e - s for s, e in zip(self.start, self.target, strict=True)]
        self.length = math.sqrt(sum(v * v for v in d))
        self.stopping = None
        if self.length <= 0:
            self.t1 = self.t2 = self.t3 = 0.0
            return
        u = [v / self.length for v in d]
        self.accel = min(accel_of(i) / abs(u[i]) for i in range(3) if abs(u[i]) > 1e-12)
        self.vmax = self.feed / 60.0
        a, L = self.accel, self.length
        vp = min(self.vmax, math.sqrt(a * L))  # triangle when the block is short
        d1 = vp * vp / (2 * a)
        self.vp = vp
        self.t1 = vp / a
        self.t2 = self.t1 + (L - 2 * d1) / vp
        self.t3 = self.t2 + vp / a

    def sv(self, now) -> tuple[float, float]:
        """Distance along the block and speed (mm, mm/s) at sim time ``now``."""
        if self.length <= 0:
            return 0.0, 0.0
        a = self.accel
        if self.stopping is not None:
            ts, ss, vs = self.stopping
            tau = min(max(now - ts, 0.0), vs / a)
            return min(ss + vs * tau - 0.5 * a * tau * tau, self.length), vs - a * tau
        tau = now - self.t0
        if tau <= 0:
            return 0.0, 0.0
        if tau < self.t1:
            return 0.5 * a * tau * tau, a * tau
        d1 = 0.5 * a * self.t1 * self.t1
        if tau < self.t2:
            return d1 + self.vp * (tau - self.t1), self.vp
        if tau < self.t3:
            r = tau - self.t2
            return d1 + self.vp * (self.t2 - self.t1) + self.vp * r - 0.5 * a * r * r, (
                self.vp - a * r
            )
        return self.length, 0.0

    def done(self, now) -> bool:
        if self.stopping is not None:
            ts, _, vs = self.stopping
            return now - ts >= vs / self.accel
        return now - self.t0 >= self.t3

    def point(self, s: float) -> list[float]:
        if self.length <= 0:
            return list(self.target)
        f = s / self.length
        return [a + f * (b - a) for a, b in zip(self.start, self.target, strict=True)]


class GrblSimulator:
    """A simulated GRBL 1.1h controller served on a pseudo-terminal.

    Parameters
    ----------
    faults : FaultPlan or str, optional
        Injected faults (see the module docstring).
    link : str, optional
        Path of a symlink kept pointing at the current slave device (stable across a
        simulated disconnect).
    settings : dict, optional
        ``$n`` settings overriding :data:`DEFAULT_SETTINGS` (e.g. ``{22: 1}`` homing).
    time_scale : float
        The controller runs this many times faster than real time (motion, dwells, homing,
        the 0.5 s alarm pause, byte timing); 0.5 is a controller at half clock.
    reconnect_after : float
        Seconds the line stays away after a ``disconnect`` / ``power-loss`` fault.
    encoders : bool
        Enable the ``$ENC`` extension (instruments with carriage encoders).
    """

    def __init__(
        self,
        faults: FaultPlan | str | None = None,
        *,
        link: str | None = None,
        settings: dict | None = None,
        time_scale: float = 1.0,
        reconnect_after: float = 0.3,
        encoders: bool = False,
    ):
        self.plan = faults if isinstance(faults, FaultPlan) else parse_faults(faults)
        self.link = link
        self.settings = dict(DEFAULT_SETTINGS)
        self.settings.update(settings or {})
        self.time_scale = float(time_scale)
        self.reconnect_after = reconnect_after
        self.encoders = encoders
        self.master = None
        self.slave = None
        self.slave_path = None
        self._thread = None
        self._running = False
        self._lock = threading.RLock()
        self._t_real0 = time.monotonic()
        self._out: deque[tuple[float, bytes]] = deque()
        #: the last lines the controller emitted: (controller time it was due, text)
        self.emitted: deque[tuple[float, str]] = deque(maxlen=256)
        self._in: deque[tuple[float, int]] = deque()
        self._tx_free = 0.0
        self._rx_last = 0.0
        self.pos = [0.0, 0.0, 0.0]  # machine mm (what MPos reports)
        self.phys = [0.0, 0.0, 0.0]  # physical carriage, switch frame (what $ENC reports)
        self.coords = {n: [0.0, 0.0, 0.0] for n in range(1, 7)}  # G54..G59 (EEPROM)
        self.g28 = [0.0, 0.0, 0.0]
        self.g30 = [0.0, 0.0, 0.0]
        self.startup = ["", ""]  # $N0, $N1 (EEPROM)
        self.build_info = ""  # $I=... (EEPROM)
        self.pins = ""  # input pins triggered (Pn:)
        self.log: list[str] = []  # every line received (diagnostics for tests)
        self.realtime_log: set[int] = set()  # the real-time bytes received
        self.moves = 0
        self.boots = 0
        self.state = "Idle"
        self._power_up()

    # ------------------------------------------------------------------ lifecycle
    @property
    def path(self) -> str:
        """Device path for clients: the ``link`` if given, else the current slave path."""
        return self.link or self.slave_path

    def start(self) -> str:
        """Open the pty and serve it from a background thread; returns :attr:`path`."""
        self._open_pty()
        self._running = True
        self._thread = threading.Thread(target=self._serve, name="grbl-sim", daemon=True)
        self._thread.start()
        return self.path

    def stop(self) -> None:
        """Stop serving and close the pty."""
        self._running = False
        if self._thread is not None:
            self._thread.join(timeout=2)
            self._thread = None
        self._close_pty()
        if self.link and os.path.islink(self.link):
            os.unlink(self.link)

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        self.stop()

    def _open_pty(self):
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)
        os.set_blocking(self.master, False)
        self.slave_path = os.ttyname(self.slave)
        if self.link:
            tmp = self.link + ".tmp"
            if os.path.lexists(tmp):
                os.unlink(tmp)
            os.symlink(self.slave_path, tmp)
            os.replace(tmp, self.link)

    def _close_pty(self):
        for fd in (self.master, self.slave):
            if fd is not None:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self.master = self.slave = None

    def now(self) -> float:
        """Controller time, s (real time scaled by ``time_scale``)."""
        return (time.monotonic() - self._t_real0) * self.time_scale

    # ------------------------------------------------------------------ controller state
    def _power_up(self):
        """Boot: machine position 0 (unknown), volatile state cleared, EEPROM kept."""
        self.boots += 1
        self.pos = [0.0, 0.0, 0.0]
        self.g92 = [0.0, 0.0, 0.0]
        self.state = "Alarm" if self.settings[22] else "Idle"
        self.critical = False
        self.pause_until = None
        self.pending_reset = False
        self.pending_status = False
        self.late: list[str] = []  # replies owed for lines cut short by an alarm
        self._after_pause = None
        self._soft_reset_state()
        self._boot_messages()

    def _boot_messages(self):
        self._emit(f"\r\n{BANNER}")
        if self.state == "Alarm":
            self._emit("[MSG:'$H'|'$X' to unlock]")
        else:
            self._run_startup()

    def _run_startup(self):
        for ln in self.startup:
            if ln:
                r = self._line(ln)
                self._emit(f">{ln}:{r or 'ok'}")

    def _soft_reset_state(self):
        self.rx = bytearray()
        self.lines: deque[bytes] = deque()
        self.planner: deque[_Block] = deque()
        self.current: _Block | None = None
        self.hold = False
        self.home_until = None
        self.home_fail = None
        self.sync_line = None  # a line waiting for motion to finish
        self.dwell_until = None
        self.modal_abs = True
        self.modal_motion = 0
        self.coord = 1  # G54
        self.feed = 0.0
        self.inch = False
        self.check = False
        self.reports_since_wco = 0
        self.report_count = 0
        self.wco_dirty = True
        self.cancel_jog = False

    @property
    def wco(self) -> list[float]:
        """Work coordinate offset: active G54..G59 + G92 (machine mm)."""
        return [c + g for c, g in zip(self.coords[self.coord], self.g92, strict=True)]

    def _emit(self, text: str, *, immediate: bool = False):
        delay = 0.0 if immediate else self.plan.slow * self.time_scale
        due = self.now() + delay
        self._out.append((due, (text + "\r\n").encode()))
        self.emitted.append((due, text))

    @property
    def moving(self) -> bool:
        return self.current is not None or bool(self.planner)

    def _accel(self, i: int) -> float:
        return float(self.settings[120 + i])

    # ------------------------------------------------------------------ serving loop
    def _serve(self):
        while self._running:
            try:
                self._step()
            except OSError as exc:  # pragma: no cover - defensive
                if exc.errno not in (errno.EIO, errno.EBADF):
                    raise
                time.sleep(0.01)

    def _step(self):
        if self.master is None:
            time.sleep(0.002)
            with self._lock:
                self._advance()
                self._time_faults()
            return
        r, _, _ = select.select([self.master], [], [], 0.002)
        if r:
            try:
                data = os.read(self.master, 1024)
            except BlockingIOError:
                data = b""
            except OSError as exc:
                if exc.errno == errno.EIO:
                    data = b""
                else:
                    raise
            now = self.now()
            for b in data:  # bytes arrive at the baud rate
                self._rx_last = max(self._rx_last, now) + BYTE_TIME
                self._in.append((self._rx_last, b))
        with self._lock:
            now = self.now()
            while self._in and self._in[0][0] <= now:
                self._byte(self._in.popleft()[1])
            self._advance()
            self._time_faults()
            if not self._paused():
                self._process_lines()
            # under the lock: a reboot() from another thread clears and refills the queue, and
            # an unlocked flush could pop the new banner in place of the chunk it had written
            self._flush_out()

    def _flush_out(self):
        now = self.now()
        while self._out and self._out[0][0] <= now and self._tx_free <= now:
            if self.master is None:
                return
            t, chunk = self._out[0]
            try:
                n = os.write(self.master, chunk)
            except BlockingIOError:
                return
            except OSError:
                self._out.clear()
                return
            self._tx_free = max(self._tx_free, now) + n * BYTE_TIME
            if n < len(chunk):
                self._out[0] = (t, chunk[n:])
                return
            self._out.popleft()

    # ------------------------------------------------------------------ the alarm pause
    def _paused(self) -> bool:
        if self.pause_until is None:
            return False
        if self.now() < self.pause_until:
            return True
        self.pause_until = None
        after, self._after_pause = self._after_pause, None
        if after is not None:
            if after == self._reinit:
                self.pending_status = False  # the reset in progress drops a pending '?'
            after()
        if self.pause_until is not None:
            return True
        if self.pending_reset:
            self.pending_reset = False
            self.pending_status = False  # a reset drops a pending '?'
            self._reset()
        elif self.pending_status:
            self.pending_status = False
            if not self.critical:  # a critical alarm answers nothing, not even '?'
                self._status()
        return self.pause_until is not None

    def _alarm(self, code: int, after=None):
        """Report ``ALARM:code`` and pause 0.5 s (controller time), then run ``after``."""
        self._emit(f"ALARM:{code}", immediate=True)
        self.state = "Alarm"
        self.pause_until = self.now() + ALARM_PAUSE
        self._after_pause = after

    # ------------------------------------------------------------------ input
    def _byte(self, b: int):
        if b in (0x3F, 0x21, 0x7E, 0x18, 0x85):
            self.realtime_log.add(b)
        if self._paused():
            if b == 0x18:
                self.pending_reset = True
            elif b == 0x3F:
                self.pending_status = True
            elif b < 0x80 and b not in (0x21, 0x7E):
                self._rx_byte(b)
            return
        if b == 0x18:
            self._reset()
            return
        if self.critical:
            return
        if b == 0x3F:  # '?'
            self._status()
            return
        if b == 0x21:  # '!'
            self._feed_hold()
            return
        if b == 0x7E:  # '~'
            if self.hold and not self._decelerating():
                self.hold = False
                if self.current is not None:
                    self.current.start = None  # restarts from rest where it stopped
                self.state = "Run" if self.moving else "Idle"
            return
        if b == 0x85:
            if self.state == "Jog":
                self._cancel_jog()
            return
        if b >= 0x80:
            return  # overrides etc.: accepted, not simulated
        self._rx_byte(b)

    def _rx_byte(self, b: int):
        if len(self.rx) + sum(len(ln) + 1 for ln in self.lines) >= RX_BUFFER - 1:
            return  # RX overflow: byte lost, as on the AVR
        if b in (0x0A, 0x0D):
            self.lines.append(bytes(self.rx))
            self.rx.clear()
        else:
            self.rx.append(b)

    def _feed_hold(self):
        if self.state == "Jog":
            self._cancel_jog()  # a hold during a jog cancels it
        elif self.state == "Run" and not self.hold:
            self.hold = True
            self._decelerate()
            self.state = "Hold"
        elif self.state == "Idle":
            self.hold = True
            self.state = "Hold"

    def _cancel_jog(self):
        """Jog cancel: decelerate to a stop, then flush the jogs (see :meth:`_advance`)."""
        if self.cancel_jog:
            return
        blk = self.current
        if blk is not None and blk.start is not None and blk.length > 0:
            self.cancel_jog = True
            self._decelerate()
            return
        self.current = None
        self.planner = deque(b for b in self.planner if not b.jog)
        self.state = "Run" if self.planner else "Idle"

    def _decelerate(self):
        blk, now = self.current, self.now()
        if blk is None or blk.start is None or blk.length <= 0:
            return
        s, v = blk.sv(now)
        blk.stopping = (now, s, v)

    def _decelerating(self) -> bool:
        blk = self.current
        return blk is not None and blk.stopping is not None and not blk.done(self.now())

    def _reset(self):
        """Soft reset (0x18): stop; ALARM:3 if moving (6 while homing); re-initialise."""
        if self.home_until is not None:
            code = 6
        elif (
            self.current is not None
            and self.current.start is not None
            and (not self.hold or self._decelerating())
        ):
            code = 3
        else:
            code = None
        self._freeze()
        self.current = None
        self.planner.clear()
        self.home_until = None
        if code is not None:
            self._alarm(code, after=self._reinit)
        else:
            self._reinit()

    def _reinit(self):
        """The firmware's reset loop: late replies, buffers flushed, banner."""
        for r in self.late:
            self._emit(r)
        self.late = []
        alarm = self.state == "Alarm" or self.critical
        self.critical = False
        self._soft_reset_state()
        self.g92 = [0.0, 0.0, 0.0]
        self.state = "Alarm" if alarm else "Idle"
        self._boot_messages()

    def _status(self):
        if self.home_until is not None:
            return  # no report during homing
        now = self.now()
        st = self.state
        if self.hold and st == "Hold":
            st = "Hold:1" if self._decelerating() else "Hold:0"
        fields = [st]
        mask = int(self.settings[10])
        pos = self._live_pos(now)
        wco = self.wco
        pos = pos if mask & 1 else [p - w for p, w in zip(pos, wco, strict=True)]
        fields.append(("MPos:" if mask & 1 else "WPos:") + ",".join(f"{v:.3f}" for v in pos))
        if mask & 2:
            free_blocks = PLANNER_BLOCKS - len(self.planner) - (1 if self.current else 0)
            rx_used = len(self.rx) + sum(len(ln) + 1 for ln in self.lines)
            fields.append(f"Bf:{max(free_blocks, 0)},{RX_BUFFER - 1 - rx_used}")
        v = 0.0
        if self.current is not None and self.current.start is not None:
            v = self.current.sv(now)[1]
        fields.append(f"FS:{int(round(v * 60))},0")
        if self.pins:
            fields.append("Pn:" + self.pins)
        busy = self.moving
        if self.wco_dirty or self.reports_since_wco >= (30 if busy else 10):
            fields.append("WCO:" + ",".join(f"{v:.3f}" for v in wco))
            self.wco_dirty = False
            self.reports_since_wco = 0
        else:
            self.reports_since_wco += 1
        self.report_count += 1
        if self.report_count == 2:
            fields.append("Ov:100,100,100")
        self._emit("<" + "|".join(fields) + ">")

    def _live_pos(self, now) -> list[float]:
        blk = self.current
        if blk is None or blk.start is None:
            return list(self.pos)
        return self._quant(blk.point(blk.sv(now)[0]))

    def _quant(self, p):
        out = []
        for i in range(3):
            spm = self.settings[100 + i]
            out.append(round(p[i] * spm) / spm)
        return out

    # ------------------------------------------------------------------ lines
    def _process_lines(self):
        while self.lines and not self.critical and self.pause_until is None:
            if self.sync_line is not None or self.home_until is not None or self.hold:
                return  # the main loop is busy (sync, homing) or suspended (feed hold)
            if len(self.planner) + (1 if self.current else 0) >= PLANNER_BLOCKS:
                return  # planner full: hold the ok back
            raw = self.lines[0]
            line = raw.decode("ascii", "replace")
            stripped = re.sub(r"\([^)]*\)|;.*$", "", line).replace(" ", "").upper()
            if _needs_sync(stripped) and self.moving:
                return  # EEPROM writes wait for the motion to end
            self.lines.popleft()
            self.log.append(line)
            reply = self._line(line)
            if reply is not None:
                self._emit(reply)

    def _line(self, line: str) -> str | None:
        stripped = re.sub(r"\([^)]*\)|;.*$", "", line).replace(" ", "").upper()
        if len(stripped) >= LINE_MAX:
            return "error:11"
        if not stripped:
            return "ok"
        if stripped.startswith("$"):
            return self._dollar(stripped)
        if self.state == "Alarm":
            return "error:9"
        if self.state == "Jog":
            return "error:9"
        return self._gcode(stripped, jog=False)

    def _dollar(self, s: str) -> str | None:
        if s.startswith("$J="):
            if self.state not in ("Idle", "Jog"):
                return "error:8"
            return self._gcode(s[3:], jog=True)
        if s == "$X":
            if self.state == "Alarm":
                self.state = "Idle"
                self._emit("[MSG:Caution: Unlocked]")
            return "ok"
        if s == "$H":
            if not self.settings[22]:
                return "error:5"
            if self.state not in ("Idle", "Alarm"):
                return "error:8"
            self._start_homing()
            return None  # ok when homing is done
        if s == "$$":
            if self.state in ("Run", "Hold"):
                return "error:8"
            for k in sorted(self.settings):
                v = self.settings[k]
                self._emit(f"${k}={v:.3f}" if isinstance(v, float) else f"${k}={v}")
            return "ok"
        if s == "$C":
            if self.check:
                self.check = False
                self._emit("[MSG:Disabled]")
                self._emit("ok")
                self.state = "Idle"
                self._reinit()  # leaving check mode resets the controller
                return None
            if self.state != "Idle":
                return "error:8"
            self.check = True
            self.state = "Check"
            self._emit("[MSG:Enabled]")
            return "ok"
        if s == "$N":
            for i, ln in enumerate(self.startup):
                self._emit(f"$N{i}={ln}")
            return "ok"
        m = re.fullmatch(r"\$N([01])=(.*)", s)
        if m:
            if self.state not in ("Idle", "Alarm"):
                return "error:8"
            self.startup[int(m[1])] = m[2]
            return "ok"
        if s.startswith("$I="):
            self.build_info = s[3:]
            return "ok"
        m = re.fullmatch(r"\$(\d+)=([-+0-9.]+)", s)
        if m:
            k = int(m[1])
            if k not in self.settings:
                return "error:3"
            if self.state not in ("Idle", "Alarm"):
                return "error:8"
            v = float(m[2])
            if k == 20 and v and not self.settings[22]:
                return "error:10"
            self.settings[k] = v if isinstance(DEFAULT_SETTINGS.get(k), float) else int(v)
            return "ok"
        if s == "$I":
            self._emit(f"[VER:1.1h.20190830:{self.build_info}]")
            self._emit("[OPT:V,15,128]")
            return "ok"
        if s == "$G":
            dist = "G90" if self.modal_abs else "G91"
            unit = "G20" if self.inch else "G21"
            motion = f"G{self.modal_motion}"
            self._emit(
                f"[GC:{motion} G{53 + self.coord} G17 {unit} {dist} G94 M5 M9 T0 F{self.feed:g} S0]"
            )
            return "ok"
        if s == "$#":
            for n in range(1, 7):
                self._emit(f"[G{53 + n}:" + ",".join(f"{v:.3f}" for v in self.coords[n]) + "]")
            self._emit("[G28:" + ",".join(f"{v:.3f}" for v in self.g28) + "]")
            self._emit("[G30:" + ",".join(f"{v:.3f}" for v in self.g30) + "]")
            self._emit("[G92:" + ",".join(f"{v:.3f}" for v in self.g92) + "]")
            self._emit("[TLO:0.000]")
            self._emit("[PRB:0.000,0.000,0.000:0]")
            return "ok"
        if s == "$ENC" and self.encoders:
            self._emit("[ENC:" + ",".join(f"{v:.3f}" for v in self.phys[:2]) + "]")
            return "ok"
        if s == "$":
            self._emit("[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]")
            return "ok"
        if len(s) > 1 and s[1].isalpha():
            return "error:2"  # an unknown letter command: the parser wants a number
        return "error:3"

    def _start_homing(self):
        """Homing toward + on every axis: seek to the switch, locate, pull off ``$27``."""
        self.state = "Home"
        seek, feed, pull = self.settings[25] / 60.0, self.settings[24] / 60.0, self.settings[27]
        dist = max(0.0, *(-p for p in self.phys))
        t = dist / seek + 2 * pull / feed + 2 * pull / seek + self.settings[26] / 1000.0
        self.home_until = self.now() + t
        self.home_fail = None
        for fl in self.plan.faults:
            if fl.kind == "homing-fail" and not fl.fired:
                fl.fired = True
                self.home_fail = int(fl.value)
                self.home_until = self.now() + min(t, 0.5)
                break

    def _gcode(self, s: str, *, jog: bool) -> str | None:
        words = re.findall(r"([A-Z])([-+]?[0-9]*\.?[0-9]*)", s)
        if "".join(a + b for a, b in words) != s:
            return "error:2" if s[0].isalpha() else "error:1"
        g_motion = None
        absolute = self.modal_abs
        inch = self.inch
        axes: dict[str, float] = {}
        feed = None
        p = None
        l_word = None
        g10 = g28 = None
        coord = self.coord
        for letter, num in words:
            if num in ("", "+", "-", "."):
                return "error:2"
            v = float(num)
            if letter == "G":
                if jog and v not in (20, 21, 90, 91, 53):
                    return "error:16"
                if v in (0, 1):
                    g_motion = int(v)
                elif v == 4:
                    g_motion = 4
                elif v == 10:
                    g10 = True
                elif v in (28.1, 30.1):
                    g28 = v
                elif v == 90:
                    absolute = True
                elif v == 91:
                    absolute = False
                elif v == 20:
                    inch = True
                elif v == 21:
                    inch = False
                elif v in (54, 55, 56, 57, 58, 59):
                    coord = int(v) - 53
                elif v in (17, 53, 94):
                    pass
                else:
                    return "error:20"
            elif letter in "XYZ":
                axes[letter] = v
            elif letter == "F":
                if v < 0:
                    return "error:4"
                feed = v
            elif letter == "P":
                p = v
            elif letter == "L":
                l_word = v
            elif letter == "N":
                pass
            elif letter == "M" and not jog:
                if v not in (0, 2, 5, 9, 30):
                    return "error:20"
            else:
                return "error:16" if jog else "error:20"
        scale = 25.4 if inch else 1.0
        if jog:
            if feed is None or feed <= 0:
                return "error:22"
            if not axes:
                return "ok"
            target = self._target(axes, absolute, inch)
            if self._soft_limit_violated(target):
                return "error:15"
            return self._queue(_Block(target, min(feed * scale, self._max_rate(target)), jog=True))
        # modal state of a normal line
        self.modal_abs = absolute
        self.inch = inch
        if coord != self.coord:
            self.coord = coord
            self.wco_dirty = True
        if feed is not None:
            self.feed = feed * scale
        if g10:
            pn = 0 if p is None else int(p)
            if l_word not in (2, 20) or not 0 <= pn <= 6:
                return "error:20"
            n = self.coord if pn == 0 else pn
            for i, a in enumerate("XYZ"):
                if a in axes:
                    if l_word == 20:
                        self.coords[n][i] = self.pos[i] - axes[a] * scale - self.g92[i]
                    else:
                        self.coords[n][i] = axes[a] * scale
            self.wco_dirty = True
            return "ok"
        if g28 is not None:
            (self.g28 if g28 == 28.1 else self.g30)[:] = list(self.pos)
            return "ok"
        if g_motion == 4:
            if p is None or p < 0:
                return "error:2"
            if self.check:
                return "ok"
            self.sync_line = ("dwell", p)
            return None  # ok after motion + dwell
        if g_motion is None:
            g_motion = self.modal_motion
        self.modal_motion = g_motion if g_motion in (0, 1) else 0
        if not axes:
            return "ok"
        target = self._target(axes, absolute, inch)
        if g_motion == 1:
            if self.feed <= 0:
                return "error:22"
            feed = min(self.feed, self._max_rate(target))
        else:
            feed = self._max_rate(target)
        if self.check:
            return "ok"
        if self._soft_limit_violated(target):
            self.late.append("ok")  # this line is answered after the reset
            self._critical_alarm(2)
            return None
        return self._queue(_Block(target, feed))

    def _target(self, axes, absolute, inch):
        base = (
            self.planner[-1].target
            if self.planner
            else (self.current.target if self.current is not None else self.pos)
        )
        t = list(base)
        wco = self.wco
        for i, a in enumerate("XYZ"):
            if a in axes:
                v = axes[a] * (25.4 if inch else 1)
                t[i] = v + wco[i] if absolute else t[i] + v
        return self._quant(t)

    def _soft_limit_violated(self, t) -> bool:
        if not self.settings[20]:
            return False
        return any(not (-self.settings[130 + i] - 1e-9 <= t[i] <= 1e-9) for i in range(3))

    def _max_rate(self, target=None) -> float:
        """The feed cap along a move: each axis at most its ``$11x`` (mm/min)."""
        base = (
            self.planner[-1].target
            if self.planner
            else (self.current.target if self.current is not None else self.pos)
        )
        if target is None:
            return min(self.settings[110], self.settings[111])
        d = [e - s for s, e in zip(base, target, strict=True)]
        L = math.sqrt(sum(v * v for v in d))
        if L <= 0:
            return min(self.settings[110], self.settings[111])
        return min(self.settings[110 + i] * L / abs(d[i]) for i in range(3) if abs(d[i]) > 1e-12)

    def _queue(self, blk: _Block) -> str:
        self.moves += 1
        blk.move_no = self.moves
        self.planner.append(blk)
        if not self.hold:
            self.state = "Jog" if blk.jog else "Run"
        return "ok"

    def _critical_alarm(self, code: int):
        self._freeze()
        self.planner.clear()
        self.current = None
        self.sync_line = None
        self.lines.clear()
        self.rx.clear()
        self.critical = True
        self.hold = False
        self._alarm(code, after=lambda: self._emit("[MSG:Reset to continue]", immediate=True))

    def _freeze(self):
        """Stop the current block where it is now (position kept, block restarts later)."""
        blk = self.current
        if blk is None or blk.start is None:
            return
        self._set_pos(blk.point(blk.sv(self.now())[0]), blk)
        blk.start = None

    def _set_pos(self, new, blk=None):
        new = self._quant(new)
        for i in range(3):
            self.phys[i] += new[i] - self.pos[i]
            self.pos[i] = new[i]
        if blk is not None:
            for fl in self.plan.faults:
                if fl.kind == "lost-steps" and not fl.fired and fl.at_move == blk.move_no:
                    fl.fired = True
                    self.phys[0] -= fl.value / self.settings[100]

    # ------------------------------------------------------------------ time
    def _advance(self):
        now = self.now()
        if self.pause_until is not None:
            return
        if self.home_until is not None:
            if now >= self.home_until:
                self.home_until = None
                if self.home_fail is not None:
                    code, self.home_fail = self.home_fail, None
                    self.late.append("ok")  # the $H line is answered, then an automatic reset
                    for i in range(3):  # somewhere on the way: the position is unknown
                        self.phys[i] = 0.5 * self.phys[i]
                        self.pos[i] = 0.0
                    self._alarm(code, after=self._reinit)
                    return
                pull = self.settings[27]
                for i in range(3):
                    self.pos[i] = -pull
                    self.phys[i] = -pull
                self.pins = ""
                self.state = "Idle"
                self.wco_dirty = True
                self._emit("ok")
            return
        if self.critical:
            return
        while True:
            if self.current is None:
                if not self.planner or self.hold:
                    break
                self.current = self.planner.popleft()
                self.current.start = None
            blk = self.current
            if blk.start is None:
                if self.hold:
                    break
                blk.plan(self.pos, now, self._accel)
                if self._move_faults(blk):
                    return
            if not blk.done(now):
                break
            if blk.stopping is not None:  # a hold or a jog cancel has come to rest
                self._set_pos(blk.point(blk.sv(now)[0]), blk)
                blk.start = None
                if self.cancel_jog:
                    self.cancel_jog = False
                    self.current = None
                    self.planner = deque(b for b in self.planner if not b.jog)
                    self.state = "Run" if self.planner else "Idle"
                    continue
                break  # Hold:0: the rest of the block waits for '~'
            self._set_pos(blk.target, blk)
            self.current = None
        if self.current is None and not self.planner and self.state in ("Run", "Jog"):
            self.state = "Idle"
        if self.sync_line is not None and not self.moving:
            kind, p = self.sync_line
            if self.dwell_until is None:
                self.dwell_until = now + p
            if now >= self.dwell_until:
                self.sync_line = None
                self.dwell_until = None
                self._emit("ok")

    def _move_faults(self, blk) -> bool:
        for fl in self.plan.faults:
            if fl.fired or fl.at_move != blk.move_no:
                continue
            if fl.kind == "alarm":
                fl.fired = True
                self._set_pos(blk.point(0.5 * blk.length))
                blk.start = None
                self.current = None
                self.pins = "X"
                self._critical_alarm(1)
                return True
            if fl.kind == "disconnect":
                fl.fired = True
                self._disconnect()
            elif fl.kind in ("reboot", "power-loss"):
                fl.fired = True
                self._set_pos(blk.point(0.5 * blk.length))
                self.current = None
                self.reboot(power_loss=fl.kind == "power-loss")
                return True
        return False

    def _time_faults(self):
        t = time.monotonic() - self._t_real0
        for fl in self.plan.faults:
            if fl.fired or fl.at_time is None or t < fl.at_time:
                continue
            fl.fired = True
            if fl.kind == "disconnect":
                self._disconnect()
            elif fl.kind == "alarm":
                self.pins = "X"
                self._critical_alarm(1)
            elif fl.kind == "lost-steps":
                self.phys[0] -= fl.value / self.settings[100]
            elif fl.kind in ("reboot", "power-loss"):
                self.reboot(power_loss=fl.kind == "power-loss")

    def reboot(self, power_loss: bool = False) -> None:
        """The controller restarts (reset button, power blip; ``power_loss``: the USB line
        goes away too and comes back after ``reconnect_after``). Motion stops where it is;
        the machine position is lost (MPos 0), EEPROM kept; an unrequested banner."""
        with self._lock:
            self._freeze()
            self.rebooted_at = list(self.phys)  # for tests: where the carriage was
            self._out.clear()
            self._in.clear()
            if power_loss:
                self._disconnect()
            self._power_up()

    def _disconnect(self):
        """The line goes away; a timer brings it back on a new pty.

        The ``link`` disappears with it (as a USB device node does): the freed pty number may
        be reused by another program at once, and nobody must reach that one through it.
        """
        if self.link and os.path.islink(self.link):
            os.unlink(self.link)
        self._close_pty()
        self._out.clear()
        self._in.clear()
        self.rx.clear()
        self.lines.clear()

        def back():
            time.sleep(self.reconnect_after)
            with self._lock:
                if self._running:
                    self._open_pty()

        threading.Thread(target=back, daemon=True).start()

    # ------------------------------------------------------------------ test helpers
    def physical_position(self) -> tuple[float, float]:
        """Physical DX, DY carriage position (mm in the limit-switch frame the machine
        coordinates have after homing): what the encoders read."""
        return (self.phys[0], self.phys[1])

    def inject(self, spec: str) -> None:
        """Add faults at run time (same syntax as ``--faults``; ``@moveN`` counts from now)."""
        with self._lock:
            for fl in parse_faults(spec).faults:
                if fl.at_move is not None:
                    fl.at_move += self.moves
                if fl.at_time is not None:
                    fl.at_time += time.monotonic() - self._t_real0
                self.plan.faults.append(fl)


def _needs_sync(stripped: str) -> bool:
    """EEPROM writes (``$x=``, ``$Nx=``, ``G10``, ``G28.1``/``G30.1``) wait for motion."""
    if stripped.startswith("$"):
        return bool(re.fullmatch(r"\$(\d+|N[01]|I)=.*", stripped))
    return bool(re.search(r"G10(?!\d)|G28\.1|G30\.1", stripped))
