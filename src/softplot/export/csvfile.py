"""CSV export: one row per vertex, ``feature,code,kind,vertex,X,Y,Z`` (object coordinates).

``feature`` numbers the features from 0 in order; ``vertex`` numbers the vertices of one
feature from 0. Floats are written with ``repr`` precision so a round trip is exact.
"""

from __future__ import annotations

import csv
from collections.abc import Iterable
from pathlib import Path

from softplot.errors import SoftplotError
from softplot.export.features import Feature

__all__ = ["write_csv", "CSV_COLUMNS"]

CSV_COLUMNS = ("feature", "code", "kind", "vertex", "X", "Y", "Z")


def write_csv(features: Iterable[Feature], path) -> Path:
    """Write the vertices of all features to CSV; returns the path."""
    path = Path(path)
    try:
        with path.open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(CSV_COLUMNS)
            for i, f in enumerate(features):
                for j, (x, y, z) in enumerate(f.vertices.tolist()):
                    w.writerow([i, f.code, f.kind, j, repr(x), repr(y), repr(z)])
    except OSError as exc:
        raise SoftplotError(f"cannot write CSV {path}: {exc.strerror or exc}") from exc
    return path
