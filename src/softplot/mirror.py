"""Scans made through the film base: mirrored left-right.

A photo scanned emulsion-down is the mirror image of the photo. Its marks look the same for
every reseau and for mirror-symmetric fiducial layouts, so the scan alone cannot say which side
it shows: the user says it (``--mirror``), and the detection says when the side rests on that
option. :func:`detect_oriented` measures a mirrored scan by detecting on the flipped pixels and
mapping every result back to the scan's own pixel system (x -> W - 1 - x, pixel centres at
integers, docs/conventions.md), so the detection JSON, and every film correction made from it,
refer to the file's pixels as stored.
"""

from __future__ import annotations

import dataclasses

import numpy as np

__all__ = ["detect_oriented", "mirror_symmetric", "side_json", "MIRROR_NOTE"]

MIRROR_NOTE = ("the marks look the same mirrored: the side of the film (emulsion up or down) "
               "rests on --mirror")


def mirror_symmetric(cam, tol_mm: float = 1e-3) -> bool:
    """Whether the camera's marks (reseau and fiducials, film mm) map onto themselves under
    x -> -x (then a mirrored scan cannot be told from the scan)."""
    pts = []
    if cam.reseau is not None:
        pts.append(cam.reseau.film())
    if cam.fiducials:
        pts.append(cam.fiducial_film())
    xy = np.concatenate(pts) if pts else np.zeros((0, 2))
    if len(xy) == 0:
        return True
    m = xy * [-1.0, 1.0]
    d = np.linalg.norm(m[:, None, :] - xy[None, :, :], axis=2)
    return bool(np.all(d.min(axis=1) <= tol_mm))


def detect_oriented(sc, cam, *, mirror: bool = False, **kwargs):
    """:func:`softplot.marks.detect` of a scan that may be mirrored (``mirror``: scanned
    through the film base). Results are in the scan's own pixel system; the detection carries
    ``mirror`` (:func:`side_json` gives its JSON keys)."""
    from softplot.marks import detect

    if not mirror:
        det = detect(sc, cam, **kwargs)
    else:
        flipped = dataclasses.replace(sc, data=sc.data[:, ::-1])
        det = detect(flipped, cam, **kwargs)
        w = float(det.width)
        det.xy = det.xy.copy()
        det.xy[:, 0] = (w - 1.0) - det.xy[:, 0]
        det.residual = det.residual.copy()
        det.residual[:, 0] = -det.residual[:, 0]
        if det.cov is not None:
            det.cov = det.cov.copy()
            det.cov[..., 0, 1] *= -1.0
            det.cov[..., 1, 0] *= -1.0
        H = det.transform.get("matrix") if isinstance(det.transform, dict) else None
        if H is not None:
            F = np.array([[-1.0, 0.0, w - 1.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
            det.transform = {**det.transform, "matrix": (F @ np.asarray(H, float)).tolist()}
    det.mirror = bool(mirror)
    return det


def side_json(cam, mirror: bool) -> dict:
    """The JSON keys of a detection on the film's side: ``mirror`` (as given) and
    ``side_from`` ("--mirror" when the layout cannot tell, else "marks")."""
    return {"mirror": bool(mirror), "side_from": "--mirror" if mirror_symmetric(cam) else "marks"}
