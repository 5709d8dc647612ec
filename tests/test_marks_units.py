"""Unit tests of the detection building blocks: analytic model, LSM, grid fit, MicMac XML."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from softplot.camera import load_camera
from softplot.marks import grid
from softplot.marks.crb import centre_crb, cross_crb_simple
from softplot.marks.lsm import lsm
from softplot.marks.template import MarkShape, aperture, box_pixel_profile, box_profile


@pytest.mark.parametrize("kind", ["cross", "dot", "circle-dot"])
def test_model_derivatives_match_finite_differences(kind):
    shape = MarkShape(kind, length=30.0, width=2.0, radius=9.0, dot_radius=3.0)
    rng = np.random.default_rng(1)
    u = rng.uniform(-18, 18, 400).astype(np.float32)
    v = rng.uniform(-18, 18, 400).astype(np.float32)
    s = np.float32(1.1)
    ap = aperture(np.array([[0.98, 0.17], [-0.17, 0.98]]))
    T, Tu, Tv, Ts = shape.evaluate(u, v, s, aperture=ap)
    h = 1e-2
    for d, (du, dv, ds) in ((Tu, (h, 0, 0)), (Tv, (0, h, 0)), (Ts, (0, 0, h))):
        Tp = shape.evaluate(u + du, v + dv, s + ds, aperture=ap)[0].astype(float)
        Tm = shape.evaluate(u - du, v - dv, s - ds, aperture=ap)[0].astype(float)
        fd = (Tp - Tm) / (2 * h)
        assert np.abs(fd - d).max() < 2e-3


def test_box_profiles_are_blurred_boxes():
    t = np.linspace(-20, 20, 4001)
    B, _, _ = box_profile(t, 6.0, 1.0)
    assert abs(B.sum() * (t[1] - t[0]) - 6.0) < 1e-3  # area of the box is kept
    assert abs(float(B[2000]) - 0.9973) < 2e-4  # Phi(3) - Phi(-3)
    P, _, _ = box_pixel_profile(t, 6.0, 1.0, 1.0, 0.0)
    assert abs(P.sum() * (t[1] - t[0]) - 6.0) < 1e-3
    # the pixel box widens the edge: at the edge the value is still 1/2 by symmetry
    assert abs(float(P[np.argmin(np.abs(t - 3.0))]) - 0.5) < 2e-3


def _render_cross(n, L, w, blur, noise, seed, theta=0.0):
    """Crosses rendered from the analytic model itself (noise-free truth at random phases)."""
    rng = np.random.default_rng(seed)
    half = int(L / 2 + 4 * blur + 8)
    size = 2 * half + 1
    c = rng.uniform(-0.5, 0.5, (n, 2)) + half
    A = np.array([[np.cos(theta), np.sin(theta)], [-np.sin(theta), np.cos(theta)]])
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    shape = MarkShape("cross", length=L, width=w)
    ap = aperture(A)
    stack = np.empty((n, size, size), np.float32)
    for i in range(n):
        dx, dy = xx - c[i, 0], yy - c[i, 1]
        T = shape.evaluate(A[0, 0] * dx + A[0, 1] * dy, A[1, 0] * dx + A[1, 1] * dy,
                           np.float32(blur), aperture=ap)[0]
        stack[i] = 0.8 - 0.5 * T + rng.normal(0, noise, T.shape)
    return stack, c, A, shape


def test_lsm_reaches_the_cramer_rao_bound():
    stack, c, A, shape = _render_cross(150, 30.0, 2.2, 0.9, 0.02, 3, theta=0.1)
    rng = np.random.default_rng(4)
    c0 = c + rng.normal(0, 0.6, c.shape)
    res = lsm(stack, np.zeros((len(c), 2)), c0, A, shape, s0=1.0, init_err=1.5)
    err = res.centre - c
    rms = float(np.sqrt(np.mean(err**2)))
    bound = centre_crb(shape, 0.9, 0.5, 0.02, A=A)
    assert rms <= 1.2 * bound, (rms, bound)
    # the covariance is honest: predicted sigma within 25 % of the actual scatter
    assert 0.75 < float(np.mean(res.sigma)) / rms < 1.25
    assert np.all(res.converged)
    assert np.all(res.gain < 0)  # dark marks


def test_lsm_holds_the_blur_when_asked():
    """``fit_blur=False`` keeps the blur at ``s0`` (the refits and rescues of ``detect`` hold
    the set's median): held at the truth the centres are as good as with a free blur."""
    stack, c, A, shape = _render_cross(60, 30.0, 2.2, 0.9, 0.02, 8, theta=0.05)
    c0 = c + np.random.default_rng(9).normal(0, 0.3, c.shape)
    free = lsm(stack, np.zeros((len(c), 2)), c0, A, shape, s0=1.2, init_err=0.6)
    held = lsm(stack, np.zeros((len(c), 2)), c0, A, shape, s0=0.9, init_err=0.6,
               fit_blur=False)
    wrong = lsm(stack, np.zeros((len(c), 2)), c0, A, shape, s0=1.4, init_err=0.6,
                fit_blur=False)
    assert np.allclose(held.s, 0.9) and np.allclose(wrong.s, 1.4)
    assert np.abs(free.s - 0.9).max() > 1e-3  # free: estimated, not the start
    rms = {k: float(np.sqrt(np.mean((r.centre - c) ** 2)))
           for k, r in (("free", free), ("held", held))}
    bound = centre_crb(shape, 0.9, 0.5, 0.02, A=A)
    assert rms["held"] <= 1.2 * bound and rms["held"] <= 1.1 * rms["free"], (rms, bound)


def test_closed_form_bound_is_the_wide_line_limit():
    # wide lines, long arms: the numerical bound (all nuisance parameters) approaches the
    # closed form; thin lines carry less information than two separate edges
    wide = MarkShape("cross", length=200.0, width=12.0)
    num = centre_crb(wide, 1.0, 1.0, 0.01)
    simple = cross_crb_simple(1.0, 0.01, np.hypot(1.0, np.sqrt(1 / 12)), 100.0)
    assert 0.9 < num / simple < 1.25
    thin = MarkShape("cross", length=200.0, width=1.0)
    assert centre_crb(thin, 1.0, 1.0, 0.01) > 1.5 * simple


def test_tukey_weights_ignore_a_blob_over_one_arm():
    stack, c, A, shape = _render_cross(40, 40.0, 2.5, 1.0, 0.01, 5)
    clean = lsm(stack, np.zeros((40, 2)), c + 0.3, A, shape, s0=1.0, init_err=1.0)
    dirty = stack.copy()
    yy, xx = np.mgrid[0 : stack.shape[1], 0 : stack.shape[2]]
    for i in range(40):
        # an opaque blob on the right arm, away from the centre
        m = (xx - (c[i, 0] + 12)) ** 2 + (yy - (c[i, 1] + 2)) ** 2 < 5.0**2
        dirty[i][m] = 0.1
    res = lsm(dirty, np.zeros((40, 2)), c + 0.3, A, shape, s0=1.0, init_err=1.0)
    err_d = np.sqrt(np.mean((res.centre - c) ** 2))
    err_c = np.sqrt(np.mean((clean.centre - c) ** 2))
    assert err_d < 1.5 * err_c + 0.003, (err_d, err_c)
    # without robust weights the blob pulls the centre
    plain = lsm(dirty, np.zeros((40, 2)), c + 0.3, A, shape, s0=1.0, init_err=1.0,
                robust=False)
    assert np.sqrt(np.mean((plain.centre - c) ** 2)) > 3 * err_d


def test_grid_fit_assigns_rows_and_cols_among_false_peaks():
    cam = load_camera("rollei-6006")
    film = cam.reseau.film()
    ppm = 1200 / 25.4
    th = np.radians(8.0)
    R = ppm * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]) @ np.diag([1, -1])
    rng = np.random.default_rng(2)
    pix = film @ R.T + [1400.0, 1350.0] + rng.normal(0, 0.5, film.shape)
    keep = rng.random(len(pix)) > 0.1  # 10 % of the crosses not found
    false = rng.uniform(0, 2800, (60, 2))  # scene peaks
    xy = np.vstack([pix[keep], false])
    score = np.concatenate([rng.uniform(0.5, 0.9, keep.sum()), rng.uniform(0.3, 0.7, 60)])
    g = grid.fit_grid(xy, score, cam.reseau, (2800, 2800), px_per_mm=ppm * 1.01)
    assert g is not None
    true_node = np.where(keep)[0]
    got = dict(zip(g.index.tolist(), g.node.tolist(), strict=True))
    for k, node in enumerate(true_node):
        if k in got:
            assert got[k] == node
    assert sum(i >= keep.sum() for i in got) <= 2  # false peaks almost never on the lattice
    assert abs(g.rotation_deg - 8.0) < 0.1
    assert len(got) >= 0.95 * keep.sum()


def test_projective_fit_recovers_a_homography():
    rng = np.random.default_rng(0)
    H = np.array([[47.0, 3.0, 1300.0], [-2.0, -46.0, 1400.0], [1e-4, -2e-4, 1.0]])
    src = rng.uniform(-25, 25, (30, 2))
    dst = grid.apply_h(H, src)
    Hf = grid.projective_fit(src, dst)
    assert np.abs(grid.apply_h(Hf, src) - dst).max() < 1e-8
    J = grid.h_jacobian(H, src[:1])[0]
    e = 1e-6
    p = src[:1]
    fx = grid.apply_h(H, p + [e, 0]) - grid.apply_h(H, p - [e, 0])
    fy = grid.apply_h(H, p + [0, e]) - grid.apply_h(H, p - [0, e])
    fd = np.column_stack([fx[0], fy[0]])
    assert np.allclose(J, fd / (2 * e), atol=1e-5)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_affine_from_neighbour_positions_follows_a_strong_deformation(seed):
    """The pixel -> mark-frame affine predicted for each cross from its neighbours' positions
    (local cubic, the cross left out) matches the exact mapping's Jacobian under a 100 um
    film deformation, rotation and anisotropy: to 1e-4 inside the grid (a plane through the
    neighbours' exact affines misses it by several times more), with a larger variance factor
    at the outline."""
    from softplot.marks.neighbours import local_fit as _local_fit
    from softplot.marks.neighbours import position_affine as _position_affine
    from softplot.synthetic.mapping import Deformation, Scanner, TruthMapping

    rng = np.random.default_rng(seed)
    dpi = 1200.0
    ppm = dpi / 25.4
    mp = TruthMapping(Deformation.random((56.0, 56.0), 100.0, 500.0, rng),
                      Scanner(dpi, 3.0, 2000.0, 1500.0, 1500.0))
    g = np.arange(-25.0, 25.1, 5.0)
    film = np.array([(x, y) for y in g[::-1] for x in g])
    xy = mp.film_to_pixel(film)
    ok = np.ones(len(film), bool)
    truth = np.linalg.inv(mp.jacobian(film) @ np.diag([1.0 / ppm, -1.0 / ppm]))
    A, lev = _position_affine(film, xy, ok, ppm)
    err = np.abs(A - truth).reshape(-1, 4).max(1)
    inner = np.abs(film).max(1) < 20.0
    assert err[inner].max() < 1e-4, err[inner].max()
    assert np.median(err) < 1e-4
    # a local plane through the exact affines of the neighbours is worse
    plane = _local_fit(film, film, truth.reshape(-1, 4), 12, degree=1).reshape(-1, 2, 2)
    assert np.median(np.abs(plane - truth).reshape(-1, 4).max(1)) > 4.0 * np.median(err)
    corner = np.abs(film).min(1) > 20.0
    assert lev[corner].min() > 2.0 * np.median(lev[inner])
    # an unaccepted cross is predicted from the others; too few accepted: NaN
    ok[60] = False
    A2, _ = _position_affine(film, xy, ok, ppm)
    assert np.abs(A2[60] - truth[60]).max() < 1e-4
    assert np.isnan(_position_affine(film, xy, np.arange(len(film)) < 3, ppm)[0]).all()
    # a partial grid (the top three rows of a cropped scan) cannot carry a cubic in y: each
    # cross falls back to the degree its neighbours determine; a single row gives no affine
    rows3 = np.arange(len(film)) < 33
    A3, _ = _position_affine(film, xy, rows3, ppm)
    assert np.abs(A3[rows3] - truth[rows3]).max() < 5e-3
    assert np.isnan(_position_affine(film, xy, np.arange(len(film)) < 11, ppm)[0]).all()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_compiled_cross_model_matches_numpy(seed):
    """The compiled LSM kernel (softplot.marks.kernels) gives the NumPy model, template,
    derivatives and Jacobian to float32 rounding, for turned, sheared, scaled and strongly
    blurred crosses with scene, tilt and saturated-background terms; so LSM's estimates do
    not depend on which path ran."""
    from softplot.marks import kernels
    from softplot.marks.lsm import _assemble, _geom

    if not kernels.AVAILABLE:
        pytest.skip("numba not installed")
    rng = np.random.default_rng(seed)
    shape = MarkShape("cross", length=rng.uniform(8, 60), width=rng.uniform(0.8, 6.0))
    n, P = 7, 900
    ext = 0.6 * shape.length + 4
    X = rng.uniform(-ext, ext, (n, P)).astype(np.float32)
    Y = rng.uniform(-ext, ext, (n, P)).astype(np.float32)
    S = rng.uniform(0.2, 0.8, (n, P)).astype(np.float32)
    Q = (rng.random((n, P)) < 0.2).astype(np.float32)
    valid = np.ones((n, P), bool)
    z = np.zeros((n, P), np.float32)
    data = (X, Y, z, valid, S, z + 1, Q, z)
    p = np.zeros((n, 12))
    p[:, 0:2] = rng.uniform(-1.5, 1.5, (n, 2))
    th = rng.uniform(-0.2, 0.2, n)
    k = rng.uniform(0.9, 1.1, (n, 2))
    sh = rng.uniform(-0.03, 0.03, n)
    p[:, 2] = k[:, 0] * np.cos(th)
    p[:, 3] = -k[:, 0] * np.sin(th) + sh
    p[:, 4] = k[:, 1] * np.sin(th)
    p[:, 5] = k[:, 1] * np.cos(th)
    p[:, 6] = rng.uniform(0.3, 3.0, n)
    p[:, 7:12] = rng.uniform(-0.3, 0.3, (n, 5))
    geo = _geom(p, data, shape)
    M, T, u, v, J = _assemble(p, data, geo)
    Mk, Tk, Tuk, Tvk, uk, vk, Jk = kernels.cross_model(p, data, shape)
    for a, b in ((M, Mk), (T, Tk), (geo[1], Tuk), (geo[2], Tvk)):  # float32 rounding
        assert np.abs(a - b).max() < 1e-5 * max(1.0, float(np.abs(a).max()))
    assert np.abs(u - uk).max() < 1e-4 and np.abs(v - vk).max() < 1e-4
    scale = np.abs(J).max(axis=(0, 1)) + 1e-6
    assert (np.abs(J - Jk).max(axis=(0, 1)) / scale).max() < 1e-4
    # the test sees a difference: a shifted centre changes the kernel's model
    p2 = p.copy()
    p2[:, 0] += 0.01
    assert np.abs(kernels.cross_model(p2, data, shape)[0] - Mk).max() > 1e-4


def test_measure_retry_holds_the_accepted_marks_median_blur():
    """The retry of a mark that failed the first pass (here: started 8.5 px off, where the
    first pass trusts its start to 0.6 px) holds the blur at the median of the marks the
    first pass accepted; ``blur=`` holds it everywhere."""
    from softplot.io import Scan
    from softplot.marks.measure import measure
    from softplot.marks.template import cross_shape
    from softplot.synthetic import ScanSpec, TruthMapping, render_scan

    img, truth = render_scan("rollei-6006", ScanSpec(dpi=1000, scene="none", noise_sigma=0.01,
                                                     blur_sigma_px=1.0), 21)
    sc = Scan.from_array(img, dpi=truth["dpi"])
    ppm = truth["dpi"] / 25.4
    shape = cross_shape(load_camera("rollei-6006"), ppm)
    rs = [m for m in truth["marks"] if m["kind"] == "reseau"][30:40]
    xy = np.array([[m["x"], m["y"]] for m in rs])
    film = np.array([[m["film_x"], m["film_y"]] for m in rs])
    A = np.linalg.inv(TruthMapping.from_truth(truth).jacobian(film)
                      @ np.diag([1.0 / ppm, -1.0 / ppm]))
    sign = -1 if truth["polarity"] == "positive" else 1
    c0 = xy.copy()
    c0[0] += (6.0, 6.0)  # between the arms
    f = measure(sc, shape, c0, A, 1.05, 1.0, sign, anchor=xy, max_shift=1.0)
    assert f.ok.all(), f.reason
    assert np.hypot(*(f.xy[0] - xy[0])) < 0.05
    assert f.s[0] == pytest.approx(np.median(f.s[1:]), abs=1e-9)
    assert np.ptp(f.s[1:]) > 1e-4  # the first pass estimates each mark's blur
    g = measure(sc, shape, xy, A, 1.3, 0.5, sign, blur=1.3)
    assert np.allclose(g.s, 1.3)


def _outlier_case(seed, sigma, extra=0.0):
    """Rollei reseau at 600 dpi: truth through a homography and a smooth bend, measured with
    per-cross noise ``sigma`` (121,) px plus ``extra`` px of noise no sigma reports (a
    deformation the local polynomial does not follow). Returns film, xy, H, sigma."""
    rng = np.random.default_rng(seed)
    film = load_camera("rollei-6006").reseau.film()
    ppm = 600 / 25.4
    H = np.array([[ppm, 0.02, 700.0], [0.01, -ppm, 680.0], [1e-6, 2e-6, 1.0]])
    xy = grid.apply_h(H, film)
    xy += 0.4 * np.stack([np.sin(film[:, 0] / 15.0), np.cos(film[:, 1] / 20.0)], 1)
    xy += rng.normal(size=xy.shape) * np.hypot(sigma, extra)[:, None]
    return film, xy, H, sigma


def test_departure_model_recovers_the_two_variance_terms():
    from softplot.marks.validation import departure_model as _departure_model
    from softplot.marks.validation import expected_departure as _expected_departure

    rng = np.random.default_rng(4)
    n = 4000
    sg = rng.uniform(0.02, 0.2, n)
    edge = rng.random(n) < 0.3
    a, b = np.where(edge, 3.0, 2.0), np.where(edge, 0.02, 0.005)
    dev = np.sqrt(a * sg**2 + b) / np.sqrt(2.0) * np.hypot(*rng.normal(size=(2, n)))
    dev[:40] += 2.0  # outliers are left out of the fit
    coef = _departure_model(dev, sg, edge)
    assert np.allclose(coef[:, 0], [3.0, 2.0], rtol=0.15), coef
    assert np.allclose(coef[:, 1], [0.02, 0.005], rtol=0.15), coef
    assert np.allclose(_expected_departure(coef, sg[:3], edge[:3]), np.sqrt(a * sg**2 + b)[:3],
                       rtol=0.1)


def test_outlier_test_holds_a_precise_cross_to_its_own_sigma(monkeypatch):
    """Over a busy scene most crosses are imprecise and the departures' spread is large; a
    precise cross pulled by 0.4 px (13 of its own sigmas) hides inside 3 spreads (0.5 px).
    The departure model (its own sigma and the prediction's error, which the neighbours'
    noise sets here: about 0.09 px) finds it; without it (OUTLIER_K huge) it is kept."""
    D = importlib.import_module("softplot.marks.validation")

    sigma = np.full(121, 0.12)
    precise = np.arange(13, 121, 5)
    sigma[precise] = 0.03
    film, xy, H, sigma = _outlier_case(2, sigma)
    bad = 58  # an inner cross (row 5, col 3), precise
    assert bad in precise
    xy[bad] += (0.4, 0.0)

    def run():
        st, rs = ["measured"] * 121, [""] * 121
        floor = np.full(121, 0.05)
        D.reject_outliers(film, xy.copy(), st, rs, H, sigma, floor_px=floor)
        return {i for i, s in enumerate(st) if s == "rejected"}

    assert run() == {bad}
    monkeypatch.setattr(D, "OUTLIER_K", 1e6)
    assert bad not in run()


def test_outlier_test_keeps_crosses_whose_departures_their_sigma_does_not_explain():
    """Sharp crosses (sigma 0.001 px) under a deformation the local cubic does not follow
    (0.03 px): the departures are 30-100 sigmas, and none is an outlier (the shared term of the
    model carries them)."""
    D = importlib.import_module("softplot.marks.validation")

    film, xy, H, sigma = _outlier_case(3, np.full(121, 0.001), extra=0.03)
    st, rs = ["measured"] * 121, [""] * 121
    _, _, _, coef = D.reject_outliers(film, xy, st, rs, H, sigma, floor_px=np.full(121, 0.02))
    assert st.count("rejected") == 0
    assert np.all(np.sqrt(coef[:, 1]) > 0.03), coef  # the shared term, not the sigma
