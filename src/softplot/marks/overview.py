"""Stage 1 of the reseau path: the overview, the reduced scan the coarse stages search.

:func:`reseau_overview` reduces the scan by an integer factor chosen so that a cross line is
about one overview pixel wide (:func:`reseau_factor`; built blockwise and kept in the scan's
own dtype, :func:`softplot.marks.coarse.overview_compact`) and refuses a blank scan. The
hand-over is :class:`ReseauOverview`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softplot.marks import coarse
from softplot.marks.common import blank_check

__all__ = ["ReseauOverview", "reseau_factor", "reseau_overview", "make_overview"]


@dataclass
class ReseauOverview:
    """The reduced scan (hand-over of :func:`reseau_overview`).

    Attributes
    ----------
    image : softplot.marks.coarse.Overview or ndarray
        Grey in [0, 1] (indexed like an array; float32 ndarray for the fiducial path),
        **overview pixel system**: overview pixel
        ``(i, j)`` averages the ``factor x factor`` full-resolution pixels it covers;
        :func:`softplot.marks.coarse.ov_to_full` / ``full_to_ov`` convert positions
        (``x_full = factor * x_ov + (factor - 1) / 2``).
    factor : int
        The reduction factor.
    px_per_mm : float
        Full-resolution pixels per film millimetre the factor was chosen for (dpi / 25.4).
    """

    image: coarse.Overview | np.ndarray
    factor: int
    px_per_mm: float


def reseau_factor(line_px: float, npix: int) -> int:
    """Overview reduction: a cross line (``line_px`` full-resolution px wide) about 0.6-1.2
    overview px wide; at most a few megapixels for a scan of ``npix`` pixels."""
    f = max(1, int(line_px / 0.62))
    # keep the overview to a few megapixels on very large scans
    while npix / (f * f) > 6e6:
        f += 1
    return f


def reseau_overview(scan, line_px: float, px_per_mm: float, name: str) -> ReseauOverview:
    """The overview of ``scan`` for crosses whose lines are ``line_px`` (full-resolution px)
    wide; a blank scan is a :class:`~softplot.marks.common.DetectionError` naming ``name``."""
    return make_overview(scan, reseau_factor(line_px, scan.width * scan.height), px_per_mm,
                         name)


def make_overview(scan, factor: int, px_per_mm: float, name: str,
                  compact: bool = True) -> ReseauOverview:
    """The overview of ``scan`` reduced by ``factor``, stored compactly
    (:func:`softplot.marks.coarse.overview_compact`) or as a float32 array
    (:func:`softplot.marks.coarse.overview`); a blank scan is a
    :class:`~softplot.marks.common.DetectionError` naming ``name``."""
    ov = coarse.overview_compact(scan, factor) if compact else coarse.overview(scan, factor)
    blank_check(ov, name)
    return ReseauOverview(image=ov, factor=factor, px_per_mm=float(px_per_mm))
