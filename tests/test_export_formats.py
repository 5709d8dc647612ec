"""DXF (ezdxf audit, layers, entities), GeoJSON and CSV export of features."""

from __future__ import annotations

import csv
import json

import ezdxf
import numpy as np
import pytest

from softplot.errors import SoftplotError
from softplot.export.csvfile import CSV_COLUMNS, write_csv
from softplot.export.dxf import features_to_dxf, write_dxf
from softplot.export.features import Feature
from softplot.export.geojson import features_to_geojson, write_geojson


def _features():
    ring = [[np.cos(a) * 10, np.sin(a) * 10, 250.0] for a in np.linspace(0, 2 * np.pi, 9)[:-1]]
    return [
        Feature("SPOT", "point", [100.123456789, 200.5, 312.345678]),
        Feature("SPOT", "point", [101.0, 201.0, 300.0]),
        Feature("BREAK", "line", [[0.0, 0.0, 10.0], [5.0, 1.0, 12.5], [9.0, 3.0, 11.0]]),
        Feature("C250", "contour", ring + [ring[0]]),
        Feature("C260", "contour", [[0, 0, 260.0], [1, 0, 260.0], [2, 1, 260.0]]),
    ]


def test_dxf_layers_entities_and_audit(tmp_path):
    path = write_dxf(_features(), tmp_path / "out.dxf", text_height=0.25)
    doc = ezdxf.readfile(path)
    auditor = doc.audit()
    assert not auditor.has_errors
    assert {"SPOT", "BREAK", "C250", "C260"} <= {layer.dxf.name for layer in doc.layers}
    msp = doc.modelspace()
    by = {}
    for e in msp:
        by.setdefault((e.dxftype(), e.dxf.layer), []).append(e)
    points = by[("POINT", "SPOT")]
    assert len(points) == 2
    assert tuple(points[0].dxf.location) == pytest.approx((100.123456789, 200.5, 312.345678))
    texts = by[("TEXT", "SPOT")]
    assert [t.dxf.text for t in texts] == ["312.35", "300.00"]
    (pl3,) = by[("POLYLINE", "BREAK")]
    assert pl3.is_3d_polyline
    assert [tuple(v) for v in pl3.points()] == [(0, 0, 10), (5, 1, 12.5), (9, 3, 11)]
    (c250,) = by[("LWPOLYLINE", "C250")]
    assert c250.closed and c250.dxf.elevation == 250.0 and len(c250) == 8
    (c260,) = by[("LWPOLYLINE", "C260")]
    assert not c260.closed and c260.dxf.elevation == 260.0
    assert np.allclose([p[:2] for p in c260.get_points()], [[0, 0], [1, 0], [2, 1]])


def test_dxf_in_memory_document():
    doc = features_to_dxf(_features()[:1])
    assert len(list(doc.modelspace())) == 2  # POINT + TEXT


def test_geojson_3d(tmp_path):
    gj = features_to_geojson(_features())
    assert gj["type"] == "FeatureCollection" and len(gj["features"]) == 5
    pt = gj["features"][0]
    assert pt["geometry"] == {"type": "Point", "coordinates": [100.123456789, 200.5, 312.345678]}
    assert pt["properties"]["height"] == 312.345678
    ln = gj["features"][2]["geometry"]
    assert ln["type"] == "LineString" and all(len(c) == 3 for c in ln["coordinates"])
    ring = gj["features"][3]["geometry"]["coordinates"]
    assert ring[0] == ring[-1]
    path = write_geojson(_features(), tmp_path / "out.geojson")
    assert json.loads(path.read_text()) == json.loads(json.dumps(gj))


def test_csv_round_trip_exact(tmp_path):
    feats = _features()
    path = write_csv(feats, tmp_path / "out.csv")
    rows = list(csv.reader(path.open()))
    assert tuple(rows[0]) == CSV_COLUMNS
    assert len(rows) - 1 == sum(len(f.vertices) for f in feats)
    body = rows[1:]
    back = np.array([[float(v) for v in r[4:7]] for r in body])
    assert np.array_equal(back, np.vstack([f.vertices for f in feats]))
    assert body[0][:4] == ["0", "SPOT", "point", "0"]


@pytest.mark.parametrize(
    "args, msg",
    [
        (("bad code", "point", [0, 0, 0]), "feature code"),
        (("A", "polygon", [0, 0, 0]), "feature kind"),
        (("A", "point", [[0, 0, 0], [1, 1, 1]]), "a point has 1 vertex"),
        (("A", "line", [[0, 0, 0]]), "needs >= 2"),
        (("A", "contour", [[0, 0, 0], [1, 1, 1]]), "not at one height"),
        (("A", "line", [[0, 0], [1, 1]]), r"must be \(N,3\)"),
        (("A", "point", [0, np.nan, 0]), "not all finite"),
    ],
)
def test_bad_features(args, msg):
    with pytest.raises(SoftplotError, match=msg):
        Feature(*args)


def test_unwritable_output(tmp_path):
    with pytest.raises(SoftplotError, match="cannot write DXF"):
        write_dxf(_features(), tmp_path / "missing" / "out.dxf")
    with pytest.raises(SoftplotError, match="cannot write CSV"):
        write_csv(_features(), tmp_path / "missing" / "out.csv")
