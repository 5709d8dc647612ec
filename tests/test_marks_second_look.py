"""A cross that passed the outlier test by its own imprecision, locked onto scene content
beside an arm, is measured again from its neighbours' prediction without each half-arm
(:func:`softplot.marks.validation.second_look`).

Exact synthetic truth: the robustness sweep's renders and their true cross centres; a gross
fit is one more than max(1 px, 8 x its Cramer-Rao bound) off its truth (the sweep's score)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import run_sweep_case
from softplot.marks import validation


@pytest.fixture(autouse=True)
def _second_look_alone(monkeypatch):
    """The second look judged alone: the neighbours' prior for flat fits, which comes after
    it (:mod:`softplot.marks.neighbour_prior`), off in both runs of each test."""
    from softplot.marks import neighbour_prior

    monkeypatch.setattr(neighbour_prior, "PRIOR_FLAT", np.inf)
    monkeypatch.setattr(neighbour_prior, "PRIOR_ANY_RATIO", np.inf)


def _run(seed, renders):
    return run_sweep_case(seed, renders)[0]


@pytest.mark.parametrize("seed", [398, 462])
def test_busy_crosses_locked_beside_an_arm_are_measured_again(seed, renders, monkeypatch):
    # 398: a Rollei at 430 dpi, thin arms (0.53 x) over a busy scene, JPEG q44; 462: a
    # Hasselblad at 478 dpi, blur 2.3 px, busy. Their first fits of R3C9, R8C5 (398) and
    # R3C3 (462) lock onto the scene 1.0-1.6 px off the truth (bounds 0.07-0.09 px) with
    # sigmas 2-5 times their peers', and pass the outlier test by them
    with monkeypatch.context() as mp:  # the counterfactual: no cross measured again
        mp.setattr(validation, "SECOND_LOOK_SPREAD", np.inf)
        first = _run(seed, renders)
    assert first.gross, "the render was expected to hold a gross first fit"
    sc = _run(seed, renders)
    assert sc.gross == [], sc.gross
    # no cross lost, and the scan's errors smaller
    assert sc.measured >= first.measured, (sc.missed, first.missed)
    assert sum(sc.err2) < 0.8 * sum(first.err2), (sum(sc.err2), sum(first.err2))
    # and their reported covariances as honest as before (normalised errors)
    assert np.mean(sc.z2) <= 1.1 * np.mean(first.z2), (np.mean(sc.z2), np.mean(first.z2))


def test_clean_crosses_keep_their_four_arm_fits(renders, monkeypatch):
    # 445: a Hasselblad at 1293 dpi, no gross fit. Its crosses farthest from their
    # neighbours' predictions are clean: their three-arm refits lie nearer the prediction
    # but are less precise. Taken for lying nearer (without the refit's precision test) they
    # made the render's RMS 1.31 -> 1.61 x its bound; kept, the render is as without a
    # second look
    with monkeypatch.context() as mp:
        mp.setattr(validation, "SECOND_LOOK_SPREAD", np.inf)
        first = _run(445, renders)
    sc = _run(445, renders)
    assert sc.measured >= first.measured
    assert sum(sc.err2) <= 1.05 * sum(first.err2), (sum(sc.err2), sum(first.err2))


def _cross_error(seed, renders, name):
    """The sweep's score of ``seed`` and the error (px, pixel system of the render) of its
    cross ``name`` against the render's true centre (NaN when not measured)."""
    from softplot.synthetic.sweep import make_case, render_case, run_case

    case = make_case(seed)
    sc, det = run_case(case, cache=renders)
    truth = {t["name"]: t for t in render_case(case, renders)[1]["marks"]}
    i = list(det.name).index(name)
    e = np.hypot(det.xy[i, 0] - truth[name]["x"], det.xy[i, 1] - truth[name]["y"])
    return sc, (float(e) if det.status[i] == "measured" else np.nan)


def _free_only(film, xy, ok, ppm, A, ids, H):
    """The corner crosses' refits with a free affine only (before the model's was held)."""
    return validation._held_groups(film, xy, ok, ppm, A, ids)


def _held_only(film, xy, ok, ppm, A, ids, H):
    """The corner crosses' refits with the model's affine held only."""
    return validation._held_groups(film, xy, ok, ppm, A, ids, H=H)


def test_corner_refits_hold_the_models_affine(renders, monkeypatch):
    # 145: a Rollei at 485 dpi, blur 2.35 px, thin arms (0.67 x) over a busy scene, JPEG.
    # The first fit of the outline cross R7C0 locks onto a road 4.1 px off its truth (bound
    # 0.17 px). Its neighbours do not surround it, so no affine is predicted from their
    # positions: refitted with a free affine only, its three half-arms turn onto the road
    # again; with the measured crosses' projective model's affine held the refit lies by the
    # cross
    with monkeypatch.context() as mp:  # the counterfactual: the corner refits' affine free
        mp.setattr(validation, "_look_groups", _free_only)
        first, e_first = _cross_error(145, renders, "R7C0")
    assert e_first > 3.0, first.gross
    sc, e = _cross_error(145, renders, "R7C0")
    assert e < 0.5 * e_first, (e, e_first)
    assert sc.measured >= first.measured, (sc.missed, first.missed)
    assert sum(sc.err2) < sum(first.err2), (sum(sc.err2), sum(first.err2))


def test_corner_refits_keep_the_free_affine_where_it_fits_better(renders, monkeypatch):
    # 452: a Rollei at 465 dpi, thin arms (0.56 x). Its corner cross R10C10 refitted with the
    # model's affine held only lies 1.03 px off its truth (bound 0.05 px, gross); its refit
    # with a free affine correlates better and lies nearer: both are fitted, the better kept
    with monkeypatch.context() as mp:  # the counterfactual: the model's affine held only
        mp.setattr(validation, "_look_groups", _held_only)
        first, e_first = _cross_error(452, renders, "R10C10")
    assert e_first > 1.0, first.gross
    sc, e = _cross_error(452, renders, "R10C10")
    assert e < e_first and sc.gross == [], (e, e_first, sc.gross)
    assert sc.measured >= first.measured, (sc.missed, first.missed)


def _one_call(film, xy, ok, ppm, A, ids, H):
    """The refits before the outline crosses held at the model's affine were a call of their
    own: fitted in one call with the surrounded crosses (then the free affine's)."""
    groups = validation._held_groups(film, xy, ok, ppm, A, ids, H=H)
    return groups + [g for g in validation._held_groups(film, xy, ok, ppm, A, ids) if g[2]]


def test_outline_refits_do_not_change_the_surrounded_crosses_scene_model(monkeypatch):
    # the second renderer's aerial scan 189 (111 dpi, dpi estimated, lines 3.7 x the
    # certificate's width over a smooth scene). Its surrounded crosses' refits take the plane
    # as the scene of their flat patches; the outline crosses' patches by the format's edge,
    # fitted in the same call, are not all flat, so the whole call took the opening's
    # estimate and refits that lay 0.2-0.5 px off their truth failed (19 more crosses over
    # 1 px off, RMS 0.98 -> 1.06 px)
    from softplot.synthetic.plain import run_plain

    with monkeypatch.context() as mp:  # the counterfactual: one call for both
        mp.setattr(validation, "_look_groups", _one_call)
        _, first = run_plain(189)
    _, row = run_plain(189)
    assert row["result"] and not row["wrong"] and not row["claimed"]
    assert row["measured"] >= first["measured"], (row["missed"], first["missed"])
    assert len(row["gross"]) <= len(first["gross"]) - 10, (len(row["gross"]),
                                                            len(first["gross"]))
    rms = np.sqrt(np.mean(np.square(row["errors"])))
    rms_first = np.sqrt(np.mean(np.square(first["errors"])))
    assert rms < 0.95 * rms_first, (rms, rms_first)
    # and the reported covariances as honest (normalised errors)
    assert np.mean(row["z2"]) <= 1.1 * np.mean(first["z2"]), (np.mean(row["z2"]),
                                                              np.mean(first["z2"]))
