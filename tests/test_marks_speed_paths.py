"""Faster paths of the reseau detection's stages give exactly what the plain formulations
give (the plain ones written out here, as they stood in the package before)."""

from __future__ import annotations

import numpy as np
import pytest

from softplot.marks import candidates, coarse


def _arm_evidence_plain(image, xy, sign, arm_half, width, s, turn_deg=0.0):
    """:func:`candidates.arm_evidence` as first written: each point's window gathered by
    clipped indices, the mean along an arm by ``mean(-1)``, the third-best arm by a sort."""
    K = len(xy)
    out = np.full(K, -np.inf)
    Hh, W = image.shape
    r0 = max(1.5, width + s)
    r = np.linspace(r0, max(arm_half, r0 + 1.0), 6)
    d = max(1.5, 1.0 * width + 1.5 * s)
    reach = int(np.ceil(np.hypot(r[-1], d))) + 2
    x0 = np.floor(xy[:, 0]).astype(int)
    y0 = np.floor(xy[:, 1]).astype(int)
    ok = (x0 >= 0) & (x0 < W) & (y0 >= 0) & (y0 < Hh)
    t = np.radians(turn_deg + candidates.ARM_TURNS)[:, None] + np.arange(4) * (np.pi / 2)
    u = np.stack([np.cos(t), np.sin(t)], -1)
    nrm = np.stack([-u[..., 1], u[..., 0]], -1)
    side = np.array([0.0, d, -d])
    off = (r[None, None, None, :, None] * u[:, :, None, None, :]
           + side[None, None, :, None, None] * nrm[:, :, None, None, :])
    i = np.flatnonzero(ok)
    ar = np.arange(-reach, reach + 2)
    cy = np.clip(y0[i][:, None] + ar, 0, Hh - 1)
    cx = np.clip(x0[i][:, None] + ar, 0, W - 1)
    win = np.asarray(image[cy[:, :, None], cx[:, None, :]], np.float32)
    p = xy[i]
    fx, fy = p[:, 0] - x0[i] + reach, p[:, 1] - y0[i] + reach
    v = candidates._read(win, fx, fy, off.reshape(-1, 2)).reshape((len(p),) + off.shape[:4])
    v = v.mean(-1)
    d1, d2 = v[..., 0] - v[..., 1], v[..., 0] - v[..., 2]
    a = sign * np.where(sign > 0, np.minimum(d1, d2), np.maximum(d1, d2))
    third = np.sort(a, axis=2)[..., 1]
    bar = np.maximum(np.minimum(a[..., 0], a[..., 2]), np.minimum(a[..., 1], a[..., 3]))
    out[ok] = np.maximum(third, 0.5 * bar).max(1)
    return out


def test_arm_evidence_on_two_threads_is_the_same(monkeypatch):
    """The arms' evidence read a chunk at a time on two threads equals the one thread's bit
    for bit (the chunks are independent)."""
    from softplot import runtime

    rng = np.random.default_rng(4)
    img = rng.uniform(0.3, 0.6, (80, 100)).astype(np.float32)
    pts = np.column_stack([rng.uniform(-3, 103, 300), rng.uniform(-3, 83, 300)])
    monkeypatch.setattr(candidates, "ARM_CHUNK", 16)
    try:
        runtime.set_threads(1)
        one = candidates.arm_evidence(img, pts, 1, 8.0, 1.0, 0.7)
        runtime.set_threads(2)
        two = candidates.arm_evidence(img, pts, 1, 8.0, 1.0, 0.7)
    finally:
        runtime.set_threads(None)
    assert np.isfinite(one).sum() > 250
    assert np.array_equal(one, two)


@pytest.mark.parametrize("sign", [1, -1])
def test_arm_evidence_is_the_plain_formulation(sign, monkeypatch):
    """On a float image and on a compact 8-bit overview (inverted grey), points inside, at
    and beyond the edges: the evidence equals the plain formulation's bit for bit (one
    chunk, as the plain one reads them), and -inf outside."""
    import cv2

    rng = np.random.default_rng(11)
    img = rng.uniform(0.3, 0.6, (70, 95)).astype(np.float32)
    cv2.line(img, (20, 30), (60, 30), 0.8, 1)
    cv2.line(img, (40, 10), (40, 50), 0.8, 1)
    img = cv2.GaussianBlur(img, (0, 0), 0.7)
    q = np.round(img * 255).astype(np.uint8)
    ov = coarse.Overview(q, 1.0 / 255.0, invert=True)
    pts = np.column_stack([rng.uniform(-4, 99, 120), rng.uniform(-4, 74, 120)])
    pts[:4] = [[40.3, 30.6], [0.2, 0.7], [94.5, 69.5], [3.0, 68.2]]
    monkeypatch.setattr(candidates, "ARM_CHUNK", 1000)
    for image in (img, ov):
        for turn in (0.0, 7.5):
            fast = candidates.arm_evidence(image, pts, sign, 8.0, 1.0, 0.7, turn)
            plain = _arm_evidence_plain(image, pts, sign, 8.0, 1.0, 0.7, turn)
            assert np.isfinite(fast).sum() > 80
            assert np.array_equal(fast, plain)


def _local_solve_plain(D, w, vals, tol=1e-6):
    """:func:`kernels.local_solve` as first written (plain Python, the same IEEE double
    arithmetic as the compiled kernel, which is not built with fast-math): one sum over the
    neighbours at a time, the normalisation's roots taken per entry."""
    from softplot.marks import kernels

    chol = kernels._chol_above.py_func
    pivot = kernels._pivot.py_func
    R, k, C = vals.shape
    Q, _, p = D.shape
    out = np.empty((R, C))
    level = np.empty(R, np.int64)
    N0, Nn, W = np.empty((p, p)), np.empty((p, p)), np.empty((p, p))
    A = np.empty((p, p + C))
    for r in range(R):
        Dq = D[r % Q]
        for a in range(p):
            for b in range(a, p):
                t = 0.0
                for i in range(k):
                    t += float(Dq[i, a]) * float(w[r, i]) * float(Dq[i, b])
                N0[a, b] = N0[b, a] = t
        for a in range(p):
            for b in range(p):
                Nn[a, b] = N0[a, b] / (np.sqrt(max(N0[a, a], 1e-300))
                                       * np.sqrt(max(N0[b, b], 1e-300)))
        if chol(Nn, p, tol, W):
            lev = p
        else:
            lev = 0
            for L in (3, 6, 10):
                if L >= p or not chol(Nn, L, tol, W):
                    break
                lev = L
        level[r] = lev
        use = max(lev, 3)
        for a in range(p):
            for b in range(p):
                A[a, b] = N0[a, b] if (a < use and b < use) else 0.0
            A[a, a] += 1e-9 if a < use else 1.0 + 1e-9
            for c in range(C):
                t = 0.0
                if a < use:
                    for i in range(k):
                        t += float(Dq[i, a]) * float(w[r, i]) * float(vals[r, i, c])
                A[a, p + c] = t
        for c in range(p):
            piv, _ = pivot(A, c, p)
            if piv != c:
                A[[c, piv]] = A[[piv, c]]
            for a in range(c + 1, p):
                f = A[a, c] / A[c, c]
                if f != 0.0:
                    A[a, c:] -= f * A[c, c:]
        for c in range(C):
            for a in range(p - 1, -1, -1):
                t = A[a, p + c]
                for b in range(a + 1, p):
                    t -= A[a, b] * A[b, p + c]
                A[a, p + c] = t / A[a, a]
            out[r, c] = A[0, p + c]
    return out, level


@pytest.mark.parametrize("p", [3, 6, 10])
def test_compiled_local_solve_is_the_plain_loop(p):
    """The compiled local fits (the neighbours' sums four at a time, the normalisation's
    roots once per fit) give the plain loop's figures bit for bit: random designs and
    weights, each degree, with rows whose neighbours are collinear (the degree drops)."""
    from softplot.marks import kernels

    if not kernels.ready():
        pytest.skip("numba not available")
    rng = np.random.default_rng(p)
    Q, k, C = 7, 16 if p < 10 else 24, 3
    X, Y = rng.normal(0, 1.5, (2, Q, k))
    Y[2] = 0.5 * X[2]  # collinear neighbours: no plane beyond a line
    Y[4] = np.round(Y[4])  # a few rows of neighbours: no cubic in y
    cols = [np.ones_like(X), X, Y, X**2, X * Y, Y**2, X**3, X**2 * Y, X * Y**2, Y**3][:p]
    D = np.stack(cols, -1)
    w = rng.uniform(0.05, 1.0, (3 * Q, k))
    vals = rng.normal(0, 1, (3 * Q, k, C))
    got, lev = kernels.local_solve(D, w, vals)
    ref, lev_ref = _local_solve_plain(D, w, vals)
    assert np.array_equal(lev, lev_ref) and lev.min() < p
    assert np.array_equal(got, ref)


@pytest.mark.parametrize("Q", [150, 61])
def test_local_solve_split_over_two_threads_is_the_same(Q, monkeypatch):
    """A large batch of local fits solved in two parts on two threads (one design per row,
    ``Q == R``, or designs shared by the rows of a batch of value sets) gives the figures of
    the single pass bit for bit."""
    from softplot import runtime
    from softplot.marks import kernels

    if not kernels.ready():
        pytest.skip("numba not available")
    monkeypatch.setattr(kernels, "SPLIT_ROWS", 100)
    rng = np.random.default_rng(Q)
    k = 16
    X, Y = rng.normal(0, 1.5, (2, Q, k))
    D = np.stack([np.ones_like(X), X, Y, X**2, X * Y, Y**2], -1)
    R = Q if Q > 100 else 5 * Q
    w = rng.uniform(0.05, 1.0, (R, k))
    vals = rng.normal(0, 1, (R, k, 2))
    try:
        runtime.set_threads(1)
        one, lev1 = kernels.local_solve(D, w, vals)
        runtime.set_threads(2)
        used = []
        orig = kernels._local_solve
        monkeypatch.setattr(kernels, "_local_solve", lambda *a: (used.append(len(a[1])),
                                                                 orig(*a)))
        two, lev2 = kernels.local_solve(D, w, vals)
    finally:
        runtime.set_threads(None)
    assert sorted(used) == ([R // 2, R - R // 2] if Q == R else [2 * Q, 3 * Q])
    assert np.array_equal(one, two) and np.array_equal(lev1, lev2)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_patches_are_the_pixelwise_gather(dtype):
    """The measurement's windows (``measure.patches``: the wholly inside ones each a slice of
    the scan) hold the scan's grey values of a pixel-by-pixel gather exactly, those cut by the
    scan's edge NaN beyond it, and their origins."""
    from softplot.io import Scan
    from softplot.marks.measure import patches

    rng = np.random.default_rng(2)
    top = np.iinfo(dtype).max
    data = rng.integers(0, top, (70, 90), dtype=dtype, endpoint=True)
    sc = Scan.from_array(data)
    c = np.array([[30.4, 20.6], [45.0, 40.0], [3.0, 5.0], [88.0, 66.0], [60.2, 30.9]])
    half = 9
    stack, origin = patches(sc, c, half)
    size = 2 * half + 1
    o = np.round(c).astype(int) - half
    assert np.array_equal(origin, o.astype(float))
    ar = np.arange(size)
    for i in range(len(c)):
        rr, cc = o[i, 1] + ar, o[i, 0] + ar
        inside = ((rr >= 0) & (rr < 70))[:, None] & ((cc >= 0) & (cc < 90))[None, :]
        ref = np.full((size, size), np.nan, np.float32)
        vals = data[np.clip(rr, 0, 69)[:, None], np.clip(cc, 0, 89)[None, :]]
        ref[inside] = (vals * np.float32(1.0 / top))[inside]
        assert np.array_equal(stack[i], ref, equal_nan=True)
    assert np.isnan(stack[2]).any() and np.isfinite(stack[[0, 1, 4]]).all()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_median_rows_is_numpys_median(dtype):
    """``common.median_rows``: NumPy's row medians bit for bit, odd and even rows, ties,
    signed zeros and rows with NaN (NumPy's own there)."""
    from softplot.marks.common import median_rows

    rng = np.random.default_rng(8)
    for n in (1, 2, 3, 8, 9, 2760, 2761):
        a = rng.normal(0, 1, (6, n)).astype(dtype)
        a[1] = np.round(a[1])  # ties
        a[2, : n // 2] = 0.0
        a[2, n // 2 :] = -0.0
        got, ref = median_rows(a), np.median(a, axis=1)
        assert got.dtype == ref.dtype and np.array_equal(got, ref)
    a = rng.normal(0, 1, (3, 50)).astype(dtype)
    a[1, 7] = np.nan
    got, ref = median_rows(a), np.median(a, axis=1)
    assert np.array_equal(got, ref, equal_nan=True) and np.isnan(got[1])


def test_both_signs_peaks_found_side_by_side_are_the_one_threads():
    """reseau_candidates finds each sign's NCC peaks on its own thread (two signs, two
    threads): the peaks of both signs, their scores and bounds are the one thread's bit for
    bit, and the two searches ran on the pool's threads."""
    import threading

    from softplot import runtime
    from softplot.camera import load_camera
    from softplot.io import Scan
    from softplot.marks import coarse
    from softplot.marks.overview import reseau_overview
    from softplot.marks.template import cross_shape
    from softplot.synthetic import ScanSpec, render_scan

    cam = load_camera("rollei-6006")
    img, _ = render_scan(cam, ScanSpec(dpi=600.0, rotation_deg=1.5, scene="busy"), seed=5)
    sc = Scan.from_array(img, dpi=600.0)
    ppm = 600.0 / 25.4
    ov = reseau_overview(sc, cross_shape(cam, ppm).width, ppm, "scan")
    where = []
    real = coarse.find_peaks

    def spy(*a, **k):
        where.append(threading.current_thread().name)
        return real(*a, **k)

    got = {}
    try:
        for n in (1, 2):
            runtime.set_threads(n)
            where.clear()
            with pytest.MonkeyPatch.context() as mp:
                mp.setattr(coarse, "find_peaks", spy)
                c = candidates.reseau_candidates(sc, ov, cam, "auto", 1.0).complete()
            got[n] = c
            assert len(where) == 2
            assert all(w.startswith("softplot") for w in where) == (n == 2)
    finally:
        runtime.set_threads(None)
    assert set(got[1].peaks) == set(got[2].peaks) == {1, -1}
    for sg in (1, -1):
        a, b = got[1].peaks[sg], got[2].peaks[sg]
        assert len(a.score) >= 100
        assert np.array_equal(a.xy, b.xy) and np.array_equal(a.score, b.score)
        assert got[1].bound[sg] == got[2].bound[sg]
