"""Renderer features for the detection robustness sweep: mark sizes other than the
certificate's, partial opacity, a larger centre cross, one-armed crosses and flat dark regions
over whole rows, each checked on the rendered pixels against the truth."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.errors import SoftplotError
from softplot.synthetic import ScanSpec, render_scan

CLEAN = dict(noise_sigma=0.0, grain_sigma=0.0, scene="none", bits=16, blur_sigma_px=0.8,
             deform_um=0.0)
DPI = 1200.0
PPM = DPI / 25.4


def _grey(img):
    return img.astype(float) / 65535.0


def _profile_extent(grey, m, axis, half):
    """Full width at half depth (px) of the profile along film ``axis`` through the mark
    centre: the length of the bar along that axis."""
    x, y = int(round(m["x"])), int(round(m["y"]))
    win = grey[y - half: y + half + 1, x - half: x + half + 1]
    bg = np.median(np.concatenate([win[0], win[-1]]))
    prof = win[half, :] if axis == "x" else win[:, half]
    depth = bg - prof
    return float(np.sum(depth > 0.5 * depth.max()))


@pytest.mark.parametrize("arm_scale,width_scale", [(0.4, 0.5), (1.0, 1.0), (2.5, 2.0)])
def test_mark_sizes_differ_from_the_certificate(arm_scale, width_scale):
    """The crosses are drawn at the spec's multiple of the certificate's arm length and line
    width; the truth records the drawn sizes, the image shows them (full width at half depth
    along and across a bar, within 1.5 px)."""
    spec = ScanSpec(dpi=DPI, mark_arm_scale=arm_scale, mark_width_scale=width_scale,
                    **CLEAN)
    img, truth = render_scan("rollei-6006", spec, seed=1)
    grey = _grey(img)
    m = next(t for t in truth["marks"] if t["name"] == "R5C5")
    assert m["arm_length_mm"] == pytest.approx(0.8 * arm_scale)
    assert m["line_width_mm"] == pytest.approx(0.04 * width_scale)
    assert truth["render"]["arm_half_length_px"] == pytest.approx(0.4 * arm_scale * PPM)
    half = int(0.4 * arm_scale * PPM) + 12
    length = _profile_extent(grey, m, "x", half)
    assert abs(length - 0.8 * arm_scale * PPM) < 1.5
    # across the vertical bar, off the centre: its width (the depth of a thin line is less
    # than the contrast: measure the integrated depth instead)
    x, y = int(round(m["x"])), int(round(m["y"] + 0.25 * arm_scale * 0.8 * PPM))
    row = grey[y, x - 10: x + 11]
    area = float(np.sum(np.median(grey[y, x - 30: x - 20]) - row))
    assert abs(area / 0.5 - 0.04 * width_scale * PPM) < 0.05 * 0.04 * width_scale * PPM + 0.05


def test_opacity_scales_the_mark_depth():
    """A mark of opacity 0.6 darkens the flat background by 0.6 of the contrast (the
    integrated depth across a bar), and the truth's contrast says so."""
    depth = []
    for op in (1.0, 0.6):
        img, truth = render_scan("rollei-6006", ScanSpec(dpi=DPI, mark_opacity=op, **CLEAN), 1)
        g = _grey(img)
        m = next(t for t in truth["marks"] if t["name"] == "R3C4")
        x, y = int(round(m["x"])), int(round(m["y"] + 10))
        row = g[y, x - 10: x + 11]
        depth.append(float(np.sum(np.median(g[y, x - 30: x - 20]) - row)))
        assert m["contrast"] == pytest.approx(0.5 * op, rel=1e-6)
    assert depth[1] / depth[0] == pytest.approx(0.6, abs=0.005)


def test_larger_centre_cross():
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=DPI, centre_scale=2.0, **CLEAN), 1)
    g = _grey(img)
    by = {m["name"]: m for m in truth["marks"]}
    assert by["R5C5"]["arm_length_mm"] == pytest.approx(1.6)
    assert by["R5C5"]["line_width_mm"] == pytest.approx(0.08)
    assert by["R4C5"]["arm_length_mm"] == pytest.approx(0.8)
    half = int(0.8 * PPM) + 12
    big = _profile_extent(g, by["R5C5"], "x", half)
    small = _profile_extent(g, by["R4C5"], "x", half)
    assert abs(big - 1.6 * PPM) < 1.5 and abs(small - 0.8 * PPM) < 1.5


def test_one_armed_crosses_show_one_bar():
    """A one-armed cross shows its surviving bar and nothing of the other: the image along
    the missing bar is the flat background."""
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=DPI, one_armed=8, **CLEAN), 4)
    g = _grey(img)
    one = [m for m in truth["marks"] if m["arms"] == 1]
    assert len(one) == 8
    assert {m["arm_axis"] for m in one} <= {"x", "y"}
    assert all(m["visible"] for m in one)
    assert sum(m["arms"] == 2 for m in truth["marks"]) == 121 - 8
    L = int(0.4 * PPM) - 3  # along the bar, inside its tip
    for m in one:
        x, y = int(round(m["x"])), int(round(m["y"]))
        horiz = g[y, x - L: x - 4].min(), g[y, x + 5: x + L].min()
        vert = g[y - L: y - 4, x].min(), g[y + 5: y + L, x].min()
        here, gone = (horiz, vert) if m["arm_axis"] == "x" else (vert, horiz)
        assert max(here) < 0.8 - 0.2  # the bar darkens the background (0.8) by its depth
        assert min(gone) > 0.8 - 1e-3  # nothing of the other bar


def test_one_armed_by_name_and_bad_names():
    _, truth = render_scan("rollei-6006", ScanSpec(dpi=300, one_armed=("R0C0", "R2C3")), 1)
    assert [m["name"] for m in truth["marks"] if m["arms"] == 1] == ["R0C0", "R2C3"]
    with pytest.raises(SoftplotError, match="one-armed"):
        render_scan("rollei-6006", ScanSpec(dpi=300, one_armed=("R99C0",)), 1)


@pytest.mark.parametrize("polarity", ["positive", "negative"])
def test_dark_rows_hide_their_crosses(polarity):
    """Rows 0-2 and 9 lie under a flat dark region exposing nothing: their crosses have no
    contrast at all (the window is flat up to noise and quantisation), truth state "dark",
    ``arms`` 0; a dark region at a quarter of the exposure leaves visible, faint crosses."""
    spec = ScanSpec(dpi=600, dark_rows=((0, 2), (9, 9)), dark_level=0.0, polarity=polarity,
                    **{**CLEAN, "scene": "texture", "noise_sigma": 0.002})
    img, truth = render_scan("rollei-6006", spec, 2)
    g = _grey(img)
    for m in truth["marks"]:
        dark = m["row"] in (0, 1, 2, 9)
        assert m["dark"] == dark
        assert m["state"] == ("dark" if dark else "visible")
        assert m["visible"] == (not dark) and m["arms"] == (0 if dark else 2)
        x, y = int(round(m["x"])), int(round(m["y"]))
        win = g[y - 12: y + 13, x - 12: x + 13]
        if dark:
            assert win.std() < 0.004  # noise only
            assert m["contrast"] == 0.0
        else:
            assert win.max() - win.min() > 0.2
    faint = ScanSpec(dpi=600, dark_rows=((0, 2),), dark_level=0.25, **CLEAN)
    _, truth = render_scan("rollei-6006", faint, 2)
    row0 = [m for m in truth["marks"] if m["row"] == 0]
    assert all(m["visible"] and m["contrast"] == pytest.approx(0.125) for m in row0)


def test_bad_variant_specs_are_refused():
    for bad in (dict(mark_arm_scale=0.0), dict(mark_opacity=1.5), dict(dark_level=1.0),
                dict(dark_rows=((3, 1),)), dict(one_armed=-1), dict(centre_scale=-2.0)):
        with pytest.raises(SoftplotError, match="synthetic scan"):
            ScanSpec(**bad).validate()
    with pytest.raises(SoftplotError, match="dark_rows"):
        render_scan("rollei-6006", ScanSpec(dpi=200, dark_rows=((0, 11),)), 1)
