"""Crosses of another size than the others (a larger centre cross) measured with their own size
(:func:`softplot.marks.measurement.other_sizes`), against the render's truth."""

from __future__ import annotations

import numpy as np

from softplot.marks import detect
from softplot.synthetic import ScanSpec, render_scan
from test_marks_accuracy import evaluate, scan_of


def test_a_centre_cross_twice_the_size_is_measured_after_two_refits():
    # the robustness sweep's seed 417: a Rollei at 465 dpi with short arms (0.64 x) and a
    # centre cross twice the others' size. Fitted in a window for the others it came out
    # 1.47 times their size (refused as the wrong size), and the 1.5 times larger template
    # 1.47 times larger again: refused once more, the one cross of 121 not measured. The
    # refit that starts at the size the last one found (2.2 times) measures it
    spec = ScanSpec(dpi=465.147, blur_sigma_px=0.887, noise_sigma=0.00584, contrast=0.382,
                    background=0.902, scene="texture", deform_um=27.5, shrink_ppm=152.9,
                    rotation_deg=181.927, anisotropy_ppm=-213.7, bits=8, margin_mm=1.0,
                    mark_arm_scale=0.6372, mark_width_scale=1.227, mark_opacity=0.8746,
                    centre_scale=2.0)
    img, truth = render_scan("rollei-6006", spec, 417)
    det = detect(scan_of(img, truth), "rollei-6006", dpi=truth["dpi"], rotate=180)
    res = evaluate(det, truth, "rollei-6006")
    assert not res["wrong"] and not res["claimed"]
    assert res["visible"] == 121
    assert res["measured"] == 121, res["missed"]
    i = det.name.index("R5C5")
    t = next(m for m in truth["marks"] if m["name"] == "R5C5")
    err = float(np.hypot(*(det.xy[i] - (t["x"], t["y"]))))
    # the bound of a cross twice the size is below the others' (0.017 px rms)
    assert err < 0.05, err
    assert res["rms"] <= 2.0 * res["crb_rms"], (res["rms"], res["crb_rms"])


def test_each_refit_starts_at_the_size_the_last_found_up_to_the_rounds():
    # a refit refused as the wrong size (its fitted affine scales the mark by 1.3 over the
    # larger template, pixel -> mark frame) is followed by one at the product of the
    # scales, at most OTHER_SIZE_ROUNDS fits in all (scene content that grows whatever the
    # template is no cross of another size: refused in the end)
    from softplot.marks import measurement as mm
    from softplot.marks.measure import Fine
    from softplot.marks.template import MarkShape

    calls = []
    A0 = np.tile(np.eye(2) / 10.0, (1, 1, 1))

    def fake_measure(sc, shape, c0, A, s0, *a, **k):
        calls.append(shape.length)
        n = len(c0)
        A_fit = A / 1.3  # scales the mark by 1.3 over the template, every time
        return Fine(np.asarray(c0, float), np.zeros((n, 2, 2)), np.ones(n), np.ones(n),
                    np.zeros(n, bool), ["wrong size"] * n, None, A_fit, None, 0,
                    np.ones(n), None, np.zeros((n, 2, 2)), np.ones(n), np.zeros((n, 2, 2)))

    fine = Fine(np.array([[50.0, 50.0]]), np.zeros((1, 2, 2)), np.ones(1), np.ones(1),
                np.zeros(1, bool), ["wrong size"], None, A0 / 1.3, None, 0, np.ones(1), None,
                np.zeros((1, 2, 2)), np.ones(1), np.zeros((1, 2, 2)))
    orig = mm.measure
    mm.measure = fake_measure
    try:
        mm.other_sizes(None, MarkShape("cross", length=10.0, width=1.0), fine.xy, A0,
                       fine.xy, fine, 1.0, 1.0, -1, None, 3.0)
    finally:
        mm.measure = orig
    # 1.3 x the first refusal's scale, then 1.3^2 (1.7 x, rounded to a tenth), then 1.7 x 1.3
    assert len(calls) == mm.OTHER_SIZE_ROUNDS
    assert np.allclose(calls, [13.0, 17.0, 22.0])
    assert not fine.ok[0]
