"""Stereo restitution: the stereo model, the four modes and the plotter loop.

Plotting sessions (folders with a journal) are :mod:`softplot.pipeline.session`.

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
