"""The motor layer: one interface for the screen and for a physical instrument.

:class:`Motors` (abstract) drives the left image's secondary carriage DX, DY in instrument mm
over integer steps and reads the main carriage X, Y. Backends: :class:`VirtualMotors`
(moves the left image's sampling position) and :class:`GrblMotors` (a GRBL 1.1 controller on
a serial line). :mod:`softplot.motors.simulator` serves a simulated GRBL on a pty.

Imports nothing of softplot but its own modules and :mod:`softplot.errors`.
"""

from softplot.motors.base import (  # noqa: F401
    AXES,
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
from softplot.motors.virtual import VirtualMotors  # noqa: F401


def __getattr__(name):  # GrblMotors imports pyserial: load it on first use
    if name in ("GrblMotors", "GrblStatus", "parse_status"):
        from softplot.motors import grbl

        return getattr(grbl, name)
    raise AttributeError(name)
