"""Polarity: ``auto`` finds dark crosses (a print, a positive) and bright ones (a negative) on
8- and 16-bit, grey and RGB (an orange-masked colour negative), JPEG and low-contrast scans;
a ``--polarity`` that the scan contradicts is reported in one line naming the right one."""

from __future__ import annotations

import functools

import pytest

from conftest import sweep
from softplot.io import Scan
from softplot.marks import detect
from softplot.marks.detect import DetectionError
from softplot.synthetic import ScanSpec, render_scan

CAM = "rollei-6006"

KINDS = [dict(bits=8), dict(bits=16), dict(rgb=True), dict(rgb=True, bits=16),
         dict(file_format="jpg", jpeg_quality=60), dict(contrast=0.12, noise_sigma=0.01)]
CASES = [(pol, i) for pol in ("positive", "negative") for i in range(len(KINDS))]


@functools.lru_cache(maxsize=2)
def _scan(pol: str, i: int):
    img, truth = render_scan(CAM, ScanSpec(dpi=600, polarity=pol, **KINDS[i]), 7 + i)
    return Scan.from_array(img, dpi=600, bit_depth=truth.get("bit_depth")), truth


@pytest.mark.parametrize("pol,i", sweep(CASES, 5))
def test_auto_polarity_is_right(pol, i):
    sc, truth = _scan(pol, i)
    det = detect(sc, CAM)
    assert det.polarity == pol, KINDS[i]
    visible = sum(bool(m["visible"]) for m in truth["marks"])
    assert det.measured.sum() >= visible - 1


@pytest.mark.parametrize("pol", ["positive", "negative"])
def test_a_wrong_polarity_is_reported_in_one_line(pol):
    sc, _ = _scan(pol, 0)
    wrong = "negative" if pol == "positive" else "positive"
    with pytest.raises(DetectionError) as e:
        detect(sc, CAM, polarity=wrong)
    msg = str(e.value)
    assert "\n" not in msg
    assert f"no reseau found with --polarity {wrong}" in msg and f"--polarity {pol}" in msg
