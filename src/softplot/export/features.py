"""Restituted features: points, 3D lines and contours in object coordinates.

A :class:`Feature` is what the plotter records and the exporters write: a feature ``code``
(one DXF layer per code), a ``kind`` (``point`` for spot heights, ``line`` for 3D break
lines and edges, ``contour`` for lines at one height) and its vertices, an (N, 3) array of
object (model) coordinates X, Y, Z (Z up, the unit of the orientation, usually m).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

import numpy as np

from softplot.errors import SoftplotError

__all__ = ["Feature", "KINDS", "features_from_records"]

#: feature kinds
KINDS = ("point", "line", "contour")
_CODE_RE = re.compile(r"^[A-Za-z0-9_\-.$]{1,64}$")


@dataclass
class Feature:
    """One restituted feature.

    Parameters
    ----------
    code : str
        Feature code (letters, digits, ``_ - . $``; at most 64): the DXF layer name.
    kind : {"point", "line", "contour"}
        ``point``: one vertex (a spot height); ``line``: >= 2 vertices (3D polyline);
        ``contour``: >= 2 vertices all at the same Z.
    vertices : array_like, shape (N, 3)
        Object (model) coordinates X, Y, Z.
    attributes : dict
        Free JSON-serialisable attributes (name, mode, image points, ...).
    """

    code: str
    kind: str
    vertices: np.ndarray
    attributes: dict = field(default_factory=dict)

    def __post_init__(self):
        if not isinstance(self.code, str) or not _CODE_RE.match(self.code):
            raise SoftplotError(
                f"bad feature code {self.code!r}: use 1-64 letters, digits, '_', '-', '.', '$'"
            )
        if self.kind not in KINDS:
            raise SoftplotError(f"bad feature kind {self.kind!r}: use one of {', '.join(KINDS)}")
        v = np.asarray(self.vertices, dtype=float)
        if v.ndim == 1 and v.shape[0] == 3:
            v = v[None, :]
        if v.ndim != 2 or v.shape[1] != 3:
            raise SoftplotError(f"feature {self.code}: vertices must be (N,3), got {v.shape}")
        if not np.all(np.isfinite(v)):
            raise SoftplotError(f"feature {self.code}: vertices are not all finite")
        if self.kind == "point" and v.shape[0] != 1:
            raise SoftplotError(f"feature {self.code}: a point has 1 vertex, got {v.shape[0]}")
        if self.kind in ("line", "contour") and v.shape[0] < 2:
            raise SoftplotError(f"feature {self.code}: a {self.kind} needs >= 2 vertices")
        if self.kind == "contour" and np.ptp(v[:, 2]) > 1e-9 * max(1.0, abs(v[0, 2])):
            raise SoftplotError(f"feature {self.code}: contour vertices are not at one height")
        self.vertices = v

    @property
    def closed(self) -> bool:
        """True for a line/contour whose last vertex equals the first."""
        v = self.vertices
        return self.kind != "point" and v.shape[0] > 2 and bool(np.all(v[0] == v[-1]))

    @property
    def height(self) -> float:
        """Z of a point or contour (first vertex)."""
        return float(self.vertices[0, 2])

    def to_record(self) -> dict:
        """JSON-serialisable dict (exact floats via ``repr`` round trip)."""
        return {
            "code": self.code,
            "kind": self.kind,
            "vertices": self.vertices.tolist(),
            "attributes": self.attributes,
        }

    @classmethod
    def from_record(cls, rec: dict) -> "Feature":
        """Inverse of :meth:`to_record`."""
        try:
            return cls(rec["code"], rec["kind"], rec["vertices"], dict(rec.get("attributes", {})))
        except KeyError as exc:
            raise SoftplotError(f"feature record without {exc.args[0]!r}") from exc


def features_from_records(records) -> list[Feature]:
    """Features from an iterable of :meth:`Feature.to_record` dicts."""
    return [Feature.from_record(r) for r in records]
