"""Stereo restitution: the stereo model, the four modes, the plotter loop and sessions.

Imports :mod:`softplot.orientation` (and through it :mod:`softplot.geometry`), the motor
interface and the feature data model.
"""

from softplot.stereo.model import (  # noqa: F401
    FastStereo,
    OrientedPhoto,
    Restitution,
    StereoModel,
)
from softplot.stereo.plotter import MODES, Cycle, Plotter, PlotterHalted  # noqa: F401
from softplot.stereo.session import Session  # noqa: F401
