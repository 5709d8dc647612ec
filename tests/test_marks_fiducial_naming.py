"""Fiducial naming: where the layout looks the same after a quarter or half turn, the result
says that the marks' names rest on --rotate (a warning in the JSON and the summary line)."""

from __future__ import annotations

from softplot.camera import Fiducial, load_camera
from softplot.marks import detect
from softplot.marks.fiducial import layout_turns
from test_marks_accuracy import render, scan_of


def test_layout_turns():
    assert layout_turns(load_camera("wild-rc10").fiducials) == [90, 180, 270]
    assert layout_turns(load_camera("zeiss-umk-10-1318").fiducials) == [180]
    # one mark off the symmetric place, or one of another shape: no turn maps it onto itself
    sq = [Fiducial("1", -50, -50), Fiducial("2", 50, -50), Fiducial("3", 50, 50),
          Fiducial("4", -50, 50)]
    assert layout_turns(sq) == [90, 180, 270]
    assert layout_turns(sq[:3] + [Fiducial("4", -50, 49)]) == []
    assert layout_turns(sq[:3] + [Fiducial("4", -50, 50, shape="dot")]) == []


def test_symmetric_layout_says_naming_rests_on_rotate():
    img, truth = render("wild-rc10", 22, dpi=250, scene="busy", rotation_deg=-8.0)
    det = detect(scan_of(img, truth), "wild-rc10")
    assert any("rest on --rotate" in w for w in det.to_json()["warnings"])
    assert "names rest on --rotate" in det.summary()


def _one_mark_camera():
    import dataclasses

    cam = load_camera("zeiss-umk-10-1318")
    return dataclasses.replace(cam, fiducials=cam.fiducials[:1], name="one-mark")


def test_a_single_fiducial_is_measured():
    import numpy as np

    from softplot.io import Scan
    from softplot.synthetic import ScanSpec, render_scan

    cam = _one_mark_camera()
    img, truth = render_scan(cam, ScanSpec(dpi=400, rotation_deg=0.4), 3)
    det = detect(Scan.from_array(img, dpi=400), cam)
    t = {m["name"]: m for m in truth["marks"]}[det.name[0]]
    assert det.status == ["measured"]
    assert np.hypot(det.xy[0, 0] - t["x"], det.xy[0, 1] - t["y"]) < 0.1


def test_a_single_fiducial_is_not_invented_on_noise():
    import numpy as np
    import pytest

    from softplot.io import Scan
    from softplot.marks.detect import DetectionError

    noise = np.random.default_rng(1).integers(0, 255, (2000, 2000)).astype(np.uint8)
    with pytest.raises(DetectionError):
        detect(Scan.from_array(noise, dpi=400), _one_mark_camera())
