"""softplot.adjust: Gauss-Markov / Gauss-Helmert estimates, statistics, constraints, diagnosis."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse
import scipy.stats

from softplot.adjust import (
    UndeterminedError,
    critical_value,
    gauss_helmert,
    least_squares,
    linear_least_squares,
)
from softplot.errors import SoftplotError


def _line(n=20, seed=0, sigma=0.01):
    rng = np.random.default_rng(seed)
    t = np.linspace(-1, 1, n)
    A = np.c_[np.ones(n), t, t**2]
    x = np.array([1.0, -2.0, 0.5])
    return A, x, A @ x + rng.normal(0, sigma, n), rng


def test_linear_matches_closed_form_and_statistics():
    A, x, l, rng = _line()
    s = np.full(l.size, 0.01)
    s[::3] = 0.02
    adj = linear_least_squares(A, l, s, names=("a", "b", "c"), sigma0_prior=0.01)
    P = np.diag((0.01 / s) ** 2)
    N = A.T @ P @ A
    xh = np.linalg.solve(N, A.T @ P @ l)
    np.testing.assert_allclose(adj.x, xh, rtol=1e-12, atol=1e-13)
    v = A @ xh - l
    r = l.size - 3
    assert adj.redundancy == r
    assert adj.sigma0 == pytest.approx(np.sqrt(v @ P @ v / r), rel=1e-10)
    np.testing.assert_allclose(adj.covariance, adj.sigma0**2 * np.linalg.inv(N), rtol=1e-9)
    np.testing.assert_allclose(adj.residuals, v, atol=1e-12)
    assert adj.redundancy_numbers.sum() == pytest.approx(r, rel=1e-10)
    assert adj.value("b") == pytest.approx(xh[1])
    np.testing.assert_allclose(np.diag(adj.correlation), 1.0)
    assert 0 < adj.global_test_p <= 1
    text = adj.summary()
    assert "converged" in text and f"r = {r}" in text and "+- " in text


def test_noise_free_recovery():
    A, x, _, _ = _line()
    adj = linear_least_squares(A, A @ x)
    np.testing.assert_allclose(adj.x, x, rtol=1e-12)


def test_nonlinear_exponential_and_sigma0_statistics():
    # y = a exp(b t): mean sigma0 over trials ~ input sigma, spread of b ~ reported std
    t = np.linspace(0, 2, 25)
    truth = np.array([2.0, -0.7])

    def fun(x):
        e = np.exp(x[1] * t)
        return x[0] * e, np.c_[e, x[0] * t * e]

    rng = np.random.default_rng(7)
    sig = 0.01
    s0, est, var = [], [], []
    for _ in range(300):
        l = fun(truth)[0] + rng.normal(0, sig, t.size)
        adj = least_squares(fun, [1.0, 0.0], l, sig, sigma0_prior=sig)
        assert adj.converged
        s0.append(adj.sigma0)
        est.append(adj.x)
        var.append(np.diag(adj.covariance))
    s0 = np.array(s0)
    # E[sigma0] = sigma * c4(r): r = 23 -> 0.989
    assert np.mean(s0**2) == pytest.approx(sig**2, rel=0.06)
    emp = np.var(np.array(est), axis=0)
    rep = np.mean(np.array(var), axis=0)
    np.testing.assert_allclose(emp / rep, 1.0, atol=0.15)


def test_fixed_unknown_and_constraint_agree():
    A, x, l, _ = _line()
    a1 = linear_least_squares(A, l, x0=np.array([0.0, 0.0, 0.5]), fixed=[False, False, True])
    a2 = linear_least_squares(
        A, l, constraints=lambda xx: (np.array([xx[2] - 0.5]), np.array([[0.0, 0.0, 1.0]]))
    )
    np.testing.assert_allclose(a1.x, a2.x, atol=1e-12)
    assert a1.redundancy == a2.redundancy == l.size - 2
    np.testing.assert_allclose(a1.covariance, a2.covariance, atol=1e-14)
    assert a2.std[2] == pytest.approx(0.0, abs=1e-9)
    assert a2.n_constraints == 1


def test_singular_names_unknowns():
    t = np.linspace(0, 1, 10)
    A = np.c_[t, 2 * t, np.ones(10)]  # a and b only as a + 2b
    with pytest.raises(UndeterminedError, match=r"not determined: a, b") as e:
        linear_least_squares(A, t, names=("a", "b", "c"))
    assert e.value.names == ("a", "b")
    assert isinstance(e.value, SoftplotError)
    # a zero column
    A = np.c_[t, np.zeros(10), np.ones(10)]
    with pytest.raises(UndeterminedError, match=r"not determined: b$"):
        linear_least_squares(A, t, names=("a", "b", "c"))
    # a constraint that fixes the defect makes it determined
    A = np.c_[t, 2 * t, np.ones(10)]
    adj = linear_least_squares(
        A,
        t,
        names=("a", "b", "c"),
        constraints=lambda xx: (np.array([xx[1]]), np.array([[0.0, 1.0, 0.0]])),
    )
    assert adj.value("a") == pytest.approx(1.0)


def test_too_few_observations():
    with pytest.raises(SoftplotError):
        linear_least_squares(np.ones((2, 3)), np.ones(2))


def test_data_snooping_flags_blunder():
    A, x, l, _ = _line(n=30, seed=3, sigma=0.01)
    l = l.copy()
    l[11] += 0.15  # 15 sigma
    adj = linear_least_squares(A, l, 0.01, sigma0_prior=0.01)
    assert critical_value(0.001) == pytest.approx(3.2905, abs=1e-4)
    assert adj.flagged[11]
    assert int(np.nanargmax(np.abs(adj.standardized))) == 11
    clean = linear_least_squares(A, A @ x + 0.0, 0.01, sigma0_prior=0.01)
    assert not clean.flagged.any()


def test_standardised_residuals_are_unit_normal():
    A, x, _, rng = _line(n=15)
    ws = []
    for _ in range(300):
        l = A @ x + rng.normal(0, 0.01, 15)
        ws.append(linear_least_squares(A, l, 0.01, sigma0_prior=0.01).standardized)
    ws = np.array(ws)
    assert np.std(ws) == pytest.approx(1.0, abs=0.05)


def test_gauss_helmert_equals_gauss_markov_for_explicit_model():
    A, x, l, _ = _line()
    s = np.linspace(0.01, 0.02, l.size)

    def cond(xx, lh):
        return A @ xx - lh, A, -np.eye(l.size)

    gh = gauss_helmert(cond, np.zeros(3), l, s, sigma0_prior=0.01)
    gm = linear_least_squares(A, l, s, sigma0_prior=0.01)
    np.testing.assert_allclose(gh.x, gm.x, atol=1e-12)
    np.testing.assert_allclose(gh.residuals, gm.residuals, atol=1e-12)
    np.testing.assert_allclose(gh.covariance, gm.covariance, rtol=1e-8)
    np.testing.assert_allclose(gh.qvv, gm.qvv, rtol=1e-8, atol=1e-14)
    assert gh.redundancy == gm.redundancy
    # sparse B gives the same
    gh2 = gauss_helmert(
        lambda xx, lh: (A @ xx - lh, A, -scipy.sparse.identity(l.size, format="csr")),
        np.zeros(3),
        l,
        s,
        sigma0_prior=0.01,
    )
    np.testing.assert_allclose(gh2.x, gm.x, atol=1e-12)
    np.testing.assert_allclose(gh2.standardized, gm.standardized, rtol=1e-8)


def test_gauss_helmert_line_fit_errors_in_both_coordinates():
    # orthogonal regression of a line y = a + b x with errors in x and y (equal sigma)
    rng = np.random.default_rng(11)
    n, sig = 40, 0.05
    xt = np.linspace(0, 10, n)
    a, b = 1.0, 0.8
    obs = np.c_[xt, a + b * xt].ravel() + rng.normal(0, sig, 2 * n)

    def cond(p, lh):
        X, Y = lh[0::2], lh[1::2]
        F = p[0] + p[1] * X - Y
        A = np.c_[np.ones(n), X]
        B = scipy.sparse.lil_matrix((n, 2 * n))
        B[np.arange(n), 2 * np.arange(n)] = p[1]
        B[np.arange(n), 2 * np.arange(n) + 1] = -1.0
        return F, A, B.tocsr()

    gh = gauss_helmert(cond, [0.0, 1.0], obs, sig, sigma0_prior=sig)
    # total least squares closed form: direction = principal axis
    P = obs.reshape(-1, 2)
    c = P.mean(0)
    _, _, Vt = np.linalg.svd(P - c)
    slope = Vt[0, 1] / Vt[0, 0]
    assert gh.x[1] == pytest.approx(slope, rel=1e-9)
    assert gh.x[0] == pytest.approx(c[1] - slope * c[0], rel=1e-9)
    assert gh.redundancy == n - 2
    # adjusted points lie on the line
    lh = (obs + gh.residuals).reshape(-1, 2)
    np.testing.assert_allclose(gh.x[0] + gh.x[1] * lh[:, 0], lh[:, 1], atol=1e-10)


# --- data snooping without a known a priori precision (Pope's tau test) -------------------


def test_tau_critical_value_limits():
    from softplot.adjust import tau_critical_value

    # below sqrt(r) (the largest |tau| possible), tends to the normal value as r grows
    for r in (2, 3, 5, 11, 50):
        assert tau_critical_value(r, 0.001) < np.sqrt(r)
    assert tau_critical_value(10**6, 0.001) == pytest.approx(critical_value(0.001), abs=1e-3)
    assert np.isnan(tau_critical_value(1, 0.001))
    with pytest.raises(SoftplotError):
        tau_critical_value(10, 0.0)


def test_tau_test_false_alarm_rate_is_alpha0():
    # unit weights (precision unknown): |tau| exceeds its critical value with probability
    # alpha0 for every observation, whatever the noise level (here 0.37); the normal critical
    # value would give 0.041 here instead of 0.05
    from softplot.adjust import data_snooping

    A, x, _, rng = _line(n=12)
    adj = linear_least_squares(A, A @ x + rng.normal(0, 0.37, 12), alpha0=0.05)
    assert adj.snooping_test == "pope-tau"
    qvv = adj.qvv  # the same for every trial of this linear model
    np.testing.assert_allclose(
        qvv, np.diag(np.eye(12) - A @ np.linalg.solve(A.T @ A, A.T)), atol=1e-12
    )
    H = A @ np.linalg.solve(A.T @ A, A.T)
    L = A @ x + rng.normal(0, 0.37, (20000, 12))
    V = L @ H.T - L
    hits = sum(int(data_snooping(v, qvv, np.ones(12), 9, alpha0=0.05).flagged.sum()) for v in V)
    # 12000 expected; the 12 of a trial are correlated: sd < 1.5 %
    assert hits / V.size == pytest.approx(0.05, rel=0.06)
    # the adjustment's own statistic is the same function
    same = data_snooping(adj.residuals, adj.qvv, adj.weights, adj.redundancy, alpha0=0.05)
    np.testing.assert_allclose(adj.standardized, same.statistic, rtol=1e-12)


def test_tau_flags_a_blunder_that_w_against_a_unit_prior_misses():
    A, x, l, _ = _line(n=30, seed=3, sigma=0.003)
    l = l.copy()
    l[11] += 0.05  # 17 sigma, but far below the unit a priori sigma0 of unit weights
    tau = linear_least_squares(A, l)  # unit weights: precision not given
    w = linear_least_squares(A, l, precision_known=True)  # the old test (sigma0 prior = 1)
    assert tau.snooping_test == "pope-tau" and w.snooping_test == "baarda-w"
    assert not w.flagged.any()
    assert tau.blunders() == [11]
    assert tau.critical_value == pytest.approx(
        np.sqrt(27) * (t := scipy.stats.t.ppf(1 - 0.0005, 26)) / np.sqrt(26 + t * t)
    )
    assert "Pope's tau test" in tau.summary()
    clean = linear_least_squares(A, A @ x + np.random.default_rng(5).normal(0, 0.003, 30))
    assert clean.blunders() == []


def test_snooping_ranks_labels_most_likely_first():
    from softplot.adjust import data_snooping, snooping_json

    v = np.array([0.1, -5.0, 0.2, 4.0, 0.0, -0.1])
    sn = data_snooping(v, np.full(6, 0.5), np.ones(6), 4, sigma0_prior=0.1)
    assert sn.test == "baarda-w"
    assert sn.ranked() == [1, 3]
    d = snooping_json(sn, ["A", "B", "B", "C", "C", "D"])
    assert d["blunders"] == ["B", "C"]
    assert d["snooping_test"]["test"] == "baarda-w"
    assert d["snooping_test"]["critical_value"] == pytest.approx(3.2905, abs=1e-4)
    # too little redundancy to locate a blunder: said, nothing flagged
    none = data_snooping(v, np.full(6, 0.5), np.ones(6), 1)
    assert none.test == "none" and not none.flagged.any()
    assert none.to_json()["critical_value"] is None
    with pytest.raises(SoftplotError, match="labels"):
        sn.ranked(["A"])
