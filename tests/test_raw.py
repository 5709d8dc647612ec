"""Camera RAW: a film frame digitised with a camera on a copy stand and saved as DNG.

The DNG is written here with tifffile (a Bayer CFA image with the tags LibRaw needs) from a
synthetic reseau scan with exact truth, so the test needs no file from outside. softplot reads
RAW linear, 16 bit, without automatic brightening and without the file's rotation: a reseau scan
must keep its geometry (every cross where the sensor saw it) and its linearity.
"""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from softplot.io import load_scan
from softplot.marks import detect
from softplot.synthetic import ScanSpec
from softplot.synthetic.scan import render_scan

rawpy = pytest.importorskip("rawpy")


def write_dng(path, grey16: np.ndarray, orientation: int = 1) -> None:
    """A neutral subject on a Bayer RGGB sensor: every photosite records ``grey16`` (uint16
    counts, linear), so demosaicing returns the same grey in each channel. ``orientation`` is
    the TIFF Orientation tag (6: the camera says "turn 90 degrees clockwise to view")."""
    tifffile.imwrite(
        path, grey16, photometric="cfa", compression=None,
        extratags=[
            (50706, 1, 4, (1, 4, 0, 0), True),       # DNGVersion
            (50707, 1, 4, (1, 4, 0, 0), True),       # DNGBackwardVersion
            (50708, 2, None, "softplot copy stand", True),  # UniqueCameraModel
            (33421, 3, 2, (2, 2), True),             # CFARepeatPatternDim
            (33422, 1, 4, (0, 1, 1, 2), True),       # CFAPattern RGGB
            (50710, 1, 3, (0, 1, 2), True),          # CFAPlaneColor
            (50717, 4, 1, (65535,), True),           # WhiteLevel
            (50721, 10, 9, (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1), True),
            (50778, 3, 1, (21,), True),              # CalibrationIlluminant1 D65
            (274, 3, 1, (orientation,), True),       # Orientation
        ],
    )


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=500, bits=16), seed=5)
    d = tmp_path_factory.mktemp("raw")
    grey = (img.astype(np.float64) * 0.6 + 2000).astype(np.uint16)  # below white, above black
    return d, grey, truth


def test_dng_keeps_size_depth_and_linearity(frame, tmp_path):
    d, grey, _ = frame
    write_dng(d / "f.dng", grey)
    sc = load_scan(d / "f.dng")
    assert sc.file_format == "raw"
    assert sc.bit_depth == 16
    assert sc.grey().shape == grey.shape
    # a step wedge of 10 flat fields: one gain and offset explain every step (linear, no
    # automatic brightening, no tone curve); the brightest step is not clipped
    levels = np.linspace(1500, 52000, 10)
    wedge = np.repeat(levels, 40)[None, :].repeat(64, 0).astype(np.uint16)
    write_dng(tmp_path / "wedge.dng", wedge)
    g = load_scan(tmp_path / "wedge.dng").grey().astype(np.float64)
    means = np.array([g[16:48, 40 * i + 8:40 * i + 32].mean() for i in range(10)])
    A = np.c_[levels, np.ones(10)]
    coef, *_ = np.linalg.lstsq(A, means, rcond=None)
    assert coef[0] > 0
    assert np.abs(means - A @ coef).max() < 1e-3 * np.ptp(means)
    assert means.max() < 0.999


@pytest.mark.parametrize("orientation", [1, 6])
def test_dng_crosses_where_the_sensor_saw_them(frame, orientation):
    """Detection on the DNG finds every visible cross at its true pixel position, also when
    the file asks to be shown turned (the turn is not applied: --rotate is the user's)."""
    d, grey, truth = frame
    p = d / f"o{orientation}.dng"
    write_dng(p, grey, orientation)
    sc = load_scan(p)
    assert sc.grey().shape == grey.shape
    det = detect(sc, "rollei-6006", dpi=500).to_json()
    tm = {m["name"]: m for m in truth["marks"]}
    err = [np.hypot(m["x"] - tm[m["name"]]["x"], m["y"] - tm[m["name"]]["y"])
           for m in det["marks"] if m["status"] == "measured"]
    visible = sum(m["visible"] for m in truth["marks"])
    assert len(err) >= visible - 1
    assert np.sqrt(np.mean(np.square(err))) < 0.1


def test_corrupt_raw_one_line(tmp_path):
    from softplot.errors import SoftplotError

    p = tmp_path / "bad.dng"
    p.write_bytes(b"II*\x00garbage" * 10)
    with pytest.raises(SoftplotError) as e:
        load_scan(p)
    assert "\n" not in str(e.value)
