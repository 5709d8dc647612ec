"""Neighbours' predictions: what a smooth film deformation lets the neighbours of a mark say.

A film deformation (and the scanner's) moves neighbouring marks alike, so the residual of a
mark against the global film -> pixel model, and its local Jacobian, are predicted by a local
polynomial through its neighbours (:func:`local_fit`). The measurement stage
(:mod:`softplot.marks.measurement`: affines held from the neighbours) and the validation stage
(:mod:`softplot.marks.validation`: outlier test, rescue) share these functions. Arrays: film
(plate) system mm for positions on the film, pixel system px for residuals and positions.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from contextlib import contextmanager

import numpy as np
from scipy.spatial import cKDTree

from softplot.marks import kernels
from softplot.marks.common import inverse_2x2, median_rows

__all__ = ["local_fit", "local_prediction", "nearest", "outline", "position_affine", "remembered"]


def local_fit(q_film, n_film, n_val, k_max=16, degree=2, n_sigma=None, n_dev=None,
               gradient=False, only=None):
    """Values at query points from a weighted local polynomial through their neighbours.

    For each query point (``q_film`` (Q, 2) mm) a polynomial in film mm (plane for
    ``degree=1``; quadratic for ``degree=2`` when at least 9 neighbours; cubic for
    ``degree=3`` when at least 16, else quadratic) is fitted to the values ``n_val`` (M, C)
    of its ``k`` nearest neighbours ``n_film`` (M, 2), the query point itself left out, with
    weights ``1/(1 + d^2)`` (``d`` in units of the median neighbour spacing), lowered for
    imprecise neighbours (``n_sigma`` (M,), against the typical one) and for neighbours far
    from their own prediction (``n_dev`` (M,), against 3x its robust spread).

    Returns (Q, C); with ``gradient`` also the polynomial's gradient at each query point
    (Q, C, 2) (value units per mm) and the variance factor of that gradient (Q,) (its two
    components' variances summed, for unit noise on the values; per mm^2).

    A batch of value sets: ``n_val`` (B, M, C) with ``n_dev`` (B, M) or None fits each set
    as its own call would, in one pass (the neighbours are found once), and returns
    (B, Q, C) (not with ``gradient``).

    ``only`` (Q,) bool: the values at these query points alone ((Q', C) or (B, Q', C), Q'
    of them), each the figure the call without it gives there (the unit of distance is
    still the median neighbour spacing of all ``q_film``; every fit is its own).
    """
    n_val = np.asarray(n_val, float)
    batch = n_val.ndim == 3
    n_val = n_val.reshape(len(n_val) if batch else 1, len(n_film), -1)  # (B, M, C)
    B = n_val.shape[0]
    k = min(k_max, len(n_film) - 1)
    d, j = nearest(q_film, n_film, k + 1)
    # leave the query point out (a zero-distance match), else the farthest neighbour
    drop = np.where(d[:, 0] < 1e-9, 0, k)
    keep = np.arange(k + 1)[None, :] != drop[:, None]
    d = d[keep].reshape(-1, k)
    j = j[keep].reshape(-1, k)
    unit = float(np.median(d[:, 0])) or 1.0
    q_film = np.asarray(q_film)
    if only is not None:  # the fits at these queries only (the unit from all of them)
        d, j, q_film = d[only], j[only], q_film[only]
    dx = (n_film[j] - q_film[:, None, :]) / unit  # (Q, k, 2)
    X, Y = dx[..., 0], dx[..., 1]
    cols = [np.ones(d.shape), X, Y]
    if degree >= 2 and k >= 9:
        cols += [X**2, X * Y, Y**2]
    if degree >= 3 and k >= 16:
        cols += [X**3, X**2 * Y, X * Y**2, Y**3]
    D = np.stack(cols, -1)  # (Q, k, p)
    w = 1.0 / (1.0 + (d / unit) ** 2)
    if n_sigma is not None:
        sg = np.nan_to_num(np.asarray(n_sigma, float), nan=1.0)
        w = w / (1.0 + (sg[j] / (float(np.median(sg)) + 1e-6)) ** 2)
    Q = len(d)
    if n_dev is not None:
        n_dev = np.asarray(n_dev, float).reshape(B, -1)
        spread = 1.4826 * median_rows(n_dev) + 1e-12  # (B,)
        # (np.take: the same gather as ``n_dev[:, j]``, several times faster)
        w = w / (1.0 + (np.take(n_dev, j, axis=1) / (3.0 * spread[:, None, None])) ** 2)
        w = w.reshape(B * Q, k)
    # else the same weights for every value set: one fit, its columns the sets' values
    C = n_val.shape[-1]
    nj = np.take(n_val, j, axis=1)  # n_val[:, j] (B, Q, k, C)
    if n_dev is not None:  # (B * Q, k, C)
        vals = nj.reshape(B * Q, k, C)
    else:  # (Q, k, B * C)
        vals = nj.transpose(1, 2, 0, 3).reshape(Q, k, B * C)
    if gradient or not kernels.ready():  # row r of a batch: design D[r % Q]
        Dr = D if len(w) == Q else np.broadcast_to(D, (B,) + D.shape).reshape(B * Q, k, -1)
        coef, level, DwT, N = _solve(Dr, w, vals)
        c0 = coef[:, 0, :]
    else:  # the same fits compiled, one pass per row (most of a batch was NumPy's overhead)
        c0 = kernels.local_solve(D, w, vals)[0]
    if batch:
        if n_dev is not None:
            return c0.reshape(B, Q, C)
        return c0.reshape(Q, B, C).transpose(1, 0, 2)
    if not gradient:
        return c0
    Ni = np.linalg.inv(N)
    var = Ni @ np.matmul(DwT, DwT.transpose(0, 2, 1)) @ Ni  # coefficients, unit noise
    grad = np.stack([coef[:, 1, :], coef[:, 2, :]], -1) / unit
    grad[level < 3] = np.nan
    return c0, grad, (var[:, 1, 1] + var[:, 2, 2]) / unit**2


#: the neighbour queries :func:`nearest` keeps (the last ones asked for)
NEAREST_KEPT = 8
_NEAREST: OrderedDict = OrderedDict()
_NEAREST_LOCK = threading.Lock()


def nearest(q_film, n_film, k):
    """``cKDTree(n_film).query(q_film, k)``: the distances and indices (Q, k) of the ``k``
    nearest of the points ``n_film`` (M, 2) to each of ``q_film`` (Q, 2) (film mm), ties in
    the tree's order. The last :data:`NEAREST_KEPT` queries are kept by the values of their
    points: a scan's validation asks the same ones several times (the outlier test, the
    variance factor's draws, the rescue: the same crosses, other values), and the tree's
    query was a quarter of the neighbours' fits. Returns read-only arrays."""
    q = np.ascontiguousarray(q_film, float)
    m = np.ascontiguousarray(n_film, float)
    key = (q.shape, m.shape, int(k), q.tobytes(), m.tobytes())
    with _NEAREST_LOCK:
        got = _NEAREST.get(key)
        if got is not None:
            _NEAREST.move_to_end(key)
            return got
    d, j = cKDTree(n_film).query(q_film, k=k)
    d.flags.writeable = False
    j.flags.writeable = False
    with _NEAREST_LOCK:
        _NEAREST[key] = (d, j)
        while len(_NEAREST) > NEAREST_KEPT:
            _NEAREST.popitem(last=False)
    return d, j


def _solve(D, w, vals):
    """The weighted fits of :func:`local_fit` by NumPy: designs ``D`` (R, k, p), weights
    ``w`` (R, k), values ``vals`` (R, k, C) (units of the neighbour spacing). Returns the
    coefficients (R, p, C), the terms used (R,) (3 plane, 6 quadratic, 10 cubic, 0 none),
    the masked weighted design transposed (R, p, k) and normal equations (R, p, p)."""
    # per query the highest degree its neighbours determine (a partial grid of a few rows
    # cannot carry a cubic in y): the terms of a degree whose normal equations are
    # ill-conditioned are dropped for that query; a plane that is not determined (collinear
    # neighbours) gives no gradient (NaN)
    p = D.shape[-1]
    DwT0 = (D * w[..., None]).transpose(0, 2, 1)
    N0 = np.matmul(DwT0, D)
    dg = np.sqrt(np.maximum(np.einsum("qii->qi", N0), 1e-300))
    Nn = N0 / (dg[:, :, None] * dg[:, None, :])  # unit diagonal
    # the leading blocks of Nn are the normalised lower-degree matrices, and no eigenvalue of
    # a principal submatrix lies below the smallest of the whole (Cauchy interlacing): where
    # the full degree is well conditioned every lower one is, and only the rest are tested
    level = np.zeros(len(w), int)  # terms used: 3 plane, 6 quadratic, 10 cubic (0: none)
    full = _smallest_eig_above(Nn, 1e-6)
    level[full] = p
    rest = np.where(~full)[0]
    lev_r = np.zeros(rest.size, int)
    below = 0
    for L in (3, 6, 10):
        if L >= p or rest.size == 0:
            break
        well = _smallest_eig_above(Nn[rest, :L, :L], 1e-6)
        lev_r = np.where(well & (lev_r == below), L, lev_r)
        below = L
    level[rest] = lev_r
    # the dropped terms' rows and columns of the normal equations are 0 (their coefficients
    # 0): masks of N0 and of the weighted design, no second product
    use = (np.arange(p)[None, :] < np.maximum(level, 3)[:, None]).astype(float)  # (Q, p)
    DwT = DwT0 * use[:, :, None]
    N = N0 * (use[:, :, None] * use[:, None, :]) + 1e-9 * np.eye(p)
    N[:, np.arange(p), np.arange(p)] += 1.0 - use
    coef = np.linalg.solve(N, np.matmul(DwT, vals))  # (rows, p, columns)
    return coef, level, DwT, N


def _smallest_eig_above(S, tol):
    """Whether the smallest eigenvalue of each symmetric matrix ``S`` (n, p, p) exceeds
    ``tol`` (n,) bool: whether ``S - tol I`` is positive definite, i.e. has a Cholesky
    factor with positive pivots (vectorised over the stack, p steps: several times cheaper
    than the eigenvalues)."""
    A = np.array(S, float)
    p = A.shape[-1]
    A[:, np.arange(p), np.arange(p)] -= tol
    ok = np.ones(len(A), bool)
    for c in range(p):
        piv = A[:, c, c]
        ok &= piv > 0.0
        piv = np.where(ok, piv, 1.0)
        col = A[:, c + 1:, c] / piv[:, None]  # (n, p - c - 1)
        A[:, c + 1:, c + 1:] -= col[:, :, None] * A[:, c, c + 1:][:, None, :]
    return ok


_MEMO = threading.local()  # the calls of local_prediction within ``remembered`` (this thread)


@contextmanager
def remembered():
    """Within this context (in this thread) :func:`local_prediction` called again with the
    inputs of an earlier call returns a copy of that call's result: the same values,
    computed once (the validation of a scan asks for some predictions several times)."""
    outer = getattr(_MEMO, "calls", None)
    if outer is None:
        _MEMO.calls = []
    try:
        yield
    finally:
        if outer is None:
            _MEMO.calls = None


def _same_inputs(a, b) -> bool:
    """Whether two calls' inputs ``(film, r, k_max, sigma)`` hold the same values."""
    for x, y in zip(a, b, strict=True):
        if x is None or y is None:
            if x is not y:
                return False
        elif np.isscalar(x):
            if x != y:
                return False
        elif x.shape != y.shape or not np.array_equal(x, y, equal_nan=True):
            return False
    return True


def local_prediction(film, r, k_max=16, sigma=None):
    """Leave-one-out prediction of each residual from a local polynomial fit to its neighbours
    (:func:`_local_prediction`; within :func:`remembered`, once per distinct inputs)."""
    calls = getattr(_MEMO, "calls", None)
    if calls is None:
        return _local_prediction(film, r, k_max, sigma)
    key = (np.array(film, float), np.array(r, float), int(k_max),
           None if sigma is None else np.array(sigma, float))
    for k, out in calls:
        if _same_inputs(k, key):
            return out.copy()
    out = _local_prediction(film, r, k_max, sigma)
    calls.append((key, out.copy()))
    return out


def _local_prediction(film, r, k_max=16, sigma=None):
    """Leave-one-out prediction of each residual from a local polynomial fit to its neighbours.

    ``film`` (M, 2) mm, ``r`` (M, 2) px. A smooth film deformation is locally quadratic to a
    good approximation (:func:`local_fit`); inside the grid, where the neighbours surround
    the mark, a local cubic through the 24 nearest follows a 100 um deformation several times
    better (true positions at 2400 dpi: largest departure 0.017 px instead of 0.036 px); on
    the grid's outline, where the fit extrapolates, the quadratic is kept. A second pass
    lowers the weight of neighbours that depart from their own prediction (one bad neighbour
    must not condemn a good mark, at a corner especially). Returns the predicted residuals
    (M, 2); for a batch of residual sets ``r`` (B, M, 2), each set's as its own call would,
    (B, M, 2).
    """
    pred = local_fit(film, film, r, k_max, 2, n_sigma=sigma)
    dev = np.hypot((r - pred)[..., 0], (r - pred)[..., 1])
    edge = outline(film)
    # the second pass's quadratic only where it is kept (the outline): inside, the cubic
    out = np.empty(np.shape(pred))
    out[..., edge, :] = local_fit(film, film, r, k_max, 2, n_sigma=sigma, n_dev=dev,
                                  only=edge)
    inner = ~edge
    if inner.any():
        out[..., inner, :] = local_fit(film[inner], film, r, 24, 3, n_sigma=sigma, n_dev=dev)
    return out


def outline(film, present=None):
    """Marks on the outline of the certificate's grid (M,) bool; with ``present`` (M,) bool
    (e.g. the measured marks) also those of which a lattice neighbour (one pitch along film x
    or y) is not present: at the edge of a cropped or partial frame, or beside a gap, a
    mark's neighbours' prediction extrapolates, as on the grid's outline."""
    film = np.asarray(film, float)
    lo, hi = film.min(0), film.max(0)
    tol = 1e-6 * float(np.max(hi - lo) + 1.0)
    out = ((np.abs(film - lo) < tol) | (np.abs(film - hi) < tol)).any(1)
    present = None if present is None else np.asarray(present, bool)
    if present is None or not present.any() or len(film) < 2:
        return out
    have = cKDTree(film[present])
    for k in (0, 1):
        u = np.unique(np.round(film[:, k], 6))
        d = np.diff(u)
        if d.size == 0:
            continue
        step = np.zeros(2)
        step[k] = float(d.min())
        for sgn in (1.0, -1.0):
            q = film + sgn * step
            # only where the certificate has that neighbour (the grid's own outline is above)
            inside = ((q >= lo - tol) & (q <= hi + tol)).all(1)
            dist, _ = have.query(q)
            out |= inside & (dist > 0.25 * step[k])
    return out


def position_affine(film, xy, ok, ppm, k=24, with_position=False):
    """Each mark's pixel -> mark-frame affine predicted from its neighbours' positions.

    The affine of a mark is the local Jacobian of the film mm -> pixel mapping (film
    deformation and scanner) in the mark frame (u along film x, v along film -y, nominal px,
    as ``A0``): here the derivative of a local cubic (:func:`local_fit`) through the
    measured pixel positions ``xy`` (M, 2) of the ``k`` nearest accepted marks (``ok`` (M,)),
    the mark itself left out. The positions are the most precise thing the detector measures
    (a Rollei's neighbours are 5 mm apart, the arms 0.8 mm long): a cubic follows a 100 um
    deformation to about 5e-5, where a plane through even the exact affines of the
    neighbours misses it by about 4e-4
    (``tests/test_marks_units.py::test_affine_from_neighbour_positions_follows_a_strong_deformation``).

    Returns
    -------
    A : (M, 2, 2)
        Predicted affines (NaN where fewer than 4 marks are accepted).
    lev : (M,)
        Variance factor of each prediction's Jacobian for unit position noise (px^2 / mm^2):
        large where the neighbours lie to one side (corners, edges).
    xy : (M, 2)
        With ``with_position``: each mark's position (pixel system) predicted by the same
        local polynomial (the mark itself left out).
    """
    good = np.where(ok & np.isfinite(xy).all(1))[0]
    M = len(film)
    if good.size < 4:
        out = np.full((M, 2, 2), np.nan), np.full(M, np.nan)
        return out + (np.full((M, 2), np.nan),) if with_position else out
    pos, grad, lev = local_fit(film, film[good], xy[good], k, degree=3, gradient=True)
    # a degenerate neighbourhood (collinear marks: a Jacobian near singular, |det| ~ 1
    # otherwise) gives NaN
    A = inverse_2x2(grad @ np.diag([1.0 / ppm, -1.0 / ppm]), 1e-6)
    return (A, lev, pos) if with_position else (A, lev)
