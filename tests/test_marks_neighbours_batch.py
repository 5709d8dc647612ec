"""The neighbours' predictions in one batch give what one call per value set gives.

The scan's variance factor sends its simulated error draws through the outlier test's
leave-one-out prediction in one batch (:func:`softplot.marks.neighbours.local_prediction`
with residuals (B, M, 2)); each draw's second pass weighs its neighbours by that draw's own
departures, so a batch that shared them would give other figures. The conditioning test of
the local polynomials (a Cholesky factor of ``N - tol I`` instead of the eigenvalues) must
choose the same degrees.
"""

from __future__ import annotations

import numpy as np

from softplot.marks import neighbours
from softplot.marks.neighbours import _smallest_eig_above, local_fit, local_prediction
from softplot.marks.precision import (
    _TRIMMED_MEAN,
    DEFORMATION_FLOOR_UM,
    DRAWS,
    MAX_FACTOR,
    TRIM,
    variance_factor,
)


def _grid(seed=3, rows=11):
    """Film mm of a 5 mm reseau with a tenth of its crosses missing (gaps: mixed degrees)."""
    rng = np.random.default_rng(seed)
    g = np.stack(np.meshgrid(np.arange(11.0), np.arange(rows)), -1).reshape(-1, 2) * 5.0
    film = g + rng.normal(0, 0.01, g.shape)
    return film[rng.random(len(film)) > 0.1], rng


def test_batch_prediction_is_each_sets_own():
    film, rng = _grid()
    sig = rng.uniform(0.01, 0.05, len(film))
    R = rng.normal(0, 0.05, (6,) + film.shape)
    R[2, 7] += 1.0  # an outlier in one set only: its neighbours' weights differ per set
    batch = local_prediction(film, R, sigma=sig)
    one = np.stack([local_prediction(film, r, sigma=sig) for r in R])
    assert batch.shape == R.shape
    assert np.max(np.abs(batch - one)) < 1e-12
    # the sets do differ in their weights: the outlier's set is not the others' fit of it
    shared = local_fit(film, film, R[2], 16, 2, n_sigma=sig)
    assert np.max(np.abs(one[2] - shared)) > 1e-3


def test_partial_grid_batch_matches_one_call_per_set():
    film, rng = _grid(seed=5, rows=3)  # three rows: no cubic in y
    R = rng.normal(0, 0.05, (3,) + film.shape)
    for deg, k in ((2, 16), (3, 24)):
        batch = local_fit(film, film, R, k, deg)
        one = np.stack([local_fit(film, film, r, k, deg) for r in R])
        assert np.max(np.abs(batch - one)) < 1e-12


def test_conditioning_test_agrees_with_the_eigenvalues():
    rng = np.random.default_rng(0)
    tol = 1e-6
    for p in (3, 6, 10):
        Qm, _ = np.linalg.qr(rng.normal(size=(4000, p, p)))
        lam = rng.uniform(0.1, 3.0, (4000, p))
        # smallest eigenvalue on either side of the tolerance, by 2 % to a factor 100
        lam[:, 0] = tol * np.exp(rng.uniform(-4.6, 4.6, 4000))
        lam[::2, 0] = tol * rng.choice([0.98, 1.02], 2000)
        S = np.einsum("nij,nj,nkj->nik", Qm, lam, Qm)
        expect = np.linalg.eigvalsh(S)[:, 0] > tol
        assert 0.2 < expect.mean() < 0.8
        assert np.array_equal(_smallest_eig_above(S, tol), expect)


def _variance_factor_draw_by_draw(film, r, C, predict, ppm, seed=0):
    """The factor as computed one simulated draw at a time (the definition)."""
    L = np.linalg.cholesky(C)
    sig = np.sqrt(0.5 * (C[:, 0, 0] + C[:, 1, 1]))
    d2 = np.sum((r - predict(film, r, sigma=sig)) ** 2, 1)
    rng = np.random.default_rng(seed)
    E = np.zeros(len(film))
    for _ in range(DRAWS):
        e = np.einsum("nij,nj->ni", L, rng.standard_normal((len(film), 2)))
        E += np.sum((e - predict(film, e, sigma=sig)) ** 2, 1)
    E /= DRAWS
    b = 2.0 * (DEFORMATION_FLOOR_UM * 1e-3 * ppm) ** 2
    q = np.sort(d2 / (E + b))
    keep = q[: max(int(np.floor((1.0 - TRIM) * len(q))), 1)]
    return float(np.clip(np.mean(keep) / _TRIMMED_MEAN, 1.0, MAX_FACTOR))


def test_variance_factor_is_the_draw_by_draw_figure():
    film, rng = _grid(seed=7)
    sig = rng.uniform(0.01, 0.04, len(film))
    C = np.einsum("n,ij->nij", sig**2, np.eye(2))
    r = rng.normal(0, 1.0, film.shape) * 1.6 * sig[:, None]  # errors 1.6x the covariances
    r[4] += 0.3  # an outlier the trim leaves out
    got = variance_factor(film, r, C, neighbours.local_prediction, 47.2)
    ref = _variance_factor_draw_by_draw(film, r, C, neighbours.local_prediction, 47.2)
    assert 1.5 < ref < 4.0
    assert abs(got - ref) < 1e-9 * ref


def test_compiled_local_fit_is_the_numpy_fit(monkeypatch):
    """The compiled local fits (:func:`softplot.marks.kernels.local_solve`) give NumPy's
    figures: single sets, batches weighted by their own departures, a partial grid whose
    queries drop to lower degrees; and both reproduce an exact cubic field."""
    from softplot.marks import kernels

    if not kernels.ready():
        return
    film, rng = _grid(seed=5, rows=3)  # three rows: no cubic in y, mixed degrees
    full, _ = _grid(seed=9)
    sig = rng.uniform(0.01, 0.05, len(full))
    R = rng.normal(0, 0.05, (5,) + full.shape)
    R[1, 3] += 1.0
    x, y = full.T / 50.0
    truth = np.stack([0.3 + x - 0.5 * y**2 + 0.2 * x**3, -0.1 + x * y - 0.3 * x**2 * y], 1)

    def fits():
        return [local_fit(film, film, R[0, : len(film)], k, deg)
                for k, deg in ((16, 2), (24, 3))] + [
            local_prediction(full, R, sigma=sig), local_prediction(full, R[1], sigma=sig),
            local_fit(full[::3], full, R[2], 24, 3, n_sigma=sig),
            local_fit(full, full, truth, 24, 3)]

    got = fits()
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    ref = fits()
    for a, b in zip(got, ref, strict=True):
        assert a.shape == b.shape and np.max(np.abs(a - b)) < 1e-11
    # an exact cubic is reproduced inside the grid (to the normal equations' ridge of 1e-9)
    inner = ~neighbours.outline(full)
    assert np.max(np.abs(got[-1] - truth)[inner]) < 1e-6


def _prediction_all_rows(film, r, k_max=16, sigma=None):
    """The leave-one-out prediction with the second pass's quadratic fitted at every mark and
    then replaced by the cubic inside the grid (what ``_local_prediction`` computed before it
    fitted that quadratic on the outline only)."""
    pred = local_fit(film, film, r, k_max, 2, n_sigma=sigma)
    dev = np.hypot((r - pred)[..., 0], (r - pred)[..., 1])
    out = local_fit(film, film, r, k_max, 2, n_sigma=sigma, n_dev=dev)
    inner = ~neighbours.outline(film)
    if inner.any():
        out[..., inner, :] = local_fit(film[inner], film, r, 24, 3, n_sigma=sigma, n_dev=dev)
    return out


def test_prediction_fits_the_outline_quadratic_only_where_it_is_kept(monkeypatch):
    """The second pass's quadratic fitted at the outline's marks only gives, bit for bit, the
    figures of that pass fitted at every mark (the unit of distance from all of them; each
    fit its own): a full and a gappy grid, three rows (every mark on the outline), batches
    with an outlier in one set, compiled and NumPy fits."""
    from softplot.marks import kernels

    full, rng = _grid(seed=9)
    g = np.stack(np.meshgrid(np.arange(11.0), np.arange(11.0)), -1).reshape(-1, 2) * 5.0
    rows3, _ = _grid(seed=5, rows=3)
    for film in (g, full, rows3):
        sig = rng.uniform(0.01, 0.05, len(film))
        R = rng.normal(0, 0.05, (5,) + film.shape)
        R[1, 3] += 1.0
        # the outline's quadratic on its own marks' spacing would differ (a jittered grid):
        # the unit is all marks'
        edge = neighbours.outline(film)
        if film is full:
            part = local_fit(film, film, R[1], 16, 2, n_sigma=sig, only=edge)
            alone = local_fit(film[edge], film, R[1], 16, 2, n_sigma=sig)
            assert part.shape == alone.shape and np.max(np.abs(part - alone)) > 1e-12
        for jit in ((True, False) if kernels.ready() else (False,)):
            monkeypatch.setattr(kernels, "AVAILABLE", jit)
            for r in (R, R[1]):
                got = neighbours._local_prediction(film, r, sigma=sig)
                ref = _prediction_all_rows(film, r, sigma=sig)
                assert got.shape == ref.shape and np.array_equal(got, ref)
