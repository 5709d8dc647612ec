"""The detector's second try with the scene taken away from the correlation
(:func:`softplot.marks.candidates.scene_removed`): over a busy scene the plain NCC of a cross
is low where the scene's edges and regions fill its window, and the other polarity's lattice
of scene peaks wins; correlated with what is narrower than the crosses' line alone, the
crosses stand out."""

import numpy as np


def test_top_hat_keeps_a_line_and_takes_a_step_and_a_ramp_away():
    """A bright line 2 px wide on a ramp beside a step of grey: the top hat (pixel system of
    the image) keeps the line's whole contrast and leaves nothing of the step and the ramp;
    of the other sign it keeps nothing of the bright line."""
    from softplot.marks.coarse import top_hat

    h, w = 60, 80
    x = np.arange(w, dtype=np.float32)
    img = np.tile(0.2 + 0.004 * x, (h, 1))  # a ramp
    img[:, 50:] += 0.3  # a step
    img[:, 20:22] += 0.25  # a bright line
    bright = top_hat(img, +1, 3.0)
    assert np.allclose(bright[:, 20:22], 0.25, atol=0.01)
    away = np.ones(w, bool)
    away[19:23] = False
    assert np.abs(bright[5:-5][:, away]).max() < 0.02  # the step and the ramp are gone
    dark = top_hat(img, -1, 3.0)
    assert np.abs(dark[5:-5, 20:22]).max() < 0.02


def _true_among_peaks(case, sign, removed):
    """How many of the render's visible crosses (truth, full-resolution pixel system) have a
    peak of ``sign`` among the candidates kept (overview pixel system) within 2 overview px."""
    from softplot.camera import load_camera
    from softplot.io import Scan
    from softplot.marks import coarse
    from softplot.marks.candidates import reseau_candidates, scene_removed
    from softplot.marks.common import MM_PER_INCH
    from softplot.marks.overview import reseau_overview
    from softplot.marks.template import cross_shape
    from softplot.synthetic.sweep import render_case

    img, truth, _, _ = render_case(case)
    bits = truth["bit_depth"] if img.dtype == np.uint16 else 8
    sc = Scan.from_array(img, dpi=truth["dpi"], bit_depth=bits)
    cam = load_camera(case.camera)
    ppm = truth["dpi"] / MM_PER_INCH
    ov = reseau_overview(sc, cross_shape(cam, ppm).width, ppm, "x")
    if removed:
        with scene_removed():
            cands = reseau_candidates(sc, ov, cam, "auto", 1.0).complete()
    else:
        cands = reseau_candidates(sc, ov, cam, "auto", 1.0).complete()
    xy = np.array([[m["x"], m["y"]] for m in truth["marks"]
                   if m["kind"] == "reseau" and m["state"] == "visible"])
    t = coarse.full_to_ov(xy, ov.factor)
    pk = cands.peaks[sign].xy
    d = np.hypot(*(t[:, None, :] - pk[None, :, :]).transpose(2, 0, 1)).min(1)
    return int((d < 2.0).sum()), len(t)


def test_busy_scene_crosses_are_candidates_with_the_scene_taken_away():
    """Sweep seed 353 (Hasselblad, dark crosses of contrast 0.45 over a busy scene, lines
    0.58x the certificate's): the plain correlation keeps few of its 15 crosses among the
    dark candidates; with the scene taken away nearly all."""
    from softplot.synthetic.sweep import make_case

    case = make_case(353)
    assert case.camera == "hasselblad-mk70" and "busy" in case.conditions
    plain, n = _true_among_peaks(case, -1, removed=False)
    removed, _ = _true_among_peaks(case, -1, removed=True)
    assert n == 15
    assert plain <= 6
    assert removed >= 12


def test_a_busy_scan_refused_by_the_plain_correlation_is_measured():
    """Seed 353 again, whole: refused with the plain correlation alone (the bright scene
    peaks' lattice wins), measured with the scene taken away: every visible cross with its
    right row and column, none claimed where no cross shows, none grossly off, within
    twice its bound (RMS)."""
    from softplot.synthetic.sweep import make_case, run_case

    sc, det = run_case(make_case(353))
    assert sc.result, sc.error
    assert det.polarity == "positive"  # dark crosses
    assert not sc.wrong and not sc.claimed and not sc.gross
    assert sc.visible == 15 and sc.measured >= 14
    assert np.mean(sc.err2) < 2.0**2 * np.mean(sc.crb2)
