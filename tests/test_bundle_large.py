"""Blocks of thousands: the bordered band solver and covariance only for what is asked."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.adjust.sparse_bundle import BandSystem, BorderedBand, Linearization
from softplot.geometry.rotation import rotation_matrix
from softplot.orientation.bundle import BundleOptions, _Model, _State, bundle_adjust
from softplot.orientation.bundle_init import initialize
from softplot.synthetic.block import make_block


@pytest.fixture(scope="module")
def block():
    net = make_block(n_strips=5, photos_per_strip=30, seed=3)
    net.intr_given[0, :3] = [152.0, 0.0, 0.0]
    net.intr_given[0, 3] = 0.0
    d = net.to_bundle_data(free=("c", "x0", "y0", "k1"))
    initialize(d)
    return net, d


def test_band_plan_orders_a_block_into_a_narrow_band(block):
    _, d = block
    model = _Model(d, np.ones((len(d.point_names), 3), bool))
    st = model.structure
    assert not st.dense and st.band is not None
    plan = st.band
    assert plan["perm"].size - plan["n_inner"] == 4  # c, x0, y0, k1: the border
    assert np.array_equal(np.sort(plan["perm"]), np.arange(st.n_cam))
    # a narrow band: about 4 photos across 5 strips (the strip order would need 30 x 6)
    assert plan["u"] < st.n_cam / 5


def test_bordered_band_solves_and_inverts_like_dense(block):
    _, d = block
    model = _Model(d, np.ones((len(d.point_names), 3), bool))
    M = rotation_matrix(d.angles[:, 0], d.angles[:, 1], d.angles[:, 2])
    intr = np.array([c.values for c in d.cameras])
    lin = Linearization(model.structure, model.evaluate(_State(d.X0, M, intr, d.XYZ), True))
    S, b, _, _ = lin.reduced(1e-3, 1e-3)
    assert isinstance(S, BandSystem)
    A = S.toarray()
    assert np.allclose(A, A.T)
    bb = BorderedBand(S)
    x = bb.solve(b)
    assert np.linalg.norm(A @ x - b) < 1e-10 * np.linalg.norm(b)
    sc = 1 / np.sqrt(np.diag(A))  # the dense reference, Jacobi-scaled as well
    Ainv = np.linalg.inv(A * sc[:, None] * sc[None, :]) * sc[:, None] * sc[None, :]
    assert np.abs(x - Ainv @ b).max() < 1e-7 * np.abs(x).max()
    X = bb.solve(np.eye(A.shape[0])[:, :5])
    assert np.allclose(X, Ainv[:, :5], rtol=1e-6, atol=1e-9 * np.abs(Ainv[:, :5]).max())
    i = bb.border_index()
    assert np.allclose(bb.border_inverse(), Ainv[np.ix_(i, i)], rtol=1e-7)


def test_interior_covariance_equals_the_full_one_without_forming_it(block):
    _, d = block
    full = bundle_adjust(d, BundleOptions(covariance="full"))
    ph, pt = d.photo_names[40], d.point_names[77]
    sel = bundle_adjust(
        d,
        BundleOptions(covariance="interior", covariance_photos=(ph,), covariance_points=(pt,)),
    )
    np.testing.assert_allclose(sel.XYZ, full.XYZ, rtol=0, atol=1e-9)
    np.testing.assert_allclose(sel.intrinsics_std, full.intrinsics_std, rtol=1e-8)
    assert sel.intrinsics_corr[0]["names"] == full.intrinsics_corr[0]["names"]
    np.testing.assert_allclose(
        sel.intrinsics_corr[0]["matrix"], full.intrinsics_corr[0]["matrix"], atol=1e-4
    )
    f, p = d.photo_names.index(ph), d.point_names.index(pt)
    np.testing.assert_allclose(sel.eo_std[f], full.eo_std[f], rtol=1e-7)
    np.testing.assert_allclose(sel.XYZ_cov[p], full.XYZ_cov[p], rtol=1e-7, atol=1e-14)
    assert np.isnan(sel.eo_std[f + 1]).all() and np.isnan(sel.XYZ_cov[p + 1]).all()
    assert not sel._internals["inv"].has_full_qcc  # Qcc never formed
    assert any("covariance limited" in w for w in sel.warnings)
    # 'auto' keeps everything for a block of this size
    assert bundle_adjust(d).redundancy_numbers[0, 0] == pytest.approx(full.redundancy_numbers[0, 0])


def test_band_solver_without_border_matches_dense_on_bal():
    """BAL cameras share no unknowns (no border): the band path gives the dense result."""
    from softplot.adjust.bal import BALModel
    from softplot.adjust.sparse_bundle import LMOptions, levenberg_marquardt
    from test_bundle_engine import synthetic_bal

    prob, _ = synthetic_bal(n_cam=12, n_pts=150, seed=4)
    start = (prob.cameras.copy(), prob.points.copy())
    opt = LMOptions(function_tolerance=1e-12, max_iterations=50)
    dense = levenberg_marquardt(BALModel(prob), start, opt)
    m = BALModel(prob, dense_limit=10)
    m.structure.dense = False
    m.structure.band = m.structure._band_plan()
    assert m.structure.band is not None and m.structure.band["n_inner"] == 9 * 12
    band = levenberg_marquardt(m, start, opt)
    assert band.cost == pytest.approx(dense.cost, rel=1e-9)
    np.testing.assert_allclose(band.state[1], dense.state[1], atol=1e-7)
