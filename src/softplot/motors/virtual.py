"""Virtual motors: the secondary carriage DX, DY moves the left image's sampling position.

On screen there is no plate to move: the floating mark of the left image is drawn (and the
image sampled) at the left film position ``(X + DX, Y + DY)`` instrument mm, mapped into the
scan by the *inverse film correction* (a callable film mm -> left-image pixel supplied by the
caller, e.g. a mesh model's inverse). So the virtual DX, DY act on image coordinates through
exactly the same interface as the stepping motors of an instrument.

Motion is instantaneous by default; ``simulate_time=True`` makes moves take
``distance / max_speed`` of wall-clock time (for demos and tests of non-blocking use).
``slack_steps`` simulates a mechanical backlash of the drive (the plate lags the motor by up
to that many steps after a reversal), so the driver's compensation can be shown to remove it.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from softplot.motors.base import AxisConfig, Motors

__all__ = ["VirtualMotors"]


class VirtualMotors(Motors):
    """Motors that move the left image's sampling position (screen backend).

    Parameters
    ----------
    dx, dy : AxisConfig, optional
        Axis configuration (resolution, travel, speed, backlash compensation).
    image_map : callable, optional
        Inverse film correction of the left scan: ``f(xy (N,2) film mm) -> (N,2) pixel``.
        Without it :meth:`sampling_position` returns left film mm.
    simulate_time : bool
        Moves take ``distance / max_speed`` seconds (default False: instantaneous).
    slack_steps : tuple of int
        Simulated mechanical backlash per axis (steps); the *physical* plate position
        (:meth:`plate_steps`) lags the motor by up to this much after a reversal.
    left_offset : (float, float)
        Fixed offset of the left plate (instrument mm), as the plotter's ``left_offset``.
    """

    def __init__(
        self,
        dx: AxisConfig | None = None,
        dy: AxisConfig | None = None,
        *,
        image_map: Callable[[np.ndarray], np.ndarray] | None = None,
        simulate_time: bool = False,
        slack_steps: tuple[int, int] = (0, 0),
        left_offset: tuple[float, float] = (0.0, 0.0),
    ):
        super().__init__(dx, dy)
        self.image_map = image_map
        self.simulate_time = simulate_time
        self.slack_steps = tuple(int(s) for s in slack_steps)
        self.left_offset = (float(left_offset[0]), float(left_offset[1]))
        self._motor = [0, 0]
        self._phys = [0, 0]  # physical plate steps (slack model)
        self._move = None  # (start motor, end motor, t0, duration)
        self.moves = 0  # number of moves started (diagnostics)

    # -------------------------------------------------------------- backend hooks
    def _start_move(self, motor_steps, speed_mm_s):
        self.moves += 1
        if not self.simulate_time:
            self._settle()
            self._advance(motor_steps)
            self._move = None
            return
        self._settle()
        start = tuple(self._motor)
        dur = max(
            abs(e - s) * ax.resolution_mm / v
            for s, e, ax, v in zip(start, motor_steps, self.axes, speed_mm_s, strict=True)
        )
        self._move = (start, tuple(motor_steps), time.monotonic(), dur)

    def _advance(self, motor_steps):
        """Set the motor to ``motor_steps`` and drag the physical plate through the slack."""
        for i, m in enumerate(motor_steps):
            slack = self.slack_steps[i]
            # plate stays within [motor, motor + slack]: pushed when the motor leaves that band
            if self._phys[i] < m:
                self._phys[i] = m
            elif self._phys[i] > m + slack:
                self._phys[i] = m + slack
            self._motor[i] = int(m)

    def _settle(self):
        """Bring the simulated motion up to the present time."""
        mv = self._move
        if mv is None:
            return
        start, end, t0, dur = mv
        f = 1.0 if dur <= 0 else min((time.monotonic() - t0) / dur, 1.0)
        now = tuple(int(round(s + f * (e - s))) for s, e in zip(start, end, strict=True))
        self._advance(now)
        if f >= 1.0:
            self._move = None

    def _busy(self):
        if self._move is None:
            return False
        with self._lock:
            self._settle()
            return self._move is not None

    def _halt(self):
        self._settle()
        self._move = None

    def _motor_steps(self):
        self._settle()
        return tuple(self._motor)

    def _home(self):
        self._move = None
        self._advance((0, 0))
        self._phys = [0, 0]

    def wait(self, timeout: float | None = None) -> bool:
        if self._move is None:
            return True
        return self._wait_idle(timeout)

    # -------------------------------------------------------------- screen side
    def plate_steps(self) -> tuple[int, int]:
        """Physical plate position in steps (equals :meth:`position_steps` when the
        simulated slack is compensated by the configured ``backlash_steps``)."""
        self._settle()
        return tuple(self._phys)

    def left_film(self) -> tuple[float, float]:
        """Left film position under the floating mark: main carriage + ``left_offset`` +
        DX, DY (instrument mm)."""
        dx, dy = self.position()
        x, y = self._main
        return (x + self.left_offset[0] + dx, y + self.left_offset[1] + dy)

    def sampling_position(self) -> np.ndarray:
        """Where the left image is sampled under the floating mark.

        Returns
        -------
        ndarray, shape (2,)
            Left-image pixel (x right, y down) through ``image_map``; left film mm if no
            ``image_map`` was given.
        """
        xy = np.asarray([self.left_film()], dtype=float)
        if self.image_map is None:
            return xy[0]
        return np.asarray(self.image_map(xy), dtype=float).reshape(-1, 2)[0]
