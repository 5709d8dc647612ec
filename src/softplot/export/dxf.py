"""DXF export with ezdxf: one layer per feature code.

* ``point`` -> ``POINT`` at (X, Y, Z) plus a ``TEXT`` with the height beside it (spot height);
* ``line`` -> 3D ``POLYLINE`` (ezdxf ``Polyline3d``) through the vertices;
* ``contour`` -> ``LWPOLYLINE`` in the plane Z = height (``elevation`` attribute), closed
  when the last vertex repeats the first.

Coordinates are object (model) coordinates, written unchanged. The document is audited
(:meth:`ezdxf.document.Drawing.audit`) before saving; an audit error raises.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import ezdxf

from softplot.errors import SoftplotError
from softplot.export.features import Feature

__all__ = ["features_to_dxf", "write_dxf"]


def features_to_dxf(
    features: Iterable[Feature],
    *,
    text_height: float = 0.5,
    height_format: str = "{:.2f}",
    dxfversion: str = "R2010",
):
    """Build an ezdxf document from features.

    Parameters
    ----------
    features : iterable of Feature
        Object coordinates.
    text_height : float
        Height of the spot-height labels, object units.
    height_format : str
        Format of the label text.
    dxfversion : str
        DXF version (ezdxf name).

    Returns
    -------
    ezdxf.document.Drawing
    """
    doc = ezdxf.new(dxfversion)
    doc.header["$INSUNITS"] = 6  # metres
    msp = doc.modelspace()
    colour = 1
    for f in features:
        if f.code not in doc.layers:
            doc.layers.add(f.code, color=colour)
            colour = colour % 254 + 1
        attrs = {"layer": f.code}
        v = f.vertices
        if f.kind == "point":
            x, y, z = (float(a) for a in v[0])
            msp.add_point((x, y, z), dxfattribs=attrs)
            msp.add_text(
                height_format.format(z),
                height=text_height,
                dxfattribs={**attrs, "insert": (x + 0.5 * text_height, y + 0.5 * text_height, z)},
            )
        elif f.kind == "line":
            closed = f.closed
            pts = v[:-1] if closed else v
            msp.add_polyline3d([tuple(map(float, p)) for p in pts], close=closed, dxfattribs=attrs)
        else:
            closed = f.closed
            pts = v[:-1] if closed else v
            msp.add_lwpolyline(
                [(float(p[0]), float(p[1])) for p in pts],
                close=closed,
                dxfattribs={**attrs, "elevation": float(f.height)},
            )
    return doc


def write_dxf(features: Iterable[Feature], path, **kw) -> Path:
    """Write features to a DXF file after a clean ezdxf audit.

    Raises
    ------
    SoftplotError
        If the audit finds errors or the file cannot be written.
    """
    doc = features_to_dxf(features, **kw)
    auditor = doc.audit()
    if auditor.has_errors:
        raise SoftplotError(f"DXF audit failed with {len(auditor.errors)} error(s)")
    path = Path(path)
    try:
        doc.saveas(path)
    except OSError as exc:
        raise SoftplotError(f"cannot write DXF {path}: {exc.strerror or exc}") from exc
    return path
