"""The detection JSON (docs/detection.md): every measured mark carries its full 2 x 2
covariance, consistent with its sigmas; the crosses' measured size is reported."""

from __future__ import annotations

import json

import numpy as np

from softplot.io import Scan
from softplot.marks import detect
from softplot.synthetic import ScanSpec, render_scan


def test_json_has_the_covariance_and_the_mark_geometry():
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=600, rotation_deg=1.0), 21)
    det = detect(Scan.from_array(img, dpi=600), "rollei-6006")
    doc = json.loads(json.dumps(det.to_json()))
    n = 0
    for m in doc["marks"]:
        if m["status"] != "measured":
            assert m["cov"] is None and m["arms"] is None
            continue
        c = np.array(m["cov"])
        assert c.shape == (2, 2) and c[0, 1] == c[1, 0]
        assert np.all(np.linalg.eigvalsh(c) > 0)
        assert np.isclose(np.sqrt(c[0, 0]), m["sigma_x"], rtol=1e-3, atol=1e-5)
        assert np.isclose(np.sqrt(c[1, 1]), m["sigma_y"], rtol=1e-3, atol=1e-5)
        assert m["arms"] == 2  # whole crosses (one bar only: tests/test_marks_onearm.py)
        n += 1
    assert n >= 120
    g = doc["mark_geometry"]
    assert set(g) >= {"arm_length_mm", "line_width_mm", "spread", "n", "source"}
    assert abs(g["arm_length_mm"] - 0.8) < 0.04
