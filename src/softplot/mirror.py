"""Scans made through the film base: mirrored left-right.

A photo scanned emulsion-down is the mirror image of the photo. Its marks look the same for
every reseau and for mirror-symmetric fiducial layouts, so the scan alone cannot say which side
it shows: the user says it (``--mirror``), and the detection says when the side rests on that
option. :func:`detect_oriented` measures a mirrored scan by detecting on the flipped pixels and
mapping every result back to the scan's own pixel system (x -> W - 1 - x, pixel centres at
integers, docs/conventions.md), so the detection JSON, and every film correction made from it,
refer to the file's pixels as stored.

Where the fiducial layout is asymmetric the marks do tell: a ``--mirror`` or ``--rotate`` that
contradicts the scan is refused in one line naming what the marks show
(:class:`OrientationContradiction`). The check costs nothing when every fiducial is found as
given; otherwise the orientations the layout can tell apart from the given one are tried, and
one that finds more fiducials is the contradiction.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from softplot.errors import SoftplotError

__all__ = ["detect_oriented", "mirror_symmetric", "side_json", "distinguishable",
           "OrientationContradiction", "MIRROR_NOTE"]

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


class OrientationContradiction(SoftplotError):
    """The marks show the photo turned or mirrored otherwise than ``--rotate`` / ``--mirror``
    say (an asymmetric fiducial layout)."""


#: film mm: marks this close after a turn or mirror of the layout are in each other's place
SYMMETRY_TOL_MM = 0.2


def _orientation(mirror: bool, rotate: float) -> np.ndarray:
    """Film-plane matrix of an orientation: mirrored left-right (x -> -x) first, then turned
    ``rotate`` degrees counter-clockwise (the order of ``--mirror`` and ``--rotate``)."""
    a = np.radians(rotate)
    R = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    return R @ np.diag([-1.0 if mirror else 1.0, 1.0])


def _invariant(fids, g: np.ndarray) -> bool:
    """Whether the film-plane map ``g`` (2x2) takes the fiducial layout onto itself
    (positions within :data:`SYMMETRY_TOL_MM`, and shapes)."""
    film = np.array([[f.x, f.y] for f in fids], float)
    shapes = [(f.shape, round(f.size_mm, 3)) for f in fids]
    moved = film @ g.T
    d = np.hypot(*(moved[:, None, :] - film[None, :, :]).transpose(2, 0, 1))
    j = d.argmin(1)
    return bool((d[np.arange(len(film)), j] <= SYMMETRY_TOL_MM).all() and len(set(j)) == len(j)
                and all(shapes[a] == shapes[b] for a, b in enumerate(j)))


def distinguishable(cam, mirror: bool = False, rotate: float = 0.0) -> list[tuple[bool, int]]:
    """The orientations ``(mirror, rotate)`` whose fiducials the scan can tell from the given
    one: those the layout does not map onto it (empty without fiducials or with a reseau,
    whose grid looks the same every way)."""
    if cam.reseau is not None or not cam.fiducials:
        return []
    g0 = _orientation(mirror, rotate)
    out = []
    for m in (False, True):
        for r in (0, 90, 180, 270):
            if m == bool(mirror) and r % 360 == round(rotate) % 360:
                continue
            g = np.linalg.solve(g0, _orientation(m, r))
            if not _invariant(cam.fiducials, np.round(g, 12)):
                out.append((m, r))
    return out


def _flags(mirror: bool, rotate: float) -> str:
    turned = round(rotate) % 360
    parts = ([f"--rotate {turned}"] if turned else []) + (["--mirror"] if mirror else [])
    return " ".join(parts) or "neither --rotate nor --mirror"


def _shows(mirror: bool, rotate: float) -> str:
    turned = round(rotate) % 360
    parts = ([f"turned {turned} degrees counter-clockwise"] if turned else [])
    parts.append("mirrored left-right" if mirror else "not mirrored")
    return ", ".join(parts)


def _n_measured(det) -> int:
    return sum(1 for k, st in zip(det.kind, det.status, strict=True)
               if k == "fiducial" and st == "measured")


def detect_oriented(sc, cam, *, mirror: bool = False, **kwargs):
    """:func:`softplot.marks.detect` of a scan that may be mirrored (``mirror``: scanned
    through the film base). Results are in the scan's own pixel system; the detection carries
    ``mirror`` (:func:`side_json` gives its JSON keys).

    Raises
    ------
    OrientationContradiction
        The fiducial layout is asymmetric and the marks show another orientation than
        ``mirror`` and ``rotate`` (one line: what the marks show and the options to give).
    """
    from softplot.camera import load_camera
    from softplot.marks.detect import DetectionError

    cam = load_camera(cam)
    rotate = float(kwargs.get("rotate", 0.0))
    det = error = None
    try:
        det = _detect_once(sc, cam, mirror, kwargs)
    except DetectionError as exc:
        error = exc
    n = len(cam.fiducials)
    if det is not None and (cam.reseau is not None or _n_measured(det) == n):
        return det
    alternatives = distinguishable(cam, mirror, rotate)
    n_given = 0 if det is None else _n_measured(det)
    best = None
    for m, r in alternatives:
        try:
            d2 = _detect_once(sc, cam, m, {**kwargs, "rotate": float(r)})
        except DetectionError:
            continue
        k = _n_measured(d2)
        if k > n_given and (best is None or k > best[0]):
            best = (k, m, r)
    if best is not None:
        k, m, r = best
        name = getattr(getattr(sc, "path", None), "name", None) or "scan"
        given = _flags(mirror, rotate).replace("neither --rotate nor --mirror",
                                               "no --rotate, no --mirror")
        raise OrientationContradiction(
            f"{name}: the {cam.name} fiducials show the photo {_shows(m, r)} ({k} of {n} "
            f"marks found that way, {n_given} with {given}): give {_flags(m, r)}"
        )
    if det is None:
        raise error
    return det


def _detect_once(sc, cam, mirror: bool, kwargs):
    """One detection with the given orientation (see :func:`detect_oriented`)."""
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
