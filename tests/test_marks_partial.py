"""Partial frames: a scan that shows a part of the reseau (a half frame, a quarter, a strip)
gives every cross it shows with its right row and column, and the rest ``missing``; the
format's edge, where the scan shows it, tells which part it is."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from softplot.io import Scan
from softplot.marks import detect
from softplot.synthetic import ScanSpec, render_scan

CAM = "rollei-6006"


@functools.lru_cache(maxsize=2)
def _render(crop):
    return render_scan(CAM, ScanSpec(dpi=600, crop_mm=crop, rotation_deg=0.5), 2)


def _score(det, truth):
    tm = {m["name"]: m for m in truth["marks"]}
    ok = wrong = claimed = 0
    for i, n in enumerate(det.name):
        if det.status[i] != "measured":
            continue
        t = tm[n]
        if not t["visible"]:
            claimed += 1
        elif np.hypot(*(det.xy[i] - (t["x"], t["y"]))) > 1.0:
            wrong += 1
        else:
            ok += 1
    visible = sum(bool(m["visible"]) for m in truth["marks"])
    return ok, wrong, claimed, visible


@pytest.mark.parametrize("crop", [
    (30, 0, 0, 0),   # right half
    (0, 0, 30, 0),   # left half
    (0, 30, 0, 0),   # bottom half
    (27, 0, 0, 27),  # a quarter
    (0, 0, 22, 0),   # through a column
])
def test_a_part_of_the_grid_is_named_right(crop):
    img, truth = _render(crop)
    det = detect(Scan.from_array(img, dpi=600), CAM)
    ok, wrong, claimed, visible = _score(det, truth)
    assert wrong == 0 and claimed == 0
    assert ok == visible
    assert sum(s == "missing" for s in det.status) == len(det) - visible
    assert any("not measured" in w for w in det.warnings)
    assert not det.ids_ambiguous  # the format's edges name the part


def test_a_strip_without_format_edges_says_its_naming_is_assumed():
    img, truth = _render((0, 12, 0, 12))  # top and bottom rows cut: which rows is unknown
    det = detect(Scan.from_array(img, dpi=600), CAM)
    ok, wrong, claimed, visible = _score(det, truth)
    assert wrong == 0 and claimed == 0 and ok == visible  # centred: the assumption holds
    assert any("could be several" in w for w in det.warnings)
    assert det.ids_ambiguous and det.to_json()["ids_ambiguous"] is True
