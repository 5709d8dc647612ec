"""The one motor interface of softplot: the left image's secondary carriage DX, DY.

The STEREOBIT/20 moved the *left* plate relative to the floating mark with a secondary
carriage driven by two stepping motors (DX, DY); the operator moved the main carriage (X, Y),
read by encoders. Every coordinate here is **instrument mm** (plate millimetres): DX, DY are
positions of the secondary carriage, X, Y those of the main carriage. Positions live on an
integer step grid (default 0.01 mm per step, the STEREOBIT's encoder resolution): a target
is rounded to the nearest step and :meth:`Motors.position` returns ``steps * resolution``.

Backends implement a handful of protected hooks; this base class does the rest, identically
for the screen (:class:`~softplot.motors.virtual.VirtualMotors`) and for a physical instrument
(:class:`~softplot.motors.grbl.GrblMotors`):

* travel limits (a target outside them raises :class:`MotorLimitError`, nothing moves);
* maximum speed (mm/s, per axis; the backend moves no faster);
* backlash compensation counted in steps: when an axis reverses, the motor is driven
  ``backlash_steps`` further so that the plate, dragged through the slack, lands on the
  target. The compensation lives here, inside the driver, so callers only ever see plate mm;
* ``move_to`` / ``move_by`` blocking (default) or not (``wait=False``), ``wait(timeout)``,
  ``stop``, ``home``.

``motors`` imports nothing of softplot but its own modules and :mod:`softplot.errors`.
"""

from __future__ import annotations

import math
import threading
from abc import ABC, abstractmethod
from dataclasses import dataclass

from softplot.errors import SoftplotError

__all__ = [
    "AXES",
    "AxisConfig",
    "Motors",
    "MotorError",
    "MotorFault",
    "MotorLimitError",
    "MotorTimeout",
    "MotorDisconnected",
    "MotorAlarm",
    "MotorCommandError",
    "LostSteps",
    "MotorPositionLost",
]

#: the driven axes, in order: secondary carriage of the left image
AXES = ("DX", "DY")


class MotorError(SoftplotError):
    """Any problem of the motor layer; the message is one line naming it."""


class MotorLimitError(MotorError):
    """A target outside the travel limits (nothing was moved)."""


class MotorFault(MotorError):
    """The motors stopped or cannot be trusted: alarm, lost steps, lost connection, timeout."""


class MotorTimeout(MotorFault):
    """The controller did not answer (or finish) in time."""


class MotorDisconnected(MotorFault):
    """The serial line went away."""


class MotorAlarm(MotorFault):
    """The controller raised an alarm (``ALARM:N``); ``code`` holds N."""

    def __init__(self, message: str, code: int | None = None):
        super().__init__(message)
        self.code = code


class MotorCommandError(MotorError):
    """The controller rejected a command (``error:N``); ``code`` holds N."""

    def __init__(self, message: str, code: int | None = None):
        super().__init__(message)
        self.code = code


class LostSteps(MotorFault):
    """The encoders disagree with the commanded position by at least one step."""


class MotorPositionLost(MotorFault):
    """The controller's position cannot be trusted (a reboot, a power cycle, an alarm that
    loses steps, a machine position that changed since it was saved): motion is refused
    until the axes are homed again or the operator confirms the position."""


@dataclass(frozen=True)
class AxisConfig:
    """One driven axis.

    Parameters
    ----------
    resolution_mm : float
        Plate mm per motor step (default 0.01 mm, the STEREOBIT's encoders).
    min_mm, max_mm : float
        Travel limits, instrument mm (inclusive).
    max_speed_mm_s : float
        Maximum speed, mm/s.
    backlash_steps : int
        Slack of the drive in steps; compensated on every reversal (0 = none).
    """

    resolution_mm: float = 0.01
    min_mm: float = -20.0
    max_mm: float = 20.0
    max_speed_mm_s: float = 10.0
    backlash_steps: int = 0

    def __post_init__(self):
        if not (self.resolution_mm > 0 and math.isfinite(self.resolution_mm)):
            raise MotorError(f"axis resolution must be > 0 mm, got {self.resolution_mm}")
        if not self.min_mm < self.max_mm:
            raise MotorError(f"axis travel min {self.min_mm} must be below max {self.max_mm}")
        if not self.max_speed_mm_s > 0:
            raise MotorError(f"axis max speed must be > 0 mm/s, got {self.max_speed_mm_s}")
        if self.backlash_steps < 0 or int(self.backlash_steps) != self.backlash_steps:
            raise MotorError(
                f"backlash must be a whole number of steps >= 0, got {self.backlash_steps}"
            )

    @property
    def min_steps(self) -> int:
        return math.ceil(self.min_mm / self.resolution_mm - 1e-9)

    @property
    def max_steps(self) -> int:
        return math.floor(self.max_mm / self.resolution_mm + 1e-9)

    def to_steps(self, mm: float) -> int:
        """Nearest step of a plate position in mm."""
        return int(round(mm / self.resolution_mm))


class Motors(ABC):
    """Abstract motor set: secondary carriage DX, DY (driven) and main carriage X, Y (read).

    Parameters
    ----------
    dx, dy : AxisConfig, optional
        Configuration of the two driven axes.

    Notes
    -----
    Backends implement ``_start_move(motor_steps)`` (begin a move of the *motors* to the
    given step counts, already backlash-compensated), ``_busy()``, ``_halt()``, ``_home()``,
    ``_motor_steps()`` (current motor step counts) and may override ``encoders()``.
    The main carriage X, Y is the operator's: on screen it is set by the GUI or a script
    through :meth:`set_main`; on an instrument a backend may read real encoders.
    """

    def __init__(self, dx: AxisConfig | None = None, dy: AxisConfig | None = None):
        self.axes = (dx or AxisConfig(), dy or AxisConfig())
        self._lock = threading.RLock()
        # plate target (steps) and last move direction per axis (+1 / -1), used for backlash
        self._target = [0, 0]
        self._dir = [1, 1]
        self._main = (0.0, 0.0)
        self._speeds = tuple(a.max_speed_mm_s for a in self.axes)

    # ------------------------------------------------------------------ backend hooks
    @abstractmethod
    def _start_move(self, motor_steps: tuple[int, int], speed_mm_s: tuple[float, float]) -> None:
        """Begin moving the motors to ``motor_steps`` (absolute), at most at ``speed_mm_s``."""

    @abstractmethod
    def _busy(self) -> bool:
        """True while the motors move."""

    @abstractmethod
    def _halt(self) -> None:
        """Stop as soon as possible (motion already under way is abandoned)."""

    @abstractmethod
    def _motor_steps(self) -> tuple[int, int]:
        """Current motor step counts (absolute)."""

    def _home(self) -> None:
        """Home the axes; afterwards the motors stand at step 0 and the slack is taken up
        in the positive direction. Backends with homing switches override this."""
        self._start_move((0, 0), tuple(a.max_speed_mm_s for a in self.axes))

    # ------------------------------------------------------------------ backlash model
    def _plate_from_motor(self, motor: tuple[int, int]) -> tuple[int, int]:
        """Plate steps from motor steps given the slack side of the last move."""
        return tuple(
            m if d > 0 else m + ax.backlash_steps
            for m, d, ax in zip(motor, self._dir, self.axes, strict=True)
        )

    # ------------------------------------------------------------------ public API
    @property
    def resolution(self) -> tuple[float, float]:
        """Plate mm per step of DX, DY."""
        return (self.axes[0].resolution_mm, self.axes[1].resolution_mm)

    def quantize(self, dx: float, dy: float) -> tuple[float, float]:
        """The plate position (mm) the motors would reach for a target ``(dx, dy)`` mm."""
        return tuple(
            ax.to_steps(v) * ax.resolution_mm for ax, v in zip(self.axes, (dx, dy), strict=True)
        )

    def move_to(self, dx: float, dy: float, *, wait: bool = True, timeout: float | None = None):
        """Move the secondary carriage to ``(dx, dy)`` instrument mm.

        Parameters
        ----------
        dx, dy : float
            Target, instrument mm; rounded to the nearest step.
        wait : bool
            Block until the move is complete (default) or return at once.
        timeout : float, optional
            Seconds to wait when ``wait`` (None = no limit); :class:`MotorTimeout` past it.

        Raises
        ------
        MotorLimitError
            The target is outside the travel limits; nothing moves.
        """
        if not (math.isfinite(dx) and math.isfinite(dy)):
            raise MotorLimitError(f"motor target is not finite: DX={dx}, DY={dy}")
        steps = [ax.to_steps(v) for ax, v in zip(self.axes, (dx, dy), strict=True)]
        for name, s, ax in zip(AXES, steps, self.axes, strict=True):
            if not ax.min_steps <= s <= ax.max_steps:
                raise MotorLimitError(
                    f"{name} target {s * ax.resolution_mm:.4f} mm outside travel "
                    f"[{ax.min_mm}, {ax.max_mm}] mm"
                )
        with self._lock:
            if steps != self._target:
                dirs = list(self._dir)
                motor = []
                for i, (s, ax) in enumerate(zip(steps, self.axes, strict=True)):
                    if s > self._target[i]:
                        dirs[i] = 1
                    elif s < self._target[i]:
                        dirs[i] = -1
                    motor.append(s if dirs[i] > 0 else s - ax.backlash_steps)
                self._start_move(tuple(motor), self._speeds)
                self._target = steps
                self._dir = dirs
        if wait and not self.wait(timeout):
            raise MotorTimeout(
                f"move to DX={dx:.4f}, DY={dy:.4f} mm not finished within {timeout} s"
            )

    def move_by(self, ddx: float, ddy: float, *, wait: bool = True, timeout: float | None = None):
        """Move by ``(ddx, ddy)`` mm relative to the current *target* (so repeated small
        relative moves do not accumulate rounding)."""
        tx, ty = self.target()
        self.move_to(tx + ddx, ty + ddy, wait=wait, timeout=timeout)

    def target(self) -> tuple[float, float]:
        """Last commanded plate position, instrument mm."""
        with self._lock:
            return tuple(
                s * ax.resolution_mm for s, ax in zip(self._target, self.axes, strict=True)
            )

    def position(self) -> tuple[float, float]:
        """Current plate position of DX, DY, instrument mm (on the step grid)."""
        with self._lock:
            plate = self._plate_from_motor(self._motor_steps())
            return tuple(s * ax.resolution_mm for s, ax in zip(plate, self.axes, strict=True))

    def position_steps(self) -> tuple[int, int]:
        """Current plate position of DX, DY in whole steps."""
        with self._lock:
            return self._plate_from_motor(self._motor_steps())

    @property
    def busy(self) -> bool:
        """True while the motors move."""
        return self._busy()

    def wait(self, timeout: float | None = None) -> bool:
        """Block until the motors stand still; False if ``timeout`` seconds passed first."""
        return self._wait_idle(timeout)

    def _wait_idle(self, timeout: float | None) -> bool:
        import time

        t_end = None if timeout is None else time.monotonic() + timeout
        while self._busy():
            if t_end is not None and time.monotonic() >= t_end:
                return False
            time.sleep(0.0005)
        return True

    def stop(self) -> None:
        """Stop the motors now; the target becomes the position where they stopped."""
        with self._lock:
            self._halt()
            self._target = list(self._plate_from_motor(self._motor_steps()))

    def home(self, *, timeout: float | None = None) -> None:
        """Home both axes (plate position 0, 0 afterwards)."""
        with self._lock:
            self._dir = [1, 1]
            self._home()
            self._target = [0, 0]
        if not self.wait(timeout):
            raise MotorTimeout(f"homing not finished within {timeout} s")

    # main carriage -------------------------------------------------------------------
    def set_main(self, x: float, y: float) -> None:
        """Set the main carriage X, Y (instrument mm) from operator input (screen/script)."""
        self._main = (float(x), float(y))

    def encoders(self) -> tuple[float, float]:
        """Main carriage X, Y, instrument mm."""
        return self._main

    def state(self) -> dict:
        """Motor state to save in a session: targets, directions, main carriage (and, for a
        controller, the frame its position was in: see :meth:`_reference`)."""
        with self._lock:
            st = {
                "target_steps": list(self._target),
                "direction": list(self._dir),
                "main": list(self._main),
                "resolution_mm": list(self.resolution),
            }
        ref = self._reference()
        if ref is not None:
            st["controller"] = ref
        return st

    def _reference(self) -> dict | None:
        """Backend data that tells whether a saved position is still valid (None: always)."""
        return None

    def _check_reference(self, state: dict) -> None:  # noqa: B027 - optional hook
        """Raise :class:`MotorPositionLost` if ``state`` was saved in another frame than the
        backend's present one (nothing to check by default)."""

    def restore(self, state: dict) -> None:
        """Re-establish a saved :meth:`state`: drive to the saved target (approaching from
        the saved direction so the slack sits on the same side) and set the main carriage.

        Raises
        ------
        MotorPositionLost
            The backend cannot vouch that its position is in the saved frame (e.g. a
            controller that was reset or power-cycled since); nothing moves.
        """
        self._check_reference(state)
        res = self.resolution
        tgt = [s * r for s, r in zip(state["target_steps"], res, strict=True)]
        dirs = state.get("direction", [1, 1])
        pre = [
            t - d * (ax.backlash_steps + 1) * r
            for t, d, ax, r in zip(tgt, dirs, self.axes, res, strict=True)
        ]
        pre = [min(max(p, ax.min_mm), ax.max_mm) for p, ax in zip(pre, self.axes, strict=True)]
        self.move_to(*pre)
        self.move_to(*tgt)
        if "main" in state:
            self.set_main(*state["main"])

    def close(self) -> None:  # noqa: B027 - optional hook, nothing to release by default
        """Release the backend (serial port, threads). Idempotent."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
