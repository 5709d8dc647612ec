"""The joint-scene refits started ahead of the decision (issue 20 point 5, busy-scene speed):
a pool thread that finds no first-pass chunk left to start while the other still fits the
last one refits a finished chunk with the joint scene (:class:`softplot.marks.measure._Ahead`)
where the chunks done already show a busy scene. The refit is the one made after the
decision, on a pool thread as there: the detection must be the same to the last bit."""

from __future__ import annotations

import numpy as np
import pytest

from softplot import runtime
from softplot.marks import detect
from softplot.marks import measure as ME
from softplot.synthetic import ScanSpec, render_scan


@pytest.fixture
def two_threads():
    runtime.set_threads(2)
    yield
    runtime.set_threads(None)


def _same(a, b):
    assert a.status == b.status and a.reason == b.reason
    for f in ("xy", "cov", "sigma", "score", "cnr", "residual"):
        assert np.array_equal(getattr(a, f), getattr(b, f), equal_nan=True), f


def test_refits_made_ahead_give_the_detection_bit_for_bit(two_threads, monkeypatch):
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=600, scene="busy", rotation_deg=2.0),
                             3)
    ahead = []
    real = ME._Ahead.rest

    def spy(self, items):
        ahead.append((len(self.refits), len(items)))
        return real(self, items)

    monkeypatch.setattr(ME._Ahead, "rest", spy)
    got = detect(img, "rollei-6006", dpi=truth["dpi"])
    # the first pass's chunks were refitted with the joint scene, one or more of them ahead
    assert got.scene == "joint" and ahead and ahead[0][0] >= 1 and ahead[0][1] >= 3
    monkeypatch.setattr(ME, "REFIT_AHEAD", False)
    want = detect(img, "rollei-6006", dpi=truth["dpi"])
    _same(got, want)
    assert got.measured.sum() >= 100


def test_a_textured_scan_refits_nothing_ahead(two_threads, monkeypatch):
    """A smooth texture shows no busy scene in any chunk: nothing is refitted ahead (no
    thread's time spent on refits the decision does not want)."""
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=600, rotation_deg=2.0), 3)
    made = []
    real = ME._Ahead.first

    def spy(self, i):
        out = real(self, i)
        made.append(len(self.refits))
        return out

    monkeypatch.setattr(ME._Ahead, "first", spy)
    det = detect(img, "rollei-6006", dpi=truth["dpi"])
    assert det.scene == "opening" and made and max(made) == 0
    assert det.measured.sum() >= 100
