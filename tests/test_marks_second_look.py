"""A cross that passed the outlier test by its own imprecision, locked onto scene content
beside an arm, is measured again from its neighbours' prediction without each half-arm
(:func:`softplot.marks.validation.second_look`).

Exact synthetic truth: the robustness sweep's renders and their true cross centres; a gross
fit is one more than max(1 px, 8 x its Cramer-Rao bound) off its truth (the sweep's score)."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.marks import validation


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A folder the renders are kept in (each seed rendered once for both runs)."""
    return tmp_path_factory.mktemp("renders")


def _run(seed, cache):
    from softplot.synthetic.sweep import make_case, run_case

    sc, det = run_case(make_case(seed), cache=cache)
    assert sc.result and not sc.wrong and not sc.claimed, (sc.error, sc.wrong, sc.claimed)
    return sc


@pytest.mark.parametrize("seed", [398, 462])
def test_busy_crosses_locked_beside_an_arm_are_measured_again(seed, cache, monkeypatch):
    # 398: a Rollei at 430 dpi, thin arms (0.53 x) over a busy scene, JPEG q44; 462: a
    # Hasselblad at 478 dpi, blur 2.3 px, busy. Their first fits of R3C9, R8C5 (398) and
    # R3C3 (462) lock onto the scene 1.0-1.6 px off the truth (bounds 0.07-0.09 px) with
    # sigmas 2-5 times their peers', and pass the outlier test by them
    with monkeypatch.context() as mp:  # the counterfactual: no cross measured again
        mp.setattr(validation, "SECOND_LOOK_SPREAD", np.inf)
        first = _run(seed, cache)
    assert first.gross, "the render was expected to hold a gross first fit"
    sc = _run(seed, cache)
    assert sc.gross == [], sc.gross
    # no cross lost, and the scan's errors smaller
    assert sc.measured >= first.measured, (sc.missed, first.missed)
    assert sum(sc.err2) < 0.8 * sum(first.err2), (sum(sc.err2), sum(first.err2))
    # and their reported covariances as honest as before (normalised errors)
    assert np.mean(sc.z2) <= 1.1 * np.mean(first.z2), (np.mean(sc.z2), np.mean(first.z2))


def test_clean_crosses_keep_their_four_arm_fits(cache, monkeypatch):
    # 445: a Hasselblad at 1293 dpi, no gross fit. Its crosses farthest from their
    # neighbours' predictions are clean: their three-arm refits lie nearer the prediction
    # but are less precise. Taken for lying nearer (without the refit's precision test) they
    # made the render's RMS 1.31 -> 1.61 x its bound; kept, the render is as without a
    # second look
    with monkeypatch.context() as mp:
        mp.setattr(validation, "SECOND_LOOK_SPREAD", np.inf)
        first = _run(445, cache)
    sc = _run(445, cache)
    assert sc.measured >= first.measured
    assert sum(sc.err2) <= 1.05 * sum(first.err2), (sum(sc.err2), sum(first.err2))
