"""The fast paths of mark detection over busy scenes give what the slower ones gave.

* the compiled joint-scene solve (:mod:`softplot.marks.scene_tv`) at every blur radius (its
  7- and 9-tap paths for radii up to 3 and 4 px, the general loop beyond) agrees with the
  NumPy path;
* the compiled parts of LSM (pixel gather, step, residual correlation, the joint scene's
  template) agree with the NumPy paths;
* ``scene="auto"`` on busy scenes, which refits with the joint scene only the crosses with a
  scene edge in their footprint, is as accurate as the joint estimate on every cross
  (``scene="joint"``, what ``auto`` did before) while solving the scene under far fewer
  patches. (The whole accuracy sweep's busy renders, compared the same way, are in
  docs/benchmarks.md, "Busy scenes".)
"""

from __future__ import annotations

import numpy as np
import pytest

from softplot.marks import kernels, scene_tv


def _patches(n=3, h=47, w=43, seed=5):
    rng = np.random.default_rng(seed)
    T = np.zeros((n, h, w), np.float32)
    T[:, 22:25, 4:39] = 1.0
    T[:, 4:43, 20:23] = 1.0
    g = rng.random((n, h, w)).astype(np.float32)
    B0 = rng.random((n, h, w)).astype(np.float32)
    return g, T, B0, rng.random(n).astype(np.float32), np.full(n, 0.05, np.float32)


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
@pytest.mark.parametrize("s_e", [0.2, 0.45, 0.7, 1.0, 1.3, 2.1])
def test_scene_solve_blur_matches_numpy_at_every_radius(s_e):
    """Radii 1..7 px (``gauss_taps``: ceil(3 s_e)): the compiled solve, whole patch and band,
    equals the NumPy path to float32 rounding, and the blurred scene it returns is the NumPy
    blur of its scene."""
    g, T, B0, level, mu = _patches()
    for band in (np.inf, 4.0):
        a = scene_tv.deconv_tv(g, T, level, B0, mu, s_e, 15, compiled=True, band_px=band)
        b = scene_tv.deconv_tv(g, T, level, B0, mu, s_e, 15, compiled=False, band_px=band)
        for x, y in zip(a, b, strict=True):
            assert np.abs(x - y).max() < 2e-5
        B, X = a
        assert np.abs(B - scene_tv._blur_np(X, scene_tv.gauss_taps(s_e))).max() < 2e-6



@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
def test_scene_solve_matches_numpy_at_every_width():
    """The compiled solve pads each row to a multiple of 8 columns: at every width modulo 8
    (and the blur radii of 7 and 9 taps) the patch's own columns are those of the NumPy
    path to float32 rounding, the scene's last column included."""
    for w in range(24, 33):
        g, T, B0, level, mu = _patches(n=2, h=21, w=w, seed=w)
        T[:, :, w // 2 - 1 : w // 2 + 2] = 1.0
        for s_e in (0.8, 1.2):
            a = scene_tv.deconv_tv(g, T, level, B0, mu, s_e, 20, compiled=True)
            b = scene_tv.deconv_tv(g, T, level, B0, mu, s_e, 20, compiled=False)
            for x, y in zip(a, b, strict=True):
                assert x.shape == (2, 21, w)
                assert np.abs(x - y).max() < 2e-5, (w, s_e)
                assert np.abs(x[..., -1] - y[..., -1]).max() < 2e-5, (w, s_e)

def _errors(det, truth):
    tm = {m["name"]: m for m in truth["marks"]}
    return {nm: det.xy[i] - (tm[nm]["x"], tm[nm]["y"]) for i, nm in enumerate(det.name)
            if det.status[i] == "measured" and tm[nm]["visible"]}


def _rms(errs):
    e = np.concatenate([np.array(list(d.values())) for d in errs])
    return float(np.sqrt(np.mean(e**2)))


def test_busy_scene_auto_is_as_accurate_as_the_joint_estimate_on_every_cross(monkeypatch):
    """Busy scenes: ``scene="auto"`` refits with the joint scene only the crosses with a scene
    edge in their footprint (``scene_tv.EDGE_MIN``), ``scene="joint"`` every cross (the
    estimate of before). Pooled over three renders the fast path's RMS error against the
    truth is within 3 % of the joint estimate's, the same crosses are measured (at most one
    more or fewer per render), no cross differs by more than 0.05 px, and the fast path solves
    the scene under at most 70 % of the patches; the opening alone is clearly worse (so the
    renders do test the scene model). The scene model judged alone: the neighbours' prior for
    flat fits (:mod:`softplot.marks.neighbour_prior`), which comes after it, is off (it brings
    the opening's crosses to the joint estimate's error here)."""
    from softplot.io import Scan
    from softplot.marks import detect, neighbour_prior
    from softplot.synthetic import ScanSpec, render_scan

    solved = {"n": 0}
    real = scene_tv.deconv_tv

    def spy(g, *a, **k):
        solved["n"] += len(g)
        return real(g, *a, **k)

    monkeypatch.setattr(scene_tv, "deconv_tv", spy)
    monkeypatch.setattr(neighbour_prior, "PRIOR_FLAT", np.inf)
    monkeypatch.setattr(neighbour_prior, "PRIOR_ANY_RATIO", np.inf)
    errs = {"joint": [], "auto": [], "opening": []}
    patches = {"joint": 0, "auto": 0}
    for seed in (11, 12, 13):
        img, truth = render_scan("rollei-6006", ScanSpec(dpi=1000, rotation_deg=1.5,
                                                         scene="busy"), seed)
        sc = Scan.from_array(img, dpi=1000)
        for mode in errs:
            solved["n"] = 0
            det = detect(sc, "rollei-6006", scene=mode)
            if mode in patches:
                patches[mode] += solved["n"]
                assert det.scene == "joint"
            errs[mode].append(_errors(det, truth))
        j, a = errs["joint"][-1], errs["auto"][-1]
        assert len(set(j) ^ set(a)) <= 1
        both = sorted(set(j) & set(a))
        assert max(np.hypot(*(j[k] - a[k])) for k in both) < 0.05
    r = {k: _rms(v) for k, v in errs.items()}
    assert r["auto"] <= 1.03 * r["joint"], r
    assert r["opening"] > 1.15 * r["joint"], r
    assert patches["auto"] <= 0.7 * patches["joint"], patches


def _cross_stack(seed, n=6, half=30):
    """N noisy patches of turned, blurred crosses over a tilted scene with an edge, clipped
    at 1 (some censored pixels): ``(stack, origin, centre, A, shape, blur)``."""
    from softplot.marks.measure import _template
    from softplot.marks.template import MarkShape

    rng = np.random.default_rng(seed)
    shape = MarkShape("cross", length=rng.uniform(25, 45), width=rng.uniform(1.5, 4.0))
    size = 2 * half + 1
    origin = rng.integers(0, 4000, (n, 2)).astype(float)
    c = origin + half + rng.uniform(-0.5, 0.5, (n, 2))
    th = rng.uniform(-0.1, 0.1, n)
    A = np.stack([np.array([[np.cos(t), np.sin(t)], [-np.sin(t), np.cos(t)]]) for t in th])
    A *= rng.uniform(0.97, 1.03, (n, 1, 1))
    s = rng.uniform(0.6, 1.6, n)
    T = _template(shape, origin, c, A, s, (size, size))
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    edge = xx[None] > rng.integers(10, 50, (n, 1, 1))
    scene = 0.62 + 0.003 * xx[None] - 0.002 * yy[None] + 0.4 * edge
    g = scene * (1 - T) + 0.08 * T + rng.normal(0, 0.02, (n, size, size))
    return np.clip(g, 0.0, 1.0).astype(np.float32), origin, c, A, shape, s


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_compiled_lsm_step_gather_and_correlation_match_numpy(seed, monkeypatch):
    """The compiled parts of LSM (the pixel gather, the weights, normal equations, inversion
    and update of each step, the residual correlation's sums, the joint scene's template)
    give what the NumPy paths give: the same gathered arrays, the same fits to 1e-4 px and
    covariances to 1e-3 (float32 sums in another order), the same correlation sums."""
    from softplot.marks import lsm as L
    from softplot.marks.measure import _template, scene_background

    stack, origin, c, A, shape, s = _cross_stack(seed)
    c0 = c + np.random.default_rng(seed).uniform(-0.4, 0.4, c.shape)
    bg, wt, _ = scene_background(stack, shape, 1.0, -1)
    kw = dict(shape=shape, s0=1.0, init_err=0.5, background=bg, weight=wt, clip=(0.0, 1.0))
    ref = np.round(c0)
    gathered = L._gather(stack, origin, ref, c0, A, shape, 3.0, bg, wt, None, (0.0, 1.0))
    fit = L.lsm(stack, origin, c0, A, **kw)
    Tk = _template(shape, origin, c, A, s, stack.shape[1:])
    # one step's state: the half-arms' shifts (the arm test) from it
    p = np.zeros((len(c0), 12))
    p[:, 0:2] = c0 - ref + 0.1
    p[:, 2:6] = A.reshape(-1, 4)
    p[:, 6] = 1.0
    state = L._step(p.copy(), gathered, shape, np.ones(12, bool), robust=True, init=True)[2]
    halves = L._half_arm_shifts(p, gathered, shape, state)
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    halves0 = L._half_arm_shifts(p, gathered, shape, state)
    for a, b in zip(halves, halves0, strict=True):
        assert np.allclose(a, b, rtol=1e-5, atol=1e-12) and np.isfinite(b).all()
    gathered0 = L._gather(stack, origin, ref, c0, A, shape, 3.0, bg, wt, None, (0.0, 1.0))
    fit0 = L.lsm(stack, origin, c0, A, **kw)
    T0 = _template(shape, origin, c, A, s, stack.shape[1:])
    for a, b in zip(gathered, gathered0, strict=True):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    assert (gathered0[7] > 0).any()  # censored pixels were there
    assert np.abs(fit.centre - fit0.centre).max() < 1e-4
    assert np.abs(fit.s - fit0.s).max() < 1e-3
    assert np.abs(fit.cov - fit0.cov).max() < 1e-3 * np.abs(fit0.cov).max()
    assert np.abs(fit.cov_white - fit0.cov_white).max() < 1e-3 * np.abs(fit0.cov_white).max()
    # the correlated covariance differs from the independent pixels' (the test can fail)
    assert not np.allclose(fit0.cov, fit0.cov_white, rtol=1e-2)
    assert np.abs(Tk - T0).max() < 2e-5 and T0.max() > 0.9


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
def test_compiled_correlation_sums_match_the_ffts(monkeypatch):
    """The residual correlation summed directly over the pixel pairs (compiled) gives the
    FFTs' covariance, at the least and the largest lag reach."""
    from softplot.marks import lsm as L

    rng = np.random.default_rng(4)
    # the pixels of a cross's footprint in a 40 x 30 box, in random order, a few invalid
    yy, xx = np.mgrid[0:30, 0:40]
    foot = (np.abs(xx - 20) <= 3) | (np.abs(yy - 15) <= 3)
    n, P = 5, int(foot.sum())
    X = np.stack([rng.permutation(xx[foot]) for _ in range(n)]).astype(np.float32)
    Y = np.zeros_like(X)
    for i in range(n):
        k = rng.permutation(P)
        X[i], Y[i] = xx[foot][k], yy[foot][k]
    valid = rng.random((n, P)) > 0.05
    r = rng.normal(0, 1, (n, P)).astype(np.float32)
    w = rng.uniform(0.2, 1, (n, P)).astype(np.float32)
    h = rng.normal(0, 1e-3, (n, 2, P)).astype(np.float32)
    s0sq = rng.uniform(0.5, 2, n)
    # and pixels anywhere in the box (a valid pixel at the corner of the valid ones, where
    # the FFTs' grid also put the invalid pixels)
    Xb, Yb = X.copy(), Y.copy()
    for i in range(n):
        k = rng.permutation(40 * 30)[:P]
        Xb[i], Yb[i] = k % 40, k // 40
        Xb[i, 0], Yb[i, 0] = Xb[i].min(), Yb[i].min()
        Xb[i, 1:][(Xb[i, 1:] == Xb[i, 0]) & (Yb[i, 1:] == Yb[i, 0])] = 39.0
    valid_b = valid.copy()
    valid_b[:, 0] = True
    for Xq, Yq, vq in ((X, Y, valid), (Xb, Yb, valid_b)):
        for blur in (0.3, 4.0):
            a = L._correlated_cov(h, r, w, vq, Xq, Yq, s0sq, np.full(n, blur))
            monkeypatch.setattr(kernels, "AVAILABLE", False)
            b = L._correlated_cov(h, r, w, vq, Xq, Yq, s0sq, np.full(n, blur))
            monkeypatch.setattr(kernels, "AVAILABLE", True)
            assert np.abs(a - b).max() < 1e-5 * np.abs(b).max()


def test_measure_with_a_half_arm_per_mark_is_the_separate_calls():
    """``measure`` with a dropped half-arm per mark (the rescue's four fits of each cross in
    one call) gives what one call per half-arm gives: the same acceptance, positions to
    2e-6 px, with the joint scene and the blur held (the sets batched into common fits)."""
    from softplot.io import Scan
    from softplot.marks.measure import _template, measure
    from softplot.marks.template import MarkShape

    rng = np.random.default_rng(11)
    shape = MarkShape("cross", length=40.0, width=3.0)
    size = 360
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
    img = 0.55 + 0.3 * (xx > 170) - 0.2 * ((yy - 120) ** 2 + (xx - 250) ** 2 < 40**2)
    centres = np.array([[60.3, 60.7], [180.2, 61.1], [300.6, 59.8], [61.1, 180.4],
                        [179.7, 179.5], [299.4, 181.2], [60.2, 300.9], [181.3, 299.6]])
    A = np.broadcast_to(np.eye(2), (len(centres), 2, 2))
    T = _template(shape, np.zeros((len(centres), 2)), centres, A, np.full(len(centres), 0.9),
                  (size, size)).max(0)
    img = img * (1 - T) + 0.1 * T + rng.normal(0, 0.015, (size, size))
    sc = Scan.from_array(np.clip(img, 0, 1).astype(np.float32))
    m = len(centres)
    kw = dict(s0=0.9, init_err=0.6, sign=-1, scene_tv=2, blur=0.9, fit_shape=False)
    start = centres + rng.uniform(-0.3, 0.3, centres.shape)
    together = measure(sc, shape, np.tile(start, (4, 1)), np.tile(A, (4, 1, 1)),
                       drop_part=np.repeat(np.arange(4), m), **kw)
    for k in range(4):
        alone = measure(sc, shape, start, A, drop_part=k, **kw)
        part = together.rows(slice(k * m, (k + 1) * m))
        assert np.array_equal(part.ok, alone.ok) and part.reason == alone.reason
        assert part.ok.sum() >= m - 1
        ok = alone.ok
        assert np.abs(part.xy[ok] - alone.xy[ok]).max() < 2e-6
        assert np.abs(part.cov[ok] - alone.cov[ok]).max() < 1e-4 * np.abs(alone.cov[ok]).max()


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
@pytest.mark.parametrize("seed", [4, 5])
def test_compiled_fine_stage_is_the_step_by_step_loop(seed, monkeypatch):
    """LSM's fine stage in one compiled loop, mark by mark
    (:func:`softplot.marks.kernels.fine_steps`), takes the steps the loop of compiled steps
    takes over all marks at once: the same centres to 1e-5 px, blur and covariances to
    float32 rounding, the same iterations and convergence, with and without the capture
    stage and the first step's radiometry; and both find the true centres."""
    from softplot.marks import lsm as L
    from softplot.marks.measure import scene_background

    stack, origin, c, A, shape, s = _cross_stack(seed, n=8)
    rng = np.random.default_rng(seed)
    bg, wt, _ = scene_background(stack, shape, 1.0, -1)
    for init_err, spread in ((0.5, 0.4), (1.5, 1.2)):  # no capture stage, then one
        c0 = c + rng.uniform(-spread, spread, c.shape)
        kw = dict(shape=shape, s0=1.0, init_err=init_err, background=bg, weight=wt,
                  clip=(0.0, 1.0))
        calls = []

        def spy(*a, calls=calls, real=kernels.fine_steps, **k):
            calls.append(1)
            return real(*a, **k)

        monkeypatch.setattr(kernels, "fine_steps", spy)
        fit = L.lsm(stack, origin, c0, A, **kw)
        assert calls  # the compiled loop ran

        def loop(p, data, shape, full, robust, init, max_iter, tol, converged):
            return L._steps(p, data, shape, full, robust, 1, max_iter, tol,
                            np.arange(len(p)), None, converged, init)

        monkeypatch.setattr(L, "_fine_stage", loop)
        ref = L.lsm(stack, origin, c0, A, **kw)
        monkeypatch.undo()
        assert np.abs(fit.centre - ref.centre).max() < 1e-5
        assert np.abs(fit.s - ref.s).max() < 1e-4
        assert np.abs(fit.cov - ref.cov).max() < 1e-3 * np.abs(ref.cov).max()
        assert fit.iterations == ref.iterations
        assert np.array_equal(fit.converged, ref.converged)
        # against the true centres (a scene edge beside some crosses: biases of 0.15 px)
        assert np.abs(fit.centre - c).max() < 0.3


def test_joint_scene_refit_reuses_the_first_pass_opening(monkeypatch):
    """``scene="auto"`` on a busy scene: the refit with the joint scene starts from the
    opening's estimate the first pass computed (``measure.REUSE_OPENING``) instead of
    computing it again. The same crosses are measured at the same places (to the float
    rounding of arrays placed elsewhere in memory, 1e-6 px) with the same covariances, the
    fast path computes the opening under fewer patches, and both are accurate against the
    truth."""
    from softplot.io import Scan
    from softplot.marks import detect
    from softplot.marks import measure as M
    from softplot.synthetic import ScanSpec, render_scan

    img, truth = render_scan("rollei-6006", ScanSpec(dpi=900, rotation_deg=1.5, scene="busy"),
                             11)
    sc = Scan.from_array(img, dpi=900)
    opened = {"n": 0}
    real = M.scene_background

    def spy(stack, *a, **k):
        opened["n"] += len(stack)
        return real(stack, *a, **k)

    monkeypatch.setattr(M, "scene_background", spy)
    out, n = {}, {}
    for reuse in (False, True):
        monkeypatch.setattr(M, "REUSE_OPENING", reuse)
        opened["n"] = 0
        out[reuse] = detect(sc, "rollei-6006")
        n[reuse] = opened["n"]
    a, b = out[True], out[False]
    assert a.scene == b.scene == "joint"
    assert list(a.status) == list(b.status)
    ok = np.array([s == "measured" for s in a.status])
    assert ok.sum() >= 110
    assert np.abs(a.xy[ok] - b.xy[ok]).max() < 1e-6
    assert np.abs(a.cov[ok] - b.cov[ok]).max() < 1e-6 * np.abs(b.cov[ok]).max()
    assert n[True] <= n[False] - 40, n
    assert _rms([_errors(a, truth)]) < 0.1


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
def test_first_step_contrast_scaling_compiled_is_numpys(monkeypatch):
    """The first LSM step's Jacobian scaled by the contrast over the scene, compiled
    (:func:`softplot.marks.kernels.scale_columns`), is NumPy's strided product bit for bit
    (float32; NaN, infinities, zeros and tiny values included), and LSM with it fits the
    crosses exactly as with NumPy's product (every figure equal), within 0.3 px of the true
    centres (a scene edge beside some of them)."""
    from softplot.marks import lsm as L
    from softplot.marks.measure import scene_background

    rng = np.random.default_rng(4)
    J = rng.normal(0, 3, (5, 301, 12)).astype(np.float32)
    J[0, :3, 0] = [np.nan, np.inf, 1e-39]
    b = rng.normal(0, 1, (5, 301)).astype(np.float32)
    b[1, :4] = [0.0, -0.0, np.inf, 1e-30]
    want = J.copy()
    want[..., :7] *= b[..., None]
    got = J.copy()
    kernels.scale_columns(got, b, 7)
    assert np.array_equal(got, want, equal_nan=True)

    stack, origin, c, A, shape, s = _cross_stack(3, n=8)
    bg, wt, _ = scene_background(stack, shape, 1.0, -1)
    kw = dict(shape=shape, s0=1.0, init_err=0.5, background=bg, weight=wt, clip=(0.0, 1.0))
    c0 = c + rng.uniform(-0.4, 0.4, c.shape)
    fit = L.lsm(stack, origin, c0, A, **kw)

    def numpy_scale(J, b, ncol):
        J[..., :ncol] *= b[..., None]

    monkeypatch.setattr(kernels, "scale_columns", numpy_scale)
    ref = L.lsm(stack, origin, c0, A, **kw)
    for k in ("centre", "A", "s", "gain", "cov", "cov_white", "noise", "score", "support"):
        assert np.array_equal(getattr(fit, k), getattr(ref, k), equal_nan=True), k
    assert np.abs(fit.centre - c).max() < 0.3


@pytest.mark.parametrize("jit", [True, False])
def test_step_loop_keeps_the_first_steps_state_as_its_own(jit, monkeypatch):
    """The step loop of LSM's fine stage keeps the first step's state of every mark as that
    step's own arrays (no copy into arrays of its own): the same parameters, states and
    convergence, bit for bit, as the loop writing every step into a state of its own, over
    up to ten steps (compiled and NumPy steps); and no state array is one of the data's.
    The fitted centres lie within 0.3 px of the truth."""
    from softplot.marks import lsm as L
    from softplot.marks.measure import scene_background

    if jit and not kernels.AVAILABLE:
        pytest.skip("numba not installed")
    monkeypatch.setattr(kernels, "AVAILABLE", jit and kernels.AVAILABLE)
    stack, origin, c, A, shape, s = _cross_stack(2, n=6)
    bg, wt, _ = scene_background(stack, shape, 1.0, -1)
    c0 = c + np.random.default_rng(7).uniform(-0.4, 0.4, c.shape)
    ref = np.round(c0)
    p0 = np.zeros((len(c0), L._NP))
    p0[:, 0:2] = c0 - ref
    p0[:, 2:6] = A.reshape(-1, 4)
    p0[:, 6] = 1.0
    data = L._gather(stack, origin, ref, c0, A, shape, 2.5 + 1.25, bg, wt, None, (0.0, 1.0))
    full = np.ones(L._NP, bool)
    n = len(c0)
    out = []
    for own in (False, True):
        p, conv = p0.copy(), np.zeros(n, bool)
        d = tuple(a.copy() for a in data)
        if own:  # the loop writing every step into its own arrays (what it did before)
            st = L._step(p0.copy(), tuple(a.copy() for a in data), shape, full, robust=False,
                         init=True)[2]
            last = {k: np.full((n,) + v.shape[1:], np.nan, v.dtype) if v.dtype.kind == "f"
                    else np.zeros((n,) + v.shape[1:], v.dtype) for k, v in st.items()}
        else:
            last = None
        last, it = L._steps(p, d, shape, full, True, 1, 10, 5e-4, np.arange(n), last, conv,
                            True)
        out.append((p, last, it, conv))
        if not own:
            for v in last.values():
                assert not any(np.shares_memory(v, a) for a in d)
    (p1, l1, i1, c1), (p2, l2, i2, c2) = out
    assert np.array_equal(p1, p2) and i1 == i2 and np.array_equal(c1, c2) and c1.any()
    assert l1.keys() == l2.keys()
    for k in l1:
        assert np.array_equal(l1[k], l2[k], equal_nan=True), k
    assert np.abs(p1[:, 0:2] + ref - c).max() < 0.3
