"""Crosses of which only one bar is visible: measured as a line (precise across the bar, a
large variance along it, ``arms: 1``); crosses with no bar are never claimed."""

from __future__ import annotations

import json

import numpy as np
import pytest

from softplot.io import Scan
from softplot.marks import detect
from softplot.marks.crb import centre_crb, effective_noise
from softplot.marks.measure import AcceptRules
from softplot.marks.template import MarkShape
from softplot.synthetic import ScanSpec, render_scan
from softplot.synthetic.mapping import TruthMapping


def _run(seed, **kw):
    spec = ScanSpec(dpi=600, one_armed=3, **kw)
    img, truth = render_scan("rollei-6006", spec, seed)
    det = detect(Scan.from_array(img, dpi=600), "rollei-6006")
    return det, json.loads(json.dumps(det.to_json())), truth


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_one_armed_crosses_are_measured_across_their_bar(seed):
    det, doc, truth = _run(seed)
    tm = {m["name"]: m for m in truth["marks"]}
    mp = TruthMapping.from_truth(truth)
    r = truth["render"]
    ppm = truth["dpi"] / 25.4
    found = 0
    for m in doc["marks"]:
        t = tm[m["name"]]
        if m["status"] == "measured":
            assert m["arms"] == t["arms"], (m["name"], m["arms"], t["arms"])
        if t["arms"] != 1:
            assert m["bar"] is None, (m["name"], m["bar"])
            continue
        assert m["status"] == "measured", (m["name"], m["reason"])
        found += 1
        along = mp.jacobian(np.array([[t["film_x"], t["film_y"]]]))[0][
            :, 0 if t["arm_axis"] == "x" else 1]
        tv = along / np.hypot(*along)
        # the JSON names the bar measured: its unit vector in the scan, the truth's bar
        assert abs(np.array(m["bar"]) @ tv) > 0.999, (m["name"], m["bar"], tv)
        # and its score and contrast to noise are the bar's fit's, which passed the
        # acceptance (not those of the cross's refused fit: 0.27 and 0.4 on seed 1's R8C4)
        assert m["score"] >= AcceptRules().min_score and m["cnr"] >= AcceptRules().min_cnr, (
            m["name"], m["score"], m["cnr"])
        nv = np.array([-tv[1], tv[0]])
        C = np.array(m["cov"])
        e = np.array([m["x"] - t["x"], m["y"] - t["y"]])
        var_n, var_t = nv @ C @ nv, tv @ C @ tv
        # honest along the bar (its neighbours' prediction's variance: the bar's error along
        # it within that; tests/test_marks_lone_bar_along.py pools them), small across it
        assert abs(e @ tv) < 4 * np.sqrt(var_t), (m["name"], e @ tv, np.sqrt(var_t))
        # across: within the 1-D bound of the bar (the per-axis bound of the cross as drawn),
        # allowing for a sample of one (4 bounds) and the sweep's 1.25 on average
        shape = MarkShape("cross", length=t["arm_length_mm"] * ppm, width=t["line_width_mm"] * ppm)
        noise = effective_noise(r["noise_sigma"], truth["bit_depth"])
        crb = centre_crb(shape, r["blur_sigma_px"], abs(t["contrast"]), noise, phases=2)
        assert abs(e @ nv) < 4 * 1.25 * crb + 0.005, (m["name"], e @ nv, crb)
        assert abs(e @ nv) < 4 * np.sqrt(var_n), (m["name"], e @ nv, np.sqrt(var_n))
    assert found == 3


def test_no_claim_where_neither_bar_is_visible():
    """A flat dark region over whole rows: the crosses there show no bar; none is claimed,
    as a cross or as a lone bar, while the one-armed crosses elsewhere are measured."""
    det, doc, truth = _run(4, dark_rows=((3, 4),), dark_level=0.0)
    tm = {m["name"]: m for m in truth["marks"]}
    dark = [m for m in doc["marks"] if tm[m["name"]]["arms"] == 0]
    assert dark, "the render has crosses without a visible bar"
    assert all(m["status"] != "measured" for m in dark)
