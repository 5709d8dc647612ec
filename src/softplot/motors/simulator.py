"""A GRBL-1.1-compatible simulated controller on a pseudo-terminal, with injectable faults.

``GrblSimulator().start()`` opens a pty (:func:`os.openpty`), puts it in raw mode and serves
the GRBL 1.1 serial protocol on the master side from a background thread; any serial client
(pyserial included) opens the *slave* path (:attr:`GrblSimulator.path`, or a stable symlink
given as ``link``) exactly as it would open ``/dev/ttyUSB0``. The real serial path of
:class:`~softplot.motors.grbl.GrblMotors` is thus exercised end to end.

What is simulated (the GRBL 1.1 serial protocol as docs/motors.md summarises it):

* lines end with ``\\n`` or ``\\r``; one ``ok`` / ``error:N`` per line, ``\\r\\n`` endings;
  128-byte RX buffer (overflowing bytes are dropped, as on the AVR); 80-char line limit
  (error:11); a 15-block planner: the ``ok`` of a motion line is held back while it is full;
* real-time bytes ``?`` (status), ``!`` (hold), ``~`` (resume), ``0x18`` (soft reset),
  ``0x85`` (jog cancel) picked off as they arrive;
* ``G0``/``G1`` (``F`` modal, mm/min, capped at ``$110``), ``G4 P`` (dwell: ``ok`` after all
  motion and the dwell), ``G90``/``G91``, ``G20``/``G21``, ``G54``, ``G94``, ``G10 L20 P1``
  (work offset), ``$J=`` jogs, ``$H`` (homing toward +, machine position ``-$27`` after it),
  ``$X``, ``$$``, ``$N=v``, ``$I``, ``$G``, ``$#``, ``$C`` is not simulated (error:3);
* status ``<State|MPos:..|Bf:..|FS:..|WCO:..>`` following ``$10`` (MPos/WPos, Bf) and the
  WCO rules (first report after reset, on change, every 10 idle / 30 busy reports);
* alarms: soft limits (``$20=1``; ALARM:2 on G0/G1, error:15 on a jog), hard-limit ALARM:1,
  reset while moving ALARM:3; a critical alarm answers nothing (not even ``?``) until
  ``0x18``; alarm lock after reset and at power-up when homing is enabled (``$22=1``);
* a vendor extension ``$ENC`` answering ``[ENC:dx,dy]`` (mm) with the instrument's own
  carriage encoders, i.e. the *physical* position (differs from MPos after lost steps);
  real GRBL answers ``error:3`` to it.

Motion runs at constant feed (no acceleration ramp) in wall-clock time scaled by
``time_scale``.

Faults (:class:`FaultPlan`, CLI ``--faults``): comma-separated ``NAME[=VALUE][@WHEN]`` with
``WHEN`` = ``moveN`` (during the N-th motion block, 1-based) or ``Ts`` (T seconds after start):

* ``disconnect@...`` - the line goes away (pty closed); it comes back after
  ``reconnect_after`` seconds on a new pty (the ``link`` symlink is updated). The controller
  keeps its state (separately powered).
* ``alarm@...`` - hard limit: motion stops, ALARM:1, ``[MSG:Reset to continue]``.
* ``lost-steps=K@...`` - the X motor (DX) loses K steps during that move: MPos does not know,
  ``$ENC`` does.
* ``slow=S`` - every reply (ok, error, status, messages) leaves S seconds late.
"""

from __future__ import annotations

import errno
import os
import re
import select
import threading
import time
import tty
from collections import deque
from dataclasses import dataclass, field

from softplot.motors.base import MotorError

__all__ = ["GrblSimulator", "FaultPlan", "parse_faults", "BANNER"]

BANNER = "Grbl 1.1h ['$' for help]"
RX_BUFFER = 128
PLANNER_BLOCKS = 15
LINE_MAX = 80

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
    22: 1,
    23: 0,
    24: 25.0,
    25: 500.0,
    26: 250,
    27: 1.0,
    30: 1000,
    31: 0,
    32: 0,
    100: 100.0,
    101: 100.0,
    102: 100.0,
    110: 600.0,
    111: 600.0,
    112: 600.0,
    120: 10.0,
    121: 10.0,
    122: 10.0,
    130: 40.0,
    131: 40.0,
    132: 40.0,
}


@dataclass
class Fault:
    """One injected fault: ``kind`` in disconnect|alarm|lost-steps|slow."""

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


_FAULT_RE = re.compile(
    r"^(?P<kind>disconnect|alarm|lost-steps|slow)(?:=(?P<val>[-+0-9.eE]+))?"
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
                f"bad fault {item!r}: use disconnect@WHEN, alarm@WHEN, lost-steps=K@WHEN or "
                "slow=SECONDS, WHEN = moveN or Ts"
            )
        kind = m["kind"]
        val = float(m["val"]) if m["val"] else (1.0 if kind == "lost-steps" else 0.0)
        at_move = int(m["move"]) if m["move"] else None
        at_time = float(m["t"]) if m["t"] else None
        if kind != "slow" and at_move is None and at_time is None:
            raise MotorError(f"fault {item!r} needs a trigger @moveN or @Ts")
        if kind == "slow" and not val > 0:
            raise MotorError(f"fault {item!r}: slow needs a delay in seconds > 0, e.g. slow=0.2")
        plan.faults.append(Fault(kind, val, at_move, at_time))
    return plan


@dataclass
class _Block:
    target: list[float]  # machine mm, 3 axes
    feed: float  # mm/min
    jog: bool = False
    dwell: float = 0.0  # seconds (dwell block when > 0 or target None)
    move_no: int = 0
    start: list[float] | None = None
    t0: float = 0.0
    duration: float = 0.0


class GrblSimulator:
    """A simulated GRBL 1.1 controller served on a pseudo-terminal.

    Parameters
    ----------
    faults : FaultPlan or str, optional
        Injected faults (see the module docstring).
    link : str, optional
        Path of a symlink kept pointing at the current slave device (stable across a
        simulated disconnect).
    settings : dict, optional
        ``$n`` settings overriding :data:`DEFAULT_SETTINGS` (e.g. ``{22: 0}`` no homing).
    time_scale : float
        Simulated motion runs this many times faster than real time.
    reconnect_after : float
        Seconds the line stays away after a ``disconnect`` fault.
    """

    def __init__(
        self,
        faults: FaultPlan | str | None = None,
        *,
        link: str | None = None,
        settings: dict | None = None,
        time_scale: float = 1.0,
        reconnect_after: float = 0.3,
    ):
        self.plan = faults if isinstance(faults, FaultPlan) else parse_faults(faults)
        self.link = link
        self.settings = dict(DEFAULT_SETTINGS)
        self.settings.update(settings or {})
        self.time_scale = float(time_scale)
        self.reconnect_after = reconnect_after
        self.master = None
        self.slave = None
        self.slave_path = None
        self._thread = None
        self._running = False
        self._lock = threading.RLock()
        self._out: deque[tuple[float, bytes]] = deque()
        self._t_start = time.monotonic()
        self.pos = [0.0, 0.0, 0.0]  # machine mm (what MPos reports)
        self.phys = [0.0, 0.0, 0.0]  # physical carriage (what $ENC reports)
        self.wco = [0.0, 0.0, 0.0]
        self.log: list[str] = []  # every line received (diagnostics for tests)
        self.moves = 0
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

    # ------------------------------------------------------------------ controller state
    def _power_up(self):
        self.state = "Alarm" if self.settings[22] else "Idle"
        self.critical = False
        self._soft_reset_state()
        self._emit(f"\r\n{BANNER}")
        if self.state == "Alarm":
            self._emit("[MSG:'$H'|'$X' to unlock]")

    def _soft_reset_state(self):
        self.rx = bytearray()
        self.lines: deque[bytes] = deque()
        self.planner: deque[_Block] = deque()
        self.current: _Block | None = None
        self.hold = False
        self.home_until = None
        self.sync_line = None  # a G4 waiting for motion to finish
        self.dwell_until = None
        self.modal_abs = True
        self.feed = 0.0
        self.inch = False
        self.reports_since_wco = 0
        self.report_count = 0
        self.wco_dirty = True
        self._status_pending = False

    def _emit(self, text: str, *, immediate: bool = False):
        delay = 0.0 if immediate else self.plan.slow
        self._out.append((time.monotonic() + delay, (text + "\r\n").encode()))

    @property
    def moving(self) -> bool:
        return self.current is not None or bool(self.planner)

    def _mm(self, v: float) -> float:
        return v * 25.4 if self.inch else v

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
            for b in data:
                self._byte(b)
        with self._lock:
            self._advance()
            self._time_faults()
            self._process_lines()
        self._flush_out()

    def _flush_out(self):
        now = time.monotonic()
        while self._out and self._out[0][0] <= now and self.master is not None:
            t, chunk = self._out[0]
            try:
                n = os.write(self.master, chunk)
            except BlockingIOError:
                return
            except OSError:
                self._out.clear()
                return
            if n < len(chunk):
                self._out[0] = (t, chunk[n:])
                return
            self._out.popleft()

    # ------------------------------------------------------------------ input
    def _byte(self, b: int):
        if b == 0x18:
            self._reset()
            return
        if self.critical:
            return
        if b == 0x3F:  # '?'
            self._status()
            return
        if b == 0x21:  # '!'
            if self.moving and self.state in ("Run", "Jog"):
                if self.state == "Jog":
                    self._cancel_jog()
                else:
                    self._freeze()
                    self.hold = True
                    self.state = "Hold:0"
            return
        if b == 0x7E:  # '~'
            if self.hold:
                self.hold = False
                self._unfreeze()
                self.state = "Run" if self.moving else "Idle"
            return
        if b == 0x85:
            if self.state == "Jog":
                self._cancel_jog()
            return
        if b >= 0x80:
            return  # overrides etc.: accepted, not simulated
        if len(self.rx) + sum(len(ln) + 1 for ln in self.lines) >= RX_BUFFER - 1:
            return  # RX overflow: byte lost, as on the AVR
        if b in (0x0A, 0x0D):
            self.lines.append(bytes(self.rx))
            self.rx.clear()
        else:
            self.rx.append(b)

    def _reset(self):
        was_moving = self.moving and self.state in ("Run", "Jog", "Home") or self.home_until
        if self.current is not None:
            self._freeze()
        if was_moving:
            self._emit("ALARM:3", immediate=True)
            self.state = "Alarm"
        if self.critical:
            self.state = "Alarm"
        self.critical = False
        self._soft_reset_state()
        self._emit(f"\r\n{BANNER}")
        if self.state.startswith("Alarm"):
            self.state = "Alarm"
            self._emit("[MSG:'$H'|'$X' to unlock]")
        elif self.state != "Idle":
            self.state = "Idle"

    def _status(self):
        if self.home_until is not None:
            return  # no report during homing
        fields = [self.state]
        mask = int(self.settings[10])
        pos = self.pos if mask & 1 else [p - w for p, w in zip(self.pos, self.wco, strict=True)]
        fields.append(("MPos:" if mask & 1 else "WPos:") + ",".join(f"{v:.3f}" for v in pos))
        if mask & 2:
            free_blocks = PLANNER_BLOCKS - len(self.planner) - (1 if self.current else 0)
            fields.append(f"Bf:{max(free_blocks, 0)},{RX_BUFFER - len(self.rx)}")
        feed = self.current.feed if self.current is not None and not self.hold else 0
        fields.append(f"FS:{int(round(feed))},0")
        busy = self.moving
        if self.wco_dirty or self.reports_since_wco >= (30 if busy else 10):
            fields.append("WCO:" + ",".join(f"{v:.3f}" for v in self.wco))
            self.wco_dirty = False
            self.reports_since_wco = 0
        else:
            self.reports_since_wco += 1
        self.report_count += 1
        if self.report_count == 2:
            fields.append("Ov:100,100,100")
        self._emit("<" + "|".join(fields) + ">")

    # ------------------------------------------------------------------ lines
    def _process_lines(self):
        while self.lines and not self.critical:
            if self.sync_line is not None or self.home_until is not None:
                return
            if len(self.planner) >= PLANNER_BLOCKS:
                return  # planner full: hold the ok back
            raw = self.lines.popleft()
            try:
                line = raw.decode("ascii", "replace")
            except Exception:  # pragma: no cover
                line = ""
            self.log.append(line)
            reply = self._line(line)
            if reply is not None:
                self._emit(reply)

    def _line(self, line: str) -> str | None:
        stripped = re.sub(r"\([^)]*\)|;.*$", "", line).replace(" ", "").upper()
        if len(stripped) > LINE_MAX:
            return "error:11"
        if not stripped:
            return "ok"
        if stripped.startswith("$"):
            return self._dollar(stripped)
        if self.state.startswith("Alarm"):
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
            if self.state.startswith("Alarm"):
                self.state = "Idle"
                self._emit("[MSG:Caution: Unlocked]")
            return "ok"
        if s == "$H":
            if not self.settings[22]:
                return "error:5"
            if self.state not in ("Idle", "Alarm"):
                return "error:8"
            self.state = "Home"
            travel = max(self.settings[130], self.settings[131])
            self.home_until = time.monotonic() + min(0.05 + travel / 2000.0, 0.3) / self.time_scale
            return None  # ok when homing is done
        if s == "$$":
            if self.state in ("Run",) or self.state.startswith("Hold"):
                return "error:8"
            for k in sorted(self.settings):
                v = self.settings[k]
                self._emit(f"${k}={v:.3f}" if isinstance(v, float) else f"${k}={v}")
            return "ok"
        m = re.fullmatch(r"\$(\d+)=([-+0-9.]+)", s)
        if m:
            k = int(m[1])
            if k not in self.settings:
                return "error:3"
            v = float(m[2])
            if k == 20 and v and not self.settings[22]:
                return "error:10"
            self.settings[k] = v if isinstance(DEFAULT_SETTINGS.get(k), float) else int(v)
            return "ok"
        if s == "$I":
            self._emit("[VER:1.1h.20190830:softplot-sim]")
            self._emit("[OPT:V,15,128]")
            return "ok"
        if s == "$G":
            dist = "G90" if self.modal_abs else "G91"
            unit = "G20" if self.inch else "G21"
            self._emit(f"[GC:G0 G54 G17 {unit} {dist} G94 M5 M9 T0 F{self.feed:g} S0]")
            return "ok"
        if s == "$#":
            self._emit("[G54:" + ",".join(f"{v:.3f}" for v in self.wco) + "]")
            self._emit("[G92:0.000,0.000,0.000]")
            self._emit("[TLO:0.000]")
            self._emit("[PRB:0.000,0.000,0.000:0]")
            return "ok"
        if s == "$ENC":
            self._emit("[ENC:" + ",".join(f"{v:.3f}" for v in self.phys[:2]) + "]")
            return "ok"
        if s == "$":
            self._emit("[HLP:$$ $# $G $I $N $x=val $Nx=line $J=line $SLP $C $X $H ~ ! ? ctrl-x]")
            return "ok"
        return "error:3"

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
        g10 = False
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
                elif v == 90:
                    absolute = True
                elif v == 91:
                    absolute = False
                elif v == 20:
                    inch = True
                elif v == 21:
                    inch = False
                elif v in (17, 53, 54, 94):
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
        if jog:
            if feed is None or feed <= 0:
                return "error:22"
            if not axes:
                return "ok"
            target = self._target(axes, absolute, inch)
            if self._soft_limit_violated(target):
                return "error:15"
            return self._queue(
                _Block(target, min(feed * (25.4 if inch else 1), self._max_rate()), jog=True)
            )
        # modal state of a normal line
        self.modal_abs = absolute
        self.inch = inch
        if feed is not None:
            self.feed = feed * (25.4 if inch else 1)
        if g10:
            if l_word != 20 or p not in (None, 0, 1):
                return "error:20"
            for i, a in enumerate("XYZ"):
                if a in axes:
                    self.wco[i] = self.pos[i] - axes[a] * (25.4 if inch else 1)
            self.wco_dirty = True
            return "ok"
        if g_motion == 4:
            if p is None or p < 0:
                return "error:2"
            self.sync_line = ("dwell", p)
            return None  # ok after motion + dwell
        if g_motion is None:
            g_motion = getattr(self, "_modal_motion", 0)
        self._modal_motion = g_motion if g_motion in (0, 1) else 0
        if not axes:
            return "ok"
        target = self._target(axes, absolute, inch)
        if self._soft_limit_violated(target):
            self._critical_alarm(2)
            return None
        if g_motion == 1:
            if self.feed <= 0:
                return "error:22"
            feed = min(self.feed, self._max_rate())
        else:
            feed = self._max_rate()
        return self._queue(_Block(target, feed))

    def _target(self, axes, absolute, inch):
        base = (
            self.planner[-1].target
            if self.planner
            else (self.current.target if self.current is not None else self.pos)
        )
        t = list(base)
        for i, a in enumerate("XYZ"):
            if a in axes:
                v = axes[a] * (25.4 if inch else 1)
                t[i] = v + self.wco[i] if absolute else t[i] + v
        # quantise to steps
        for i in range(3):
            spm = self.settings[100 + i]
            t[i] = round(t[i] * spm) / spm
        return t

    def _soft_limit_violated(self, t) -> bool:
        if not self.settings[20]:
            return False
        return any(not (-self.settings[130 + i] - 1e-9 <= t[i] <= 1e-9) for i in range(3))

    def _max_rate(self) -> float:
        return min(self.settings[110], self.settings[111])

    def _queue(self, blk: _Block) -> str:
        self.moves += 1
        blk.move_no = self.moves
        self.planner.append(blk)
        if not self.hold:
            self.state = "Jog" if blk.jog else "Run"
        return "ok"

    def _critical_alarm(self, code: int):
        if self.current is not None:
            self._freeze()
        self.planner.clear()
        self.current = None
        self.sync_line = None
        self.lines.clear()
        self.rx.clear()
        self.critical = True
        self.state = "Alarm"
        self._emit(f"ALARM:{code}", immediate=True)
        self._emit("[MSG:Reset to continue]", immediate=True)

    def _cancel_jog(self):
        if self.current is not None:
            self._freeze()
        self.current = None
        self.planner = deque(b for b in self.planner if not b.jog)
        self.state = "Run" if self.planner else "Idle"

    def _freeze(self):
        """Stop the current block where it is now (remaining motion kept for resume)."""
        blk = self.current
        if blk is None or blk.start is None:
            return
        self._move_to_fraction(blk, self._fraction(blk))
        blk.start = None

    def _unfreeze(self):
        pass  # the frozen block restarts from the present position in _advance

    def _fraction(self, blk: _Block) -> float:
        if blk.duration <= 0:
            return 1.0
        return min((time.monotonic() - blk.t0) / blk.duration, 1.0)

    def _move_to_fraction(self, blk: _Block, f: float):
        new = [s + f * (e - s) for s, e in zip(blk.start, blk.target, strict=True)]
        for i in range(3):
            spm = self.settings[100 + i]
            new[i] = round(new[i] * spm) / spm
            d = new[i] - self.pos[i]
            self.pos[i] = new[i]
            self.phys[i] += d
        self._lost_steps_during(blk)

    def _lost_steps_during(self, blk):
        for fl in self.plan.faults:
            if fl.kind == "lost-steps" and not fl.fired and fl.at_move == blk.move_no:
                fl.fired = True
                self.phys[0] -= fl.value / self.settings[100]

    # ------------------------------------------------------------------ time
    def _advance(self):
        now = time.monotonic()
        if self.home_until is not None:
            if now >= self.home_until:
                self.home_until = None
                pull = self.settings[27]
                for i in range(3):
                    self.pos[i] = -pull
                    self.phys[i] = -pull
                self.state = "Idle"
                self.wco_dirty = True
                self._emit("ok")
            return
        if self.hold or self.critical:
            return
        while True:
            if self.current is None:
                if not self.planner:
                    break
                blk = self.planner.popleft()
                self.current = blk
                blk.start = None
            blk = self.current
            if blk.start is None:
                blk.start = list(self.pos)
                blk.t0 = now
                dist = sum((e - s) ** 2 for s, e in zip(blk.start, blk.target, strict=True)) ** 0.5
                blk.duration = dist / blk.feed * 60.0 / self.time_scale if blk.feed > 0 else 0.0
                for fl in self.plan.faults:
                    if fl.fired or fl.at_move != blk.move_no:
                        continue
                    if fl.kind == "alarm":
                        fl.fired = True
                        self.pos = [
                            s + 0.5 * (e - s) for s, e in zip(blk.start, blk.target, strict=True)
                        ]
                        self.phys = list(self.pos)
                        self.current = None
                        self._critical_alarm(1)
                        return
                    if fl.kind == "disconnect":
                        fl.fired = True
                        self._disconnect()
            f = self._fraction(blk)
            if f < 1.0:
                break
            self._move_to_fraction(blk, 1.0)
            self.current = None
        if self.current is None and not self.planner and self.state in ("Run", "Jog"):
            self.state = "Idle"
        if self.sync_line is not None and not self.moving:
            kind, p = self.sync_line
            if self.dwell_until is None:
                self.dwell_until = now + p / self.time_scale
            if now >= self.dwell_until:
                self.sync_line = None
                self.dwell_until = None
                self._emit("ok")

    def _time_faults(self):
        t = time.monotonic() - self._t_start
        for fl in self.plan.faults:
            if fl.fired or fl.at_time is None or t < fl.at_time:
                continue
            fl.fired = True
            if fl.kind == "disconnect":
                self._disconnect()
            elif fl.kind == "alarm":
                self._critical_alarm(1)
            elif fl.kind == "lost-steps":
                self.phys[0] -= fl.value / self.settings[100]

    def _disconnect(self):
        """The line goes away; a timer brings it back on a new pty.

        The ``link`` disappears with it (as a USB device node does): the freed pty number may
        be reused by another program at once, and nobody must reach that one through it.
        """
        if self.link and os.path.islink(self.link):
            os.unlink(self.link)
        self._close_pty()
        self._out.clear()
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
        """Physical DX, DY carriage position (machine mm), what the encoders read."""
        return (self.phys[0], self.phys[1])

    def inject(self, spec: str) -> None:
        """Add faults at run time (same syntax as ``--faults``; ``@moveN`` counts from now)."""
        with self._lock:
            for fl in parse_faults(spec).faults:
                if fl.at_move is not None:
                    fl.at_move += self.moves
                if fl.at_time is not None:
                    fl.at_time += time.monotonic() - self._t_start
                self.plan.faults.append(fl)
