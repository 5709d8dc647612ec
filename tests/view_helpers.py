"""A synthetic stereo session with scans on disk, for the viewer's tests and benchmarks.

Two vertical photos (c = 150 mm, 1000 m above flat ground, base 300 m) of a distortion-free
camera; each scan is ``size`` x ``size`` px of ``pixel_mm`` whose film is deformed by an exact
affine ``D`` (so film correction, frame and pixels have exact truth: :func:`truth_px`). The
scans hold a coordinate-coded pattern ``(7 col + 3 row) mod 200`` and, around each of
``points`` (object X, Y, Z), a black 41 x 41 px square with one white pixel at the point's
rounded truth pixel (the dots the browser tests find by their centroid).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import tifffile

from session_helpers import corner_camera
from softplot.correction import FilmCorrection, ScanFrame, ScanPhotoMap
from softplot.geometry.models import ReferenceMarks
from softplot.pipeline.session import Session
from softplot.stereo import OrientedPhoto, StereoModel

C = 150.0
X0 = {"left": (0.0, 0.0, 1000.0), "right": (300.0, 0.0, 1000.0)}
ANGLES = {"left": (0.002, -0.003, 0.01), "right": (-0.001, 0.004, -0.02)}
D = {"left": np.array([[1.0002, 0.0003, 0.05], [-0.0002, 0.9998, -0.03]]),
     "right": np.array([[0.9997, -0.0004, -0.04], [0.0001, 1.0003, 0.02]])}
#: object points with a dot in both scans (object units, m)
POINTS = [(150.0, 0.0, 0.0), (120.0, 40.0, 12.5), (185.0, -35.0, -20.0)]


def pattern(h: int, w: int) -> np.ndarray:
    r, c = np.mgrid[0:h, 0:w]
    return ((7 * c + 3 * r) % 200).astype(np.uint8)


def model_and_maps(size: int, pixel_mm: float, scans: dict | None = None):
    cam = corner_camera(C, half=100.0)
    frame = ScanFrame(size, size, pixel_mm)
    maps, photos = {}, {}
    for side in ("left", "right"):
        film = cam.fiducial_film()
        px = frame.to_pixel(film @ D[side][:, :2].T + D[side][:, 2])
        marks = ReferenceMarks(None, None, film, px, tuple(f.name for f in cam.fiducials))
        fc = FilmCorrection(cam, marks, "affine", (size, size))
        maps[side] = ScanPhotoMap(fc, frame, None if scans is None else scans[side])
        photos[side] = OrientedPhoto(X0[side], ANGLES[side], C, name=side.upper(),
                                     to_photo=maps[side], to_film=maps[side].inverse)
    return StereoModel(photos["left"], photos["right"]), maps, frame


def truth_px(model, frame, side: str, XYZ) -> np.ndarray:
    """Exact scan pixel of object points: projection, then the affine film deformation and
    the scan frame (independent of the film-correction code)."""
    photo = model.left if side == "left" else model.right
    film = photo.project(np.atleast_2d(XYZ))  # principal point 0, no distortion
    return frame.to_pixel(film @ D[side][:, :2].T + D[side][:, 2])


def make_session(folder: Path, *, size: int = 1025, pixel_mm: float = 0.2,
                 dtype=np.uint8, points=POINTS, mode: str = "single",
                 height: float | None = None, left_offset=(0.0, 0.0)) -> dict:
    """Write the two scans and the session in ``folder``; returns the truth."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = {s: folder / f"{s}.tif" for s in ("left", "right")}
    model, maps, frame = model_and_maps(size, pixel_mm, paths)
    dots = {}
    for side in ("left", "right"):
        img = pattern(size, size)
        t = truth_px(model, frame, side, points)
        dots[side] = np.rint(t).astype(int)
        for cx, cy in dots[side]:
            img[cy - 20:cy + 21, cx - 20:cx + 21] = 0
            img[cy, cx] = 255
        if dtype == np.uint16:
            img = img.astype(np.uint16) * 257
        tifffile.imwrite(paths[side], img, resolution=(25.4 / pixel_mm, 25.4 / pixel_mm),
                         resolutionunit="INCH")
    Session.create(folder / "session", model, mode=mode, height=height,
                   left_offset=left_offset).close()
    return {"folder": folder / "session", "model": model, "frame": frame, "dots": dots,
            "points": np.asarray(points, float), "paths": paths, "maps": maps}
