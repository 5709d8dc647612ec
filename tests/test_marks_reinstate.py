"""Outline crosses that the outlier test rejects only because the neighbours' local quadratic
extrapolates a smooth film deformation badly are measured again when the whole grid's
polynomial places them (:func:`softplot.marks.validation.reinstate`); a cross locked a few
tenths of a pixel off stays rejected. Exact synthetic truth: a Hasselblad 5 x 5 reseau under
the robustness sweep's deformations (40 um, shrinkage 300 ppm) at 1450 dpi, crosses measured
with 0.005 px of noise."""
import numpy as np
import pytest

from softplot.camera import load_camera
from softplot.marks.validation import outlier_floor, reinstate, reject_outliers
from softplot.synthetic.mapping import Deformation, Scanner

DPI = 1450.0
SIGMA = 0.005
SEEDS = range(40)


def _grid(seed, shift=None):
    """Truth (M, 2) and measured (M, 2) pixel positions of the reseau, its film positions
    (M, 2) mm; ``shift`` (index, (dx, dy) px) moves one measured cross off its truth."""
    cam = load_camera("hasselblad-mk70")
    film = cam.reseau.film()
    rng = np.random.default_rng(seed)
    deform = Deformation.random(cam.format_mm, 40.0, 300.0, rng)
    true = Scanner(dpi=DPI, rotation_deg=1.0, tx=1500.0, ty=1500.0).forward(
        deform.forward(film))
    xy = true + rng.normal(0.0, SIGMA, true.shape)
    if shift is not None:
        xy[shift[0]] += shift[1]
    return film, true, xy


def _test(film, xy):
    """The outlier test, then the reinstatement: (rejected, reinstated) indices."""
    status, reason = ["measured"] * len(film), [""] * len(film)
    floor = outlier_floor(film, status, DPI / 25.4)
    Hm = reject_outliers(film, xy, status, reason, np.eye(3), np.full(len(film), SIGMA),
                         floor_px=floor)[0]
    rejected = [i for i, s in enumerate(status) if s == "rejected"]
    back = reinstate(film, xy, status, reason, floor, Hm)
    assert all(status[i] == "measured" and reason[i] == "" for i in back)
    assert all(status[i] == "rejected" for i in set(rejected) - set(back.tolist()))
    return rejected, back


def test_correct_outline_crosses_rejected_by_the_local_prediction_are_measured_again():
    rejected = back = 0
    for seed in SEEDS:
        film, true, xy = _grid(seed)
        rej, got = _test(film, xy)
        rejected += len(rej)
        back += len(got)
        # every cross here is correct (0.005 px of noise): the ones measured again too
        assert np.all(np.hypot(*(xy[got] - true[got]).T) < 0.05)
    # the counterfactual: without the reinstatement these correct crosses are lost
    assert rejected >= 20, rejected
    assert back >= 6, (back, rejected)


@pytest.mark.parametrize("shift", [(0.8, 0.0), (0.0, -0.8), (0.6, 0.6)])
def test_a_cross_locked_off_its_mark_stays_rejected(shift):
    """A top-edge cross moved 0.8 px (5.6 x the floor at 1450 dpi) that the outlier test
    rejects is never measured again."""
    rejected = 0
    for seed in SEEDS:
        film, true, xy = _grid(seed, shift=(2, np.array(shift)))
        rej, got = _test(film, xy)
        rejected += 2 in rej
        assert 2 not in got.tolist(), seed
    assert rejected >= 30, rejected
