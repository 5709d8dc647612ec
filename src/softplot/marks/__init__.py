"""Reseau-cross and fiducial-mark detection to the accuracy limit.

``detect(scan, camera, ...) -> Detection``: coarse NCC search on a reduced overview, robust grid
fit with row/col assignment, prediction of every mark, and least-squares template matching of
an analytic blurred-mark model at full resolution (see :mod:`softplot.marks.detect`).
Imports :mod:`softplot.camera`, :mod:`softplot.io` and :mod:`softplot.errors` only.

Stages (each a module with one hand-over object; :mod:`softplot.marks.detect` runs them in
order, and no stage imports it):

============================  ================================  ===================
module                        hand-over                         owner (development)
============================  ================================  ===================
common                        (errors, grid part, JSON)         reorg
overview                      ReseauOverview                    ident
candidates                    Candidates, WindowCandidates      ident
lattice (+ grid, coarse)      Lattice (grid.GridFit)            ident
prediction                    Prediction                        measure
marksize (+ geometry)         geometry.MarkGeometry             measure
measurement (+ measure, lsm)  Measurement (measure.Fine)        measure
validation                    Validation                        measure
neighbours                    (local fits shared by the above)  measure
scene (+ scene_tv, kernels)   (the scene model's choice)        speed
result, crb, qc               Detection, bounds, QC plot        measure
fiducial                      Detection                         reorg
detect (orchestrator)         Detection                         reorg
============================  ================================  ===================

"(+ ...)": the modules the stage builds on, owned with it.
"""

from softplot.marks.common import DetectionError  # noqa: F401
from softplot.marks.detect import detect  # noqa: F401
from softplot.marks.result import Detection  # noqa: F401

__all__ = ["detect", "Detection", "DetectionError"]
