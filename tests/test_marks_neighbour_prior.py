"""The neighbours' position prior for crosses whose own fit is flat along a direction
(:mod:`softplot.marks.neighbour_prior`).

Exact synthetic truth: a grid of crosses under a known projective model and a smooth film
deformation, each measured with an error drawn from its own known covariance; a quarter of
them with a covariance long along one direction (a fit whose objective is flat there)."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import run_sweep_case
from softplot.marks import grid
from softplot.marks.neighbour_prior import PRIOR_MIN_MARKS, neighbour_update
from softplot.marks.validation import prediction_cov

PPM = 20.0  # px per film mm


def _grid(seed, n=20, pitch=10.0, long_px=1.0, short_px=0.08, share=0.25):
    """Film positions (M, 2) mm, the model film mm -> pixel system, the true positions and
    the measured ones (M, 2) px, the crosses' covariances (M, 2, 2) px^2 (pixel system, the
    errors' exact ones) and which crosses are long along a direction (M,) bool."""
    rng = np.random.default_rng(seed)
    g = np.arange(n) * pitch
    film = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    c, s = np.cos(0.02), np.sin(0.02)
    H = np.array([[PPM * c, -PPM * s, 50.0], [PPM * s, PPM * c, 80.0], [1e-6, 2e-6, 1.0]])
    # a smooth deformation of a few px over the frame, which the local quadratic follows
    span = g[-1]
    deform = 2.0 * np.stack([np.sin(film[:, 0] / span * 2.0),
                             np.cos(film[:, 1] / span * 1.5)], -1)
    true = grid.apply_h(H, film) + deform
    M = len(film)
    flat = rng.random(M) < share
    ang = rng.uniform(0, np.pi, M)
    u = np.stack([np.cos(ang), np.sin(ang)], -1)
    v = np.stack([-u[:, 1], u[:, 0]], -1)
    lam = np.where(flat, long_px, short_px) ** 2
    cov = (lam[:, None, None] * u[:, :, None] * u[:, None, :]
           + short_px**2 * v[:, :, None] * v[:, None, :])
    e = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.standard_normal((M, 2)))
    return film, H, true, true + e, cov, flat


def _sigma(cov):
    return np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_flat_fits_take_their_neighbours_prediction_honestly(seed):
    film, H, true, xy, cov, flat = _grid(seed)
    out, W, sel = neighbour_update(film, xy, cov, _sigma(cov), H, PPM, 0.3, prediction_cov)
    # the long fits are updated, the precise ones keep their own fit
    assert sel[flat].mean() > 0.95, sel[flat].mean()
    assert not sel[~flat].any()
    assert np.array_equal(out[~sel], xy[~sel]) and np.array_equal(W[~sel], cov[~sel])
    # the updated crosses lie much nearer their truth (the errors along their flat direction
    # are the prediction's, not the fit's)
    e0 = np.sqrt(np.mean(np.sum((xy[sel] - true[sel]) ** 2, 1)))
    e1 = np.sqrt(np.mean(np.sum((out[sel] - true[sel]) ** 2, 1)))
    assert e1 < 0.4 * e0, (e1, e0)
    # and the reported covariances hold: normalised errors of RMS near 1
    d = out[sel] - true[sel]
    z2 = np.einsum("ni,nij,nj->n", d, np.linalg.inv(W[sel]), d) / 2.0
    assert 0.75 < np.sqrt(np.mean(z2)) < 1.3, np.sqrt(np.mean(z2))
    # and the update never reports a covariance larger than the fit's
    assert np.all(np.linalg.eigvalsh(cov[sel] - W[sel]) > -1e-12)


def _even_grid(seed, n=20, pitch=10.0, sigma_px=0.5, spread=0.5):
    """:func:`_grid` of crosses whose fits are all imprecise and none long along a
    direction (a busy scan: isotropic covariances, sigmas log-normal about ``sigma_px``
    with log spread ``spread``), each measured with an error drawn from its covariance."""
    film, H, true, _, _, _ = _grid(seed, n, pitch)
    rng = np.random.default_rng(seed + 100)
    sig = sigma_px * np.exp(spread * rng.standard_normal(len(film)))
    cov = sig[:, None, None] ** 2 * np.eye(2)
    return film, H, true, true + sig[:, None] * rng.standard_normal((len(film), 2)), cov


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fits_far_less_precise_than_their_neighbours_prediction_take_it(seed, monkeypatch):
    # a scan whose scene disturbs the fits: every fit imprecise, none flat beside its peers;
    # where a fit's variance is PRIOR_ANY_RATIO times its neighbours' prediction's, the
    # update takes it there
    from softplot.marks import neighbour_prior

    film, H, true, xy, cov = _even_grid(seed)
    with monkeypatch.context() as mp:  # the counterfactual: the flat fits alone
        mp.setattr(neighbour_prior, "PRIOR_ANY_RATIO", np.inf)
        out0, _, sel0 = neighbour_update(film, xy, cov, _sigma(cov), H, PPM, 0.3,
                                         prediction_cov, disturbed=True)
    out, W, sel = neighbour_update(film, xy, cov, _sigma(cov), H, PPM, 0.3, prediction_cov,
                                   disturbed=True)
    assert sel0.sum() < sel.sum() and sel.mean() > 0.15, (sel0.sum(), sel.sum())
    assert np.all(sel[sel0])  # the flat fits' update is unchanged
    assert np.array_equal(out[~sel], xy[~sel]) and np.array_equal(W[~sel], cov[~sel])

    # against the exact truth: the scan's crosses nearer their truth, the updated ones much
    def rms(p, k):
        return np.sqrt(np.mean(np.sum((p[k] - true[k]) ** 2, 1)))

    every = np.ones(len(xy), bool)
    assert rms(out, every) < 0.9 * rms(out0, every), (rms(out, every), rms(out0, every))
    assert rms(out, sel) < 0.6 * rms(xy, sel), (rms(out, sel), rms(xy, sel))
    # with honest covariances (normalised errors of RMS near 1)
    d = out[sel] - true[sel]
    z2 = np.einsum("ni,nij,nj->n", d, np.linalg.inv(W[sel]), d) / 2.0
    assert 0.75 < np.sqrt(np.mean(z2)) < 1.3, np.sqrt(np.mean(z2))


def test_an_undisturbed_scan_updates_its_flat_fits_alone(monkeypatch):
    # on a scan whose scene does not disturb the fits, a cross keeps its own fit unless it is
    # flat beside its peers (the reported crosses stay independent measurements)
    from softplot.marks import neighbour_prior

    film, H, true, xy, cov = _even_grid(0)
    out, W, sel = neighbour_update(film, xy, cov, _sigma(cov), H, PPM, 0.3, prediction_cov)
    monkeypatch.setattr(neighbour_prior, "PRIOR_ANY_RATIO", np.inf)
    out0, W0, sel0 = neighbour_update(film, xy, cov, _sigma(cov), H, PPM, 0.3, prediction_cov,
                                      disturbed=True)
    assert np.array_equal(sel, sel0) and np.array_equal(out, out0) and np.array_equal(W, W0)


def test_a_small_grid_keeps_its_own_fits():
    # on a small grid the prediction leans on the global model the cross itself helps fit
    film, H, true, xy, cov, flat = _grid(0, n=4)
    assert len(film) < PRIOR_MIN_MARKS
    out, W, sel = neighbour_update(film, xy, cov, _sigma(cov), H, PPM, 0.3, prediction_cov)
    assert not sel.any() and np.array_equal(out, xy) and np.array_equal(W, cov)


def _run(seed, renders):
    return run_sweep_case(seed, renders)


def _leaning(doc):
    """The names of the measured crosses the result says lean on their neighbours, and
    whether a warning counts them."""
    names = {m["name"] for m in doc["marks"] if m["from_neighbours"]}
    assert all(m["status"] == "measured" for m in doc["marks"] if m["from_neighbours"])
    return names, any("lean on their neighbours' prediction" in w for w in doc["warnings"])


@pytest.mark.parametrize("seed", [145, 273])
def test_the_sweeps_flat_fits_take_their_neighbours_prediction(seed, renders, monkeypatch):
    # 145: a Rollei at 485 dpi, blur 2.35 px, thin arms (0.67 x) over a busy scene, JPEG;
    # 273: a Rollei at 416 dpi, thin lines (0.67 x) over a busy scene. Their gross fits lie
    # 1-4 px off their truth with sigmas several times their peers' (normalised errors near
    # 1: the sigma knows, the fit errs), where the neighbours predict them to a few tenths
    from softplot.marks import neighbour_prior

    with monkeypatch.context() as mp:  # the counterfactual: no prior
        mp.setattr(neighbour_prior, "PRIOR_FLAT", np.inf)
        mp.setattr(neighbour_prior, "PRIOR_ANY_RATIO", np.inf)
        first, doc_first = _run(seed, renders)
    assert len(first.gross) >= 8, first.gross
    sc, doc = _run(seed, renders)
    # the result says which crosses lean on their neighbours (their errors correlate)
    assert _leaning(doc_first) == (set(), False)
    names, warned = _leaning(doc)
    assert len(names) >= 3 and warned, names
    assert len(sc.gross) <= len(first.gross) - 3, (sc.gross, first.gross)
    assert sc.measured == first.measured
    assert sum(sc.err2) < 0.8 * sum(first.err2), (sum(sc.err2), sum(first.err2))
    # the reported covariances as honest as before (normalised errors)
    z, z_first = np.sqrt(np.mean(sc.z2)), np.sqrt(np.mean(first.z2))
    assert 0.67 < z < 1.5 and z <= 1.15 * z_first, (z, z_first)


def test_the_qc_plot_rings_the_crosses_that_lean_on_their_neighbours(tmp_path, monkeypatch):
    """The QC plot shows which crosses' positions lean on their neighbours' prediction
    (a legend entry counting them, as the JSON flags them); none with the prior off."""
    from matplotlib.figure import Figure

    from softplot.camera import load_camera
    from softplot.io import Scan
    from softplot.marks import detect, neighbour_prior
    from softplot.marks.qc import plot_qc
    from softplot.synthetic.sweep import make_case, render_case

    case = make_case(273)
    img, truth, _, _ = render_case(case, tmp_path)
    bits = truth["bit_depth"] if img.dtype == np.uint16 else 8
    scan = Scan.from_array(img, dpi=truth["dpi"], bit_depth=bits)
    saved = []
    real = Figure.savefig

    def spy(self, *a, **k):
        saved.append([t.get_text() for ax in self.axes if ax.get_legend()
                      for t in ax.get_legend().get_texts()])
        return real(self, *a, **k)

    monkeypatch.setattr(Figure, "savefig", spy)

    def labels():
        det = detect(scan, load_camera(case.camera), dpi=truth["dpi"], rotate=case.rotate)
        plot_qc(det, scan, tmp_path / "qc.png")
        n = int(np.sum(det.from_neighbours & det.measured))
        return n, [t for t in saved[-1] if t.startswith("from neighbours")]

    n, got = labels()
    assert n >= 3 and got == [f"from neighbours ({n})"], (n, got)
    with monkeypatch.context() as mp:
        mp.setattr(neighbour_prior, "PRIOR_FLAT", np.inf)
        mp.setattr(neighbour_prior, "PRIOR_ANY_RATIO", np.inf)
        assert labels() == (0, [])
