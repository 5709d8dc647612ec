"""Orientation: interior, resection, intersection, projection centres, relative, absolute.

Imports :mod:`softplot.geometry` and :mod:`softplot.adjust` only (plus base modules).
"""

from softplot.orientation.absolute import AbsoluteOrientation, absolute_orientation  # noqa: F401
from softplot.orientation.intersection import Intersection, intersect, intersect_pair  # noqa: F401
from softplot.orientation.relative import RelativeOrientation, relative_orientation  # noqa: F401
from softplot.orientation.resection import Resection, resect  # noqa: F401
from softplot.orientation.two_planes import (  # noqa: F401
    differential,
    fiducial_resection,
    principal_distance,
    two_planes,
)
