"""Detection without being told what it cannot know, and never inventing marks (issue 3, 4)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from softplot.io import Scan
from softplot.marks import DetectionError, detect
from test_marks_accuracy import evaluate, render, scan_of

CAM = "rollei-6006"


def _truth_xy(truth):
    return {m["name"]: (m["x"], m["y"]) for m in truth["marks"]}


def test_covered_and_cut_crosses_are_missing_never_invented():
    # crop 4 mm off the left and top edges: column 0 and row 0 cut by the scan edge
    img, truth = render(CAM, 11, dpi=900, cover=6, crop_mm=(4.0, 4.0, 0.0, 0.0))
    states = [m["state"] for m in truth["marks"]]
    assert states.count("covered") == 6 and states.count("cut") >= 5
    det = detect(scan_of(img, truth), CAM)
    res = evaluate(det, truth, CAM)
    assert not res["claimed"] and not res["wrong"]
    assert len(res["missed"]) <= 1
    tm = {m["name"]: m for m in truth["marks"]}
    for i, n in enumerate(det.name):
        if tm[n]["state"] != "visible":
            assert det.status[i] == "missing" and det.reason[i]


def test_dust_and_scratches_over_arms_do_not_pull_centres():
    img, truth = render(CAM, 12, dpi=1000, scene="none", noise_sigma=0.01)
    img = img.copy()
    ppm = 1000 / 25.4
    rng = np.random.default_rng(0)
    hit = []
    for m in truth["marks"][::9]:
        x, y = m["x"], m["y"]
        arm = rng.integers(4)
        dx, dy = [(1, 0), (0, 1), (-1, 0), (0, -1)][arm]
        d = 0.22 * ppm  # in the middle of an arm, off the centre
        cv2.circle(img, (int(round(x + dx * d)), int(round(y + dy * d))), int(0.07 * ppm),
                   20, -1, lineType=cv2.LINE_AA)
        hit.append(m["name"])
    # a scratch across two arms of another cross
    m = truth["marks"][60]
    cv2.line(img, (int(m["x"] - 0.35 * ppm), int(m["y"] + 0.3 * ppm)),
             (int(m["x"] + 0.35 * ppm), int(m["y"] + 0.1 * ppm)), 250, 2, cv2.LINE_AA)
    hit.append(m["name"])
    det = detect(scan_of(img, truth), CAM)
    res = evaluate(det, truth, CAM)
    assert not res["wrong"] and not res["claimed"]
    tx = _truth_xy(truth)
    errs = []
    for i, n in enumerate(det.name):
        if n in hit and det.status[i] == "measured":
            errs.append(np.hypot(*(det.xy[i] - tx[n])))
    assert len(errs) >= len(hit) - 1, det.reason
    assert max(errs) < 0.03, errs


def test_refused_crosses_are_measured_again_from_three_half_arms(monkeypatch):
    """A cross that the acceptance tests refuse in every fit of all its arms (here by a
    stand-in: what one half-arm on conflicting scene content does) is fitted again from its
    neighbours' prediction, once without each half-arm, and measured from its clean parts;
    a cross cut by the scan edge is never fitted."""
    import importlib

    # every module of the reseau path that fits crosses
    mods = [importlib.import_module(f"softplot.marks.{m}")
            for m in ("marksize", "measurement", "validation")]
    img, truth = render(CAM, 13, dpi=1000, scene="none", noise_sigma=0.01,
                        crop_mm=(4.0, 0.0, 0.0, 0.0))
    tx = _truth_xy(truth)
    picked = ["R2C3", "R5C5", "R8C7"]
    at = np.array([tx[n] for n in picked])
    orig = mods[0].measure

    def refusing(sc, shape, c0, *a, **k):
        f = orig(sc, shape, c0, *a, **k)
        if k.get("drop_part") is None:  # every fit of the whole cross
            near = (np.hypot(*(np.asarray(c0)[:, None, :] - at[None]).transpose(2, 0, 1))
                    < 3.0).any(1)
            f.ok[near] = False
            for j in np.where(near)[0]:
                f.reason[j] = "refused (test)"
        return f

    for mod in mods:
        monkeypatch.setattr(mod, "measure", refusing)
    det = detect(scan_of(img, truth), CAM)
    res = evaluate(det, truth, CAM)
    assert not res["wrong"] and not res["claimed"]
    states = {m["name"]: m["state"] for m in truth["marks"]}
    for n in picked:
        i = det.name.index(n)
        assert det.status[i] == "measured", (n, det.reason[i])
        assert np.hypot(*(det.xy[i] - tx[n])) < 0.05
    for i, n in enumerate(det.name):
        if states[n] != "visible":
            assert det.status[i] == "missing"


def test_scene_crosses_never_get_a_grid_id():
    img, truth = render(CAM, 13, dpi=900, scene="texture")
    img = img.copy()
    ppm = 900 / 25.4
    L, w = int(0.4 * ppm), max(1, int(round(0.04 * ppm)))
    fakes = []
    marks = truth["marks"]
    for m in marks[5:100:7]:
        # a cross of the same size half a pitch off the grid
        x, y = int(m["x"] + 2.5 * ppm), int(m["y"] + 2.5 * ppm)
        cv2.line(img, (x - L, y), (x + L, y), 60, w)
        cv2.line(img, (x, y - L), (x, y + L), 60, w)
        fakes.append((x, y))
    det = detect(scan_of(img, truth), CAM)
    res = evaluate(det, truth, CAM)
    assert not res["wrong"] and not res["claimed"]
    assert len(res["missed"]) <= 1
    xy = det.xy[det.measured]
    for f in fakes:
        assert np.min(np.hypot(*(xy - f).T)) > 20


def test_unknown_dpi_is_estimated():
    img, truth = render(CAM, 14, dpi=1100, rotation_deg=4.0)
    det = detect(Scan.from_array(img, dpi=None), CAM)
    assert det.dpi_source == "estimated"
    assert abs(det.dpi / 1100 - 1) < 0.01
    res = evaluate(det, truth, CAM)
    assert not res["wrong"] and not res["claimed"] and len(res["missed"]) <= 1
    assert res["rms"] < 0.03


@pytest.mark.parametrize("turn", [90, 270])
def test_quarter_turned_scan_with_rotate(turn):
    img, truth = render(CAM, 15, dpi=700, polarity="negative")
    k = turn // 90
    rot = np.ascontiguousarray(np.rot90(img, k))  # counter-clockwise
    H, W = img.shape[:2]
    det = detect(Scan.from_array(rot, dpi=700), CAM, rotate=turn)
    assert det.polarity == "negative"
    tx = _truth_xy(truth)
    n = 0
    for i, name in enumerate(det.name):
        if det.status[i] != "measured":
            continue
        x, y = tx[name]
        for _ in range(k):  # pixel coordinates after one counter-clockwise quarter turn
            x, y, W, H = y, W - 1 - x, H, W
        W, H = img.shape[1], img.shape[0]
        assert np.hypot(det.xy[i, 0] - x, det.xy[i, 1] - y) < 0.05, name
        n += 1
    assert n >= 120


def test_rgb_orange_mask_16bit_and_jpeg():
    for kw in (dict(rgb=True, polarity="negative", bits=16, dpi=800),
               dict(file_format="jpg", jpeg_quality=85, dpi=800, scene="texture")):
        img, truth = render(CAM, 16, **kw)
        det = detect(scan_of(img, truth), CAM)
        res = evaluate(det, truth, CAM)
        assert not res["wrong"] and not res["claimed"], kw
        assert len(res["missed"]) <= 1, (kw, res["missed"])
        assert res["rms"] < 0.05, (kw, res["rms"])


def test_bad_inputs_name_expected_and_found():
    img, truth = render(CAM, 17, dpi=600)
    blank = np.full((1500, 1500), 200, np.uint8)
    with pytest.raises(DetectionError, match="blank"):
        detect(Scan.from_array(blank, dpi=600), CAM)
    small = np.ascontiguousarray(img[:150, :150])  # not even 3 x 3 crosses
    with pytest.raises(DetectionError, match="much smaller"):
        detect(Scan.from_array(small, dpi=600), CAM)
    noise = np.random.default_rng(0).integers(0, 255, (1500, 1500)).astype(np.uint8)
    with pytest.raises(DetectionError, match="no reseau found"):
        detect(Scan.from_array(noise, dpi=600), CAM)
    # a fiducial camera on a reseau scan: its fiducial pattern is not there
    with pytest.raises(DetectionError, match="expected"):
        detect(scan_of(img, truth), "zeiss-umk-10-1318", dpi=600)


def test_crosses_where_the_neighbours_extrapolate_far_are_not_outliers():
    """Sweep render 125 (Rollei half frame at 1133 dpi with dark rows): crosses of the
    bottom row and beside the dark band were rejected as outliers though measured within
    0.02 px of the truth: their neighbours' prediction extrapolates farther than along the
    outline elsewhere and misses the film's deformation by 0.12-0.18 px (3-4 um), beyond
    the outline's floor. Every visible cross measured, none grossly off, nothing claimed."""
    from softplot.synthetic.sweep import make_case, run_case

    sc, det = run_case(make_case(125))
    assert sc.result and sc.gross == [] and sc.claimed == [] and sc.wrong == []
    assert not [m for m in sc.missed if "rejected outlier" in m]
    assert sc.measured == sc.visible
