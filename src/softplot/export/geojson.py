"""GeoJSON export (RFC 7946 structure) with 3D coordinates [X, Y, Z].

``point`` -> ``Point``; ``line`` and ``contour`` -> ``LineString`` (``Polygon`` is not used:
a closed contour is a closed LineString). Properties: ``code``, ``kind``, ``height`` (points
and contours) and the feature's attributes. Coordinates are object coordinates as given
(no CRS is asserted; RFC 7946 readers assume WGS 84 unless told otherwise).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

from softplot.errors import SoftplotError
from softplot.export.features import Feature

__all__ = ["features_to_geojson", "write_geojson"]


def features_to_geojson(features: Iterable[Feature]) -> dict:
    """A GeoJSON FeatureCollection dict of the features (3D coordinates)."""
    out = []
    for i, f in enumerate(features):
        coords = f.vertices.tolist()
        geom = (
            {"type": "Point", "coordinates": coords[0]}
            if f.kind == "point"
            else {"type": "LineString", "coordinates": coords}
        )
        props = {"code": f.code, "kind": f.kind}
        if f.kind in ("point", "contour"):
            props["height"] = f.height
        props.update(f.attributes)
        out.append({"type": "Feature", "id": i, "geometry": geom, "properties": props})
    return {"type": "FeatureCollection", "features": out}


def write_geojson(features: Iterable[Feature], path) -> Path:
    """Write features as GeoJSON; returns the path."""
    path = Path(path)
    try:
        path.write_text(json.dumps(features_to_geojson(features), indent=1) + "\n")
    except OSError as exc:
        raise SoftplotError(f"cannot write GeoJSON {path}: {exc.strerror or exc}") from exc
    return path
