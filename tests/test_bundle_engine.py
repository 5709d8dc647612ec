"""Sparse Schur LM engine: steps and covariance blocks against dense normal equations."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.adjust.bal import BALModel, BALProblem, solve_bal
from softplot.adjust.sparse_bundle import (
    Evaluation,
    Linearization,
    LMOptions,
    NormalInverse,
    SchurStructure,
    inv3,
    levenberg_marquardt,
)


def synthetic_bal(n_cam=5, n_pts=60, noise=0.5, seed=0, perturb=True):
    """A small BAL problem with exact truth: cameras on an arc looking at a point cloud."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(seed)
    pts = rng.uniform(-1, 1, (n_pts, 3)) + [0, 0, 0]
    cams = np.zeros((n_cam, 9))
    for i in range(n_cam):
        ang = -0.4 + 0.8 * i / max(n_cam - 1, 1)
        # camera centre on a circle of radius 6 around the cloud, looking at the origin
        C = np.array([6 * np.sin(ang), 0.3 * i, 6 * np.cos(ang)])
        zc = C / np.linalg.norm(C)  # camera +z points away from the scene (BAL looks along -z)
        xc = np.cross([0, 1, 0], zc)
        xc /= np.linalg.norm(xc)
        yc = np.cross(zc, xc)
        R = np.vstack([xc, yc, zc])
        cams[i, :3] = Rotation.from_matrix(R).as_rotvec()
        cams[i, 3:6] = -R @ C
        cams[i, 6] = 800.0 + 10 * i
        cams[i, 7] = -0.05
        cams[i, 8] = 0.01
    ci, pi = np.meshgrid(np.arange(n_cam), np.arange(n_pts), indexing="ij")
    ci, pi = ci.ravel(), pi.ravel()
    keep = (rng.random(ci.size) < 0.8) | (ci == 0) | (ci == n_cam - 1)  # >= 2 rays per point
    ci, pi = ci[keep], pi[keep]
    prob = BALProblem(ci, pi, np.zeros((ci.size, 2)), cams, pts)
    model = BALModel(prob)
    xy = model.evaluate((cams, pts), False).r  # residual = predicted - 0
    prob.xy = xy + noise * rng.standard_normal(xy.shape)
    truth = (cams.copy(), pts.copy())
    if perturb:
        prob.cameras = cams.copy()
        prob.cameras[:, :6] += rng.normal(0, 1e-2, (n_cam, 6))
        prob.points = pts + rng.normal(0, 0.02, pts.shape)
    return prob, truth


class Anchored(BALModel):
    """BAL model with priors on camera 0 and on points 0 and 1 (removes the gauge freedom)."""

    def __init__(self, problem, **kw):
        super().__init__(problem, **kw)
        self.c_ref = problem.cameras[0].copy()
        self.p_ref = problem.points[:2].copy()

    def evaluate(self, state, jacobian):
        ev = super().evaluate(state, jacobian)
        cams, pts = state
        idx = np.arange(9)
        w = np.full(9, 30.0)
        ev.cam_prior = (idx, w * (cams[0] - self.c_ref), w)
        J = np.broadcast_to(np.eye(3) * 20.0, (2, 3, 3)).copy()
        ev.pt_prior = (np.array([0, 1]), 20.0 * (pts[:2] - self.p_ref), J)
        return ev


def dense_system(model, state):
    """Dense J (observations then priors) of a model, columns: camera side then points."""
    st = model.structure
    ev = model.evaluate(state, True)
    m, d = ev.r.shape
    nc, npt = st.n_cam, st.n_pts
    rows = []
    J = np.zeros((m * d, nc + 3 * npt))
    for o in range(m):
        for i, col in enumerate(st.group_params[st.obs_group[o]]):
            if col < nc:
                J[o * d : (o + 1) * d, col] += ev.Jc[o, :, i]
        p = st.obs_point[o]
        if p >= 0:
            J[o * d : (o + 1) * d, nc + 3 * p : nc + 3 * p + 3] = ev.Jp[o]
    rows.append(ev.r.ravel())
    blocks = [J]
    if ev.cam_prior is not None:
        idx, r, jd = ev.cam_prior
        Jc = np.zeros((idx.size, nc + 3 * npt))
        Jc[np.arange(idx.size), idx] = jd
        blocks.append(Jc)
        rows.append(r)
    if ev.pt_prior is not None:
        idx, r, Jpp = ev.pt_prior
        Jq = np.zeros((3 * idx.size, nc + 3 * npt))
        for s, p in enumerate(idx):
            Jq[3 * s : 3 * s + 3, nc + 3 * p : nc + 3 * p + 3] = Jpp[s]
        blocks.append(Jq)
        rows.append(r.ravel())
    return np.vstack(blocks), np.concatenate(rows), ev


@pytest.mark.parametrize("dense_limit,tilde", [(4000, False), (4000, True), (0, False)])
def test_damped_step_matches_dense_normal_equations(dense_limit, tilde):
    prob, _ = synthetic_bal()
    model = Anchored(prob, dense_limit=dense_limit)
    model.structure.tilde_ok = tilde  # pair GEMMs or one dense product for W V^-1 W'
    state = (prob.cameras.copy(), prob.points.copy())
    J, r, ev = dense_system(model, state)
    lin = Linearization(model.structure, ev)
    lam = 1e-3
    Dc = np.clip(lin.diag_c, 1e-6, 1e32)
    Dp = np.clip(lin.diag_p, 1e-6, 1e32)
    dc, dp = lin.solve(lam * Dc, lam * Dp)
    N = J.T @ J
    N[np.diag_indices_from(N)] += lam * np.concatenate([Dc, Dp.ravel()])
    x = np.linalg.solve(N, -J.T @ r)
    got = np.concatenate([dc, dp.ravel()])
    assert np.allclose(got, x, rtol=1e-7, atol=1e-9 * np.abs(x).max())
    # the engine's model decrease equals the dense one
    pred = 0.5 * (r @ r - np.sum((r + J @ x) ** 2))
    assert lin.model_decrease(dc, dp) == pytest.approx(pred, rel=1e-8)


@pytest.mark.parametrize("dense_product_limit", [4e9, 0.0])
def test_covariance_blocks_match_dense_inverse(dense_product_limit):
    prob, _ = synthetic_bal(n_cam=4, n_pts=40)
    model = Anchored(prob)
    res = levenberg_marquardt(model, (prob.cameras.copy(), prob.points.copy()))
    J, r, ev = dense_system(model, res.state)
    Q = np.linalg.inv(J.T @ J)
    inv = NormalInverse(res.linearization, chunk=97, dense_product_limit=dense_product_limit)
    st = model.structure
    nc = st.n_cam
    assert np.allclose(inv.Qcc, Q[:nc, :nc], rtol=1e-6, atol=1e-12)
    Qpp = inv.point_blocks()
    for p in [0, 5, 17, 39]:
        sl = slice(nc + 3 * p, nc + 3 * p + 3)
        assert np.allclose(Qpp[p], Q[sl, sl], rtol=1e-6, atol=1e-14)
    B = inv.cross_blocks()
    for o in [0, 7, 33, st.m - 1]:
        cols = st.group_params[st.obs_group[o]]
        p = st.obs_point[o]
        assert np.allclose(B[o], Q[np.ix_(cols, range(nc + 3 * p, nc + 3 * p + 3))], atol=1e-12)
    q = inv.observation_blocks()
    H = J @ Q @ J.T
    m = st.m
    diag_dense = np.diag(H)[: 2 * m].reshape(m, 2)
    assert np.allclose(np.einsum("mii->mi", q), diag_dense, rtol=1e-6, atol=1e-12)
    # solve() is Q times a vector
    rc = np.random.default_rng(1).standard_normal((nc, 2))
    rp = np.random.default_rng(2).standard_normal((st.n_pts, 3, 2))
    xc, xp = inv.solve(rc, rp)
    full = Q @ np.vstack([rc, rp.reshape(-1, 2)])
    assert np.allclose(np.vstack([xc, xp.reshape(-1, 2)]), full, rtol=1e-6, atol=1e-10)


def test_lm_recovers_truth_without_noise():
    prob, truth = synthetic_bal(noise=0.0)
    model = Anchored(prob)
    # anchor to the truth so the gauge is the true one
    model.c_ref = truth[0][0].copy()
    model.p_ref = truth[1][:2].copy()
    res = levenberg_marquardt(model, (prob.cameras.copy(), prob.points.copy()))
    assert res.cost < 1e-12
    assert np.abs(res.state[1] - truth[1]).max() < 1e-6
    assert res.initial_cost > 1e3


def test_bal_solver_reduces_cost_to_noise_level():
    prob, _ = synthetic_bal(noise=0.5, n_cam=6, n_pts=80, seed=3)
    out = solve_bal(prob, LMOptions(function_tolerance=1e-10))
    m = prob.n_observations
    # 0.5 * sum r^2 ~ 0.5 * sigma^2 * (2m - unknowns): within a generous chi-square band
    dof = 2 * m - (6 * 9 + 3 * prob.n_points - 7)
    expect = 0.5 * 0.25 * dof
    assert 0.6 * expect < out.final_cost < 1.4 * expect
    assert out.final_cost < 0.05 * out.initial_cost


def test_inv3_matches_numpy():
    A = np.random.default_rng(0).standard_normal((50, 3, 3)) + 3 * np.eye(3)
    assert np.allclose(inv3(A), np.linalg.inv(A))


def test_structure_rejects_bad_indices():
    from softplot.errors import SoftplotError

    with pytest.raises(SoftplotError):
        SchurStructure(3, 2, [[0, 1, 5]], [0], [0])
    with pytest.raises(SoftplotError):
        SchurStructure(3, 2, [[0, 1, 2]], [0], [4])


def test_evaluation_cost_includes_priors():
    ev = Evaluation(
        np.ones((2, 2)),
        cam_prior=(np.array([0]), np.array([2.0]), np.array([1.0])),
        pt_prior=(np.array([0]), np.ones((1, 3)), np.ones((1, 3, 3))),
    )
    assert ev.cost == pytest.approx(0.5 * (4 + 4 + 3))
