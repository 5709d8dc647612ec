"""Reseau-cross and fiducial-mark detection to the accuracy limit.

``detect(scan, camera, ...) -> Detection``: coarse NCC search on a reduced overview, robust grid
fit with row/col assignment, prediction of every mark, and least-squares template matching of
an analytic blurred-mark model at full resolution (see :mod:`softplot.marks.detect`).
Imports :mod:`softplot.camera`, :mod:`softplot.io` and :mod:`softplot.errors` only.
"""

from softplot.marks.detect import DetectionError, detect  # noqa: F401
from softplot.marks.result import Detection  # noqa: F401

__all__ = ["detect", "Detection", "DetectionError"]
