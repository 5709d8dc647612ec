"""Film corrections as data for session tests: exact affine film deformations.

A session stores film corrections as data (:class:`softplot.correction.ScanPhotoMap`: a scan
frame and a :class:`softplot.correction.FilmCorrection` fitted to reference marks). These
helpers make one that reproduces a known affine film deformation exactly (to rounding), so
plotting tests keep their truth: fiducials at the certificate's film mm, "measured" where the
deformation puts them on a scan of ``pixel_mm`` pixels, corrected by the affine fit.
"""

from __future__ import annotations

import numpy as np

from softplot.camera import Camera, Distortion, Fiducial, load_camera
from softplot.correction import FilmCorrection, ScanFrame, ScanPhotoMap
from softplot.geometry.models import ReferenceMarks


def corner_camera(c: float, half: float = 110.0, name: str = "test-affine") -> Camera:
    """A distortion-free certificate with four corner fiducials at +-``half`` film mm."""
    fids = tuple(
        Fiducial(n, x, y, "cross", 1.0, 0.05, 0.1)
        for n, x, y in (("TL", -half, half), ("TR", half, half), ("BR", half, -half),
                        ("BL", -half, -half))
    )
    return Camera(name, "metric", (2 * half + 10, 2 * half + 10), float(c),
                  distortion=Distortion(), fiducials=fids)


def affine_scan_map(camera, D=None, pixel_mm: float = 0.025, size: int = 12001) -> ScanPhotoMap:
    """A :class:`ScanPhotoMap` whose instrument mm are the film deformed by ``D``.

    ``D`` (2, 3): deformed film = ``D[:, :2] @ film + D[:, 2]`` (identity when None). The map
    takes instrument mm (the deformed film, scan-centred) to photo mm through an affine
    correction fitted to the camera's fiducials and its interior orientation.
    """
    cam = load_camera(camera)
    D = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]) if D is None else np.asarray(D, float)
    frame = ScanFrame(size, size, pixel_mm)
    film = cam.fiducial_film()
    px = frame.to_pixel(film @ D[:, :2].T + D[:, 2])
    names = tuple(f.name for f in cam.fiducials)
    marks = ReferenceMarks(None, None, film, px, names)
    fc = FilmCorrection(cam, marks, "affine", (size, size))
    return ScanPhotoMap(fc, frame)
