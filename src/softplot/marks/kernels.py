"""Compiled (numba) kernel of least-squares matching for crosses: model and Jacobian.

:func:`cross_model` computes, for N crosses of up to P pixels each, exactly what
``lsm._assemble(p, data, lsm._geom(p, data, shape))`` computes with NumPy -- the mark-frame
coordinates, the blurred cross seen through square pixels (:meth:`MarkShape.evaluate` with
:func:`softplot.marks.template.aperture`), the model grey values and the 12-column Jacobian --
in one pass over the pixels instead of some 250 array operations, and it skips the profile
terms that are saturated (0 or 1 with zero derivatives; a bar's far side is most of them).
The standard normal CDF and density of :func:`softplot.marks.template._Phi_phi` are read from
a table of that function at 1/256 steps with linear interpolation (error below 5e-7 each,
1e-5 of the contrast in the model, far below any scan's noise), which is what makes the pass
cheap: no transcendental function per pixel.
``tests/test_marks_units.py::test_compiled_cross_model_matches_numpy`` holds the two
implementations together.

The rest of an LSM step is compiled too, each the NumPy path's arithmetic in one pass:
:func:`weigh` (residuals, censoring, robust and prior weights, the weighted Jacobian and
gradient), :func:`invert` and :func:`advance` (the pinned, damped normal equations' inverse
and the limited update), :func:`influence` (the centre's influence on each pixel); and
:func:`gather_cross` (the pixels a fit uses), :func:`corr_sums` (the residual correlation of
the covariance, summed directly over the few lags it uses instead of by FFTs),
:func:`cross_template` (the joint scene's template) and :func:`scale_columns` (the first step's
Jacobian scaled by the contrast). Most of a fit of a few marks was NumPy's
per-call overhead; these passes hold the GIL only to start
(``tests/test_marks_speed_accuracy.py::test_compiled_lsm_step_gather_and_correlation_match_numpy``).
:func:`fine_steps` runs LSM's whole fine stage in one compiled loop, mark by mark (the same
steps; between them no Python, so a second thread's fits run alongside;
``tests/test_marks_speed_accuracy.py::test_compiled_fine_stage_is_the_step_by_step_loop``).

:func:`local_solve` fits the neighbours' local polynomials of
:func:`softplot.marks.neighbours.local_fit` (film mm in units of the neighbour spacing), one
pass per fit, the degree chosen as there
(``tests/test_marks_neighbours_batch.py::test_compiled_local_fit_is_the_numpy_fit``).

The LSM arrays are in the pixel system of :mod:`softplot.marks.lsm` (coordinates relative to
each mark's reference pixel). Without numba (or with ``SOFTPLOT_JIT=0`` in the environment)
:data:`AVAILABLE` is False and LSM uses its NumPy path.
"""

from __future__ import annotations

import os
import threading
import warnings

import numpy as np

from softplot.marks.template import _ZSAT, _Phi_phi

__all__ = ["AVAILABLE", "cross_model", "weigh", "influence", "invert", "advance", "gather_cross",
           "cross_template", "corr_sums", "half_arms", "local_solve", "fine_steps",
           "scale_columns", "load", "ready", "on_load"]

try:  # pragma: no cover - exercised where numba is installed (it is a dependency)
    if os.environ.get("SOFTPLOT_JIT", "1") == "0":
        raise ImportError("disabled by SOFTPLOT_JIT=0")
    import numba
except ImportError:  # pragma: no cover
    numba = None

AVAILABLE = numba is not None

_f4 = np.float32
#: table steps per unit of z
_HZ = 256.0
_Z = np.arange(-float(_ZSAT) - 2.0 / _HZ, float(_ZSAT) + 4.0 / _HZ, 1.0 / _HZ).astype(np.float32)
_TP, _TD = (np.ascontiguousarray(a, np.float32) for a in _Phi_phi(_Z))
_Z0 = _f4(_Z[0])
_IH = _f4(_HZ)
_ONE, _ZERO, _HALF = _f4(1.0), _f4(0.0), _f4(0.5)
_TWELFTH = _f4(1.0 / 12.0)


def _no_jit(*args, **kwargs):  # without numba the kernel is defined but never called
    return lambda f: f


# module-level functions (not closures), so that numba's on-disk cache finds them again in
# the next process instead of compiling anew
njit = numba.njit if AVAILABLE else _no_jit


@njit(inline="always", fastmath=True)
def _phi_pd(z):
    w = (min(max(z, -_ZSAT), _ZSAT) - _Z0) * _IH
    k = int(w)
    f = w - _f4(k)
    p0 = _TP[k]
    d0 = _TD[k]
    return p0 + f * (_TP[k + 1] - p0), d0 + f * (_TD[k + 1] - d0)


@njit(inline="always", fastmath=True)
def _box(t, h, inv):
    # blurred box of half-width h (template.box_profile): value, d/dt, d/ds
    zp = (t + h) * inv
    zm = (t - h) * inv
    if zp <= -_ZSAT or zm >= _ZSAT:
        return _ZERO, _ZERO, _ZERO
    if zp >= _ZSAT and zm <= -_ZSAT:
        return _ONE, _ZERO, _ZERO
    Pp, pp = _phi_pd(zp)
    Pm, pm = _phi_pd(zm)
    return Pp - Pm, (pp - pm) * inv, -(zp * pp - zm * pm) * inv


@njit(inline="always", fastmath=True)
def _pixel_box(t, h, hb, inv):
    # the four Psi terms of template.box_pixel_profile: sum, d/dz sum, density sum
    z0 = (t + h + hb) * inv
    z3 = (t - h - hb) * inv
    P = _ZERO
    dt = _ZERO
    ds = _ZERO
    if z0 <= -_ZSAT or z3 >= _ZSAT:
        return P, dt, ds
    for k in range(4):
        if k == 0:
            z, sg = z0, _ONE
        elif k == 1:
            z, sg = (t + h - hb) * inv, -_ONE
        elif k == 2:
            z, sg = (t - h + hb) * inv, -_ONE
        else:
            z, sg = z3, _ONE
        if z <= -_ZSAT:
            continue
        if z >= _ZSAT:  # Phi = 1, density 0: Psi(z) = z
            P += sg * z
            dt += sg
            continue
        P_, p_ = _phi_pd(z)
        P += sg * (z * P_ + p_)
        dt += sg * P_
        ds += sg * p_
    return P, dt, ds


@njit(fastmath=True, cache=True, nogil=True)
def _kernel(X, Y, S, Qs, q, length, width, alpha, M, T, Tu, Tv, U, V, J):
    n, npx = X.shape
    hL = _HALF * length
    hW = _HALF * width
    for i in range(n):
        cx, cy = _f4(q[i, 0]), _f4(q[i, 1])
        a00, a01, a10, a11 = _f4(q[i, 2]), _f4(q[i, 3]), _f4(q[i, 4]), _f4(q[i, 5])
        s, a, bb = _f4(q[i, 6]), _f4(q[i, 7]), _f4(q[i, 8])
        gx, gy, sat = _f4(q[i, 9]), _f4(q[i, 10]), _f4(q[i, 11])
        # pixel footprint in the mark frame (template.aperture)
        bu, mu = max(abs(a00), abs(a01)), min(abs(a00), abs(a01))
        bv, mv = max(abs(a10), abs(a11)), min(abs(a10), abs(a11))
        s_len = np.sqrt(s * s + _TWELFTH)
        invL = _ONE / s_len
        dsl = s / s_len
        Su = np.sqrt(s * s + mu * mu * _TWELFTH)
        Sv = np.sqrt(s * s + mv * mv * _TWELFTH)
        invu, invv = _ONE / Su, _ONE / Sv
        hbu, hbv = _HALF * bu, _HALF * bv
        ibu, ibv = _ONE / bu, _ONE / bv
        for j in range(npx):
            x = X[i, j]
            y = Y[i, j]
            dx = x - cx
            dy = y - cy
            u = a00 * dx + a01 * dy
            v = a10 * dx + a11 * dy
            Lu, Lu_t, Lu_s = _box(u, hL, invL)
            Lv, Lv_t, Lv_s = _box(v, hL, invL)
            Lu_s *= dsl
            Lv_s *= dsl
            pu, tu, su = _pixel_box(u, hW, hbu, invu)
            Wu, Wu_t, Wu_s = pu * Su * ibu, tu * ibu, su * ibu * s * invu
            pv, tv, sv = _pixel_box(v, hW, hbv, invv)
            Wv, Wv_t, Wv_s = pv * Sv * ibv, tv * ibv, sv * ibv * s * invv
            t_ = Lu * Wv + Wu * Lv - Wu * Wv
            tu_ = Lu_t * Wv + Wu_t * Lv - Wu_t * Wv
            tv_ = Lu * Wv_t + Wu * Lv_t - Wu * Wv_t
            ts_ = Lu_s * Wv + Lu * Wv_s + Wu_s * Lv + Wu * Lv_s - Wu_s * Wv - Wu * Wv_s
            if alpha != _ONE:  # the mark's opacity (MarkShape.evaluate)
                t_ *= alpha
                tu_ *= alpha
                tv_ *= alpha
                ts_ *= alpha
            qs = Qs[i, j]
            bg = S[i, j] + gx * x + gy * y + sat * qs
            b = bb - bg
            M[i, j] = a + bg + b * t_
            T[i, j] = t_
            Tu[i, j] = tu_
            Tv[i, j] = tv_
            U[i, j] = u
            V[i, j] = v
            bu_ = b * tu_
            bv_ = b * tv_
            om = _ONE - t_
            J[i, j, 0] = -(bu_ * a00 + bv_ * a10)
            J[i, j, 1] = -(bu_ * a01 + bv_ * a11)
            J[i, j, 2] = bu_ * dx
            J[i, j, 3] = bu_ * dy
            J[i, j, 4] = bv_ * dx
            J[i, j, 5] = bv_ * dy
            J[i, j, 6] = b * ts_
            J[i, j, 7] = _ONE
            J[i, j, 8] = t_
            J[i, j, 9] = x * om
            J[i, j, 10] = y * om
            J[i, j, 11] = qs * om


def cross_model(p, data, shape):
    """Model, template and Jacobian of N crosses at parameters ``p`` (N, 12) (lsm's order).

    ``data`` is lsm's gathered tuple ``(X, Y, G, valid, S, Wp, Q, Cc)``. Returns
    ``(M, T, Tu, Tv, u, v, J)``: model grey values, blurred cross and its derivatives along
    the mark frame's u and v, the pixels' mark-frame coordinates (all (N, P) float32) and the
    Jacobian (N, P, 12) float32 -- as ``lsm._geom`` and ``lsm._assemble`` give them.
    """
    X, Y = data[0], data[1]
    n, npx = X.shape
    q = np.ascontiguousarray(p, np.float32)
    out = [np.empty((n, npx), np.float32) for _ in range(6)]
    J = np.empty((n, npx, 12), np.float32)
    _kernel(np.ascontiguousarray(X), np.ascontiguousarray(Y), np.ascontiguousarray(data[4]),
            np.ascontiguousarray(data[6]), q, _f4(shape.length), _f4(shape.width),
            _f4(shape.opacity), *out, J)
    M, T, Tu, Tv, u, v = out
    return M, T, Tu, Tv, u, v, J



@njit(fastmath=True, cache=True, nogil=True)
def _weigh(G, M, valid, Wp, Cc, S, X, Y, Qs, q, pb, robust, R, WR, W, J, g, rss, wsum):
    # (fastmath: the order of the float64 sums is free; the MAD's element is picked exactly)
    n, npx = X.shape
    K = J.shape[2]
    buf = np.empty(npx, np.float32)
    gg = np.empty(K)
    for i in range(n):
        # residuals, censoring (a grey value at the end of the range that the model passes
        # carries nothing), the MAD of the valid residuals and the mean background
        nv = 0
        sbg = 0.0
        for j in range(npx):
            if valid[i, j]:
                r = G[i, j] - M[i, j]
                c = Cc[i, j]
                if (c > 0 and M[i, j] >= G[i, j]) or (c < 0 and M[i, j] <= G[i, j]):
                    r = _ZERO
                R[i, j] = r
                buf[nv] = abs(r)
                nv += 1
                sbg += S[i, j] + q[i, 9] * X[i, j] + q[i, 10] * Y[i, j] + q[i, 11] * Qs[i, j]
            else:
                R[i, j] = _ZERO
        inv_c = 0.0
        if robust:
            med = 0.0
            if nv > 0:
                med = float(np.partition(buf[:nv], nv // 2)[nv // 2])
            scale = max(1.4826 * med, 1e-9)
            contrast = pb[i] - sbg / max(float(nv), 1e-6)
            scale = max(scale, 0.01 * abs(contrast) + 1e-4)
            inv_c = 1.0 / (4.685 * scale)
        for a in range(K):
            gg[a] = 0.0
        ss = 0.0
        sw_ = 0.0
        for j in range(npx):
            if not valid[i, j]:
                WR[i, j] = _ZERO
                W[i, j] = _ZERO
                for a in range(K):
                    J[i, j, a] = _ZERO
                continue
            r = R[i, j]
            if robust:
                t = r * inv_c
                wr = _f4((1.0 - t * t) ** 2) if abs(t) < 1.0 else _ZERO
            else:
                wr = _ONE
            WR[i, j] = wr
            c = Cc[i, j]
            cens = (c > 0 and M[i, j] >= G[i, j]) or (c < 0 and M[i, j] <= G[i, j])
            w = _ZERO if cens else wr * Wp[i, j]
            W[i, j] = w
            sw_ += w
            sw = np.sqrt(w)
            swr = float(sw * r)
            ss += float(w * r * r)
            for a in range(K):
                ja = J[i, j, a] * sw
                J[i, j, a] = ja
                gg[a] += ja * swr
        for a in range(K):
            g[i, a] = gg[a]
        rss[i] = ss
        wsum[i] = sw_


@njit(fastmath=True, cache=True, nogil=True)
def _influence(Ninv2, J, h):
    n, npx, K = J.shape
    for i in range(n):
        for j in range(npx):
            h0 = _ZERO
            h1 = _ZERO
            for a in range(K):
                h0 += Ninv2[i, 0, a] * J[i, j, a]
                h1 += Ninv2[i, 1, a] * J[i, j, a]
            h[i, 0, j] = h0
            h[i, 1, j] = h1


def weigh(p, data, M, J, robust):
    """The rest of one LSM step over N crosses in one compiled pass: residuals (censored
    grey values zeroed), robust weights (Tukey's biweight on the residuals over their scale,
    ``lsm._scale``; 1 without ``robust``), the pixel weights ``w`` (robust x prior, 0 where
    censored) and the weighted normal equations (float64) with ``J`` scaled by ``sqrt(w)`` in
    place -- what ``lsm._step`` and ``lsm._normal`` compute with NumPy, to float32 rounding.

    ``data`` is lsm's gathered tuple; ``M`` (N, P) the model, ``J`` (N, P, 12) its Jacobian
    (both from :func:`cross_model`). Returns ``(r, w_rob, w, Nm, g, wrr)``: (N, P) float32
    each, then (N, 12, 12), (N, 12) and (N,) float64 (``wrr`` = Sum w r^2); no parameter
    pinned.
    """
    X, Y, G, valid, S, Wp, Qs, Cc = data
    n, npx = X.shape
    R, WR, W = (np.empty((n, npx), np.float32) for _ in range(3))
    K = J.shape[2]
    g = np.empty((n, K))
    rss = np.empty(n)
    wsum = np.empty(n)
    q = np.ascontiguousarray(p, np.float32)
    pb = np.ascontiguousarray(p[:, 8], np.float64)
    c = np.ascontiguousarray
    _weigh(c(G), c(M), c(valid), c(Wp), c(Cc), c(S), c(X), c(Y), c(Qs), q, pb, bool(robust),
           R, WR, W, J, g, rss, wsum)
    # J^T J by BLAS (faster than a compiled loop over the 78 products)
    Nm = np.matmul(J.transpose(0, 2, 1), J).astype(float)
    return R, WR, W, Nm, g, rss, wsum


@njit(fastmath=False, cache=True, nogil=True)
def _scale_columns(J, b, ncol):
    n, npx, K = J.shape
    for i in range(n):
        for j in range(npx):
            s = b[i, j]
            for a in range(ncol):
                J[i, j, a] *= s


def scale_columns(J, b, ncol):
    """``J[..., :ncol] *= b[..., None]`` in place: the first ``ncol`` columns of the
    Jacobian ``J`` (N, P, K) float32 scaled by ``b`` (N, P) float32 per pixel (the initial
    step's contrast over the scene, ``lsm._step``), compiled: the same float32 products
    without NumPy's strided pass over the columns."""
    if (J.dtype == np.float32 and b.dtype == np.float32 and J.flags.c_contiguous
            and J.flags.writeable and b.shape == J.shape[:2]):
        _scale_columns(J, np.ascontiguousarray(b), int(ncol))
    else:
        J[..., :ncol] *= b[..., None]


def influence(Ninv, J):
    """The centre's influence on each weighted pixel, ``Ninv[:, 0:2, :] @ J^T`` (N, 2, P)
    float32, ``J`` the ``sqrt(w)``-scaled Jacobian (N, P, 12) of :func:`weigh`."""
    n, npx, _ = J.shape
    h = np.empty((n, 2, npx), np.float32)
    _influence(np.ascontiguousarray(Ninv[:, 0:2, :], np.float32), J, h)
    return h


@njit(fastmath=True, cache=True, nogil=True)
def _template(q, length, width, alpha, margin, T):
    n, h, w = T.shape
    hL = _HALF * length
    hW = _HALF * width
    for i in range(n):
        cx, cy = q[i, 0], q[i, 1]
        a00, a01, a10, a11 = q[i, 2], q[i, 3], q[i, 4], q[i, 5]
        s = q[i, 6]
        bu, mu = max(abs(a00), abs(a01)), min(abs(a00), abs(a01))
        bv, mv = max(abs(a10), abs(a11)), min(abs(a10), abs(a11))
        s_len = np.sqrt(s * s + _TWELFTH)
        invL = _ONE / s_len
        Su = np.sqrt(s * s + mu * mu * _TWELFTH)
        Sv = np.sqrt(s * s + mv * mv * _TWELFTH)
        invu, invv = _ONE / Su, _ONE / Sv
        hbu, hbv = _HALF * bu, _HALF * bv
        ibu, ibv = _ONE / bu, _ONE / bv
        ml = hL + margin[i]
        mw = hW + margin[i]
        for y in range(h):
            dy = _f4(y) - cy
            for x in range(w):
                dx = _f4(x) - cx
                u = a00 * dx + a01 * dy
                v = a10 * dx + a11 * dy
                au, av = abs(u), abs(v)
                if not ((au <= ml and av <= mw) or (av <= ml and au <= mw)):
                    T[i, y, x] = _ZERO
                    continue
                Lu = _box(u, hL, invL)[0]
                Lv = _box(v, hL, invL)[0]
                Wu = _pixel_box(u, hW, hbu, invu)[0] * Su * ibu
                Wv = _pixel_box(v, hW, hbv, invv)[0] * Sv * ibv
                t_ = Lu * Wv + Wu * Lv - Wu * Wv
                T[i, y, x] = t_ * alpha if alpha != _ONE else t_


def cross_template(shape, origin, c, A, s, hw, margin):
    """The blurred cross ``T`` (N, h, w) float32 of N patches (pixel system: ``origin`` each
    patch's [0, 0] pixel, centres ``c``, pixel -> mark-frame affines ``A``, blurs ``s``), as
    :meth:`MarkShape.evaluate` with :func:`softplot.marks.template.aperture` gives it, 0
    beyond ``margin`` (N,) px of the drawn bars (the template is below 1e-6 there)."""
    n = len(c)
    q = np.zeros((n, 7), np.float32)
    # the pixels relative to the patch origin, as lsm.patch_frame computes them
    q[:, 0:2] = (np.asarray(c, float) - origin).astype(np.float32)
    q[:, 2:6] = np.asarray(A, np.float32).reshape(n, 4)
    q[:, 6] = np.asarray(s, np.float32)
    T = np.empty((n,) + tuple(hw), np.float32)
    _template(q, _f4(shape.length), _f4(shape.width), _f4(shape.opacity),
              np.asarray(margin, np.float32), T)
    return T


@njit(fastmath=True, cache=True, nogil=True)
def _corr_sums(ix, iy, valid, R, H, K, out):
    n, npx = R.shape
    for q in range(n):
        gh = 0
        gw = 0
        for j in range(npx):
            if valid[q, j]:
                gh = max(gh, iy[q, j] + 1)
                gw = max(gw, ix[q, j] + 1)
        # dense grids, zero off the valid pixels and in a border of K; each row's span of
        # valid pixels
        G = np.zeros((4, gh + 2 * K, gw + 2 * K), np.float32)
        lo = np.full(gh, gw, np.int64)
        hi = np.zeros(gh, np.int64)
        for j in range(npx):
            if valid[q, j]:
                y = iy[q, j]
                x = ix[q, j]
                G[0, y + K, x + K] = R[q, j]
                G[1, y + K, x + K] = _ONE
                G[2, y + K, x + K] = H[q, 0, j]
                G[3, y + K, x + K] = H[q, 1, j]
                lo[y] = min(lo[y], x)
                hi[y] = max(hi[y], x + 1)
        Rg, Vg, Ag, Bg = G[0], G[1], G[2], G[3]
        # half the lags: the others by symmetry (c(-lag) = c(lag); the cross term enters
        # the covariance only as kxy(lag) + kxy(-lag), kept as its mean at both)
        for dy in range(K + 1):
            for dx in range(-K, K + 1):
                if dy == 0 and dx < 0:
                    continue
                srr = 0.0
                svv = 0.0
                sxx = 0.0
                syy = 0.0
                sxy = 0.0
                for y in range(gh):
                    # a row's sums in float32 (they vectorise), the rows' in float64
                    rr_ = _ZERO
                    vv_ = _ZERO
                    xx_ = _ZERO
                    yy_ = _ZERO
                    xy_ = _ZERO
                    a0 = lo[y] + K
                    m = hi[y] - lo[y]
                    r1 = Rg[y + K, a0 : a0 + m]
                    r2 = Rg[y + K + dy, a0 + dx : a0 + dx + m]
                    v1 = Vg[y + K, a0 : a0 + m]
                    v2 = Vg[y + K + dy, a0 + dx : a0 + dx + m]
                    p1 = Ag[y + K, a0 : a0 + m]
                    p2 = Ag[y + K + dy, a0 + dx : a0 + dx + m]
                    q1 = Bg[y + K, a0 : a0 + m]
                    q2 = Bg[y + K + dy, a0 + dx : a0 + dx + m]
                    for x in range(m):
                        rr_ += r1[x] * r2[x]
                        vv_ += v1[x] * v2[x]
                        xx_ += p1[x] * p2[x]
                        yy_ += q1[x] * q2[x]
                        xy_ += p1[x] * q2[x] + q1[x] * p2[x]
                    srr += rr_
                    svv += vv_
                    sxx += xx_
                    syy += yy_
                    sxy += xy_
                for (u, v) in ((K + dy, K + dx), (K - dy, K - dx)):
                    out[q, 0, u, v] = srr
                    out[q, 1, u, v] = svv
                    out[q, 2, u, v] = sxx
                    out[q, 3, u, v] = 0.5 * sxy
                    out[q, 4, u, v] = syy


def corr_sums(ix, iy, valid, R, H, K):
    """``Sum_i a_i b_{i+lag}`` over each mark's valid pixels at the lags -K..K (rows: y, cols:
    x) for the pairs (R, R), (1, 1), (h0, h0), (h0, h1), (h1, h1): (N, 5, 2K+1, 2K+1)
    float64 -- the correlations ``lsm._correlated_cov`` takes from FFTs, summed directly over
    the pixel pairs (for the few lags it uses, far fewer operations); of the pair (h0, h1)
    the mean of the lags +-lag (all the covariance takes of it). ``ix``, ``iy`` (N, P)
    int: the pixels' integer positions (>= 0 where valid); ``R`` (N, P) and ``H`` (N, 2, P)
    float32."""
    n = R.shape[0]
    out = np.empty((n, 5, 2 * K + 1, 2 * K + 1))
    c = np.ascontiguousarray
    _corr_sums(c(ix, np.int64), c(iy, np.int64), c(valid), c(R, np.float32),
               c(H, np.float32), int(K), out)
    return out


@njit(cache=True, nogil=True)
def _support(patches, cl, A, hl, hw, keep, counts):
    n, h, w = patches.shape
    for i in range(n):
        cx, cy = cl[i, 0], cl[i, 1]
        a00, a01, a10, a11 = A[i, 0], A[i, 1], A[i, 2], A[i, 3]
        c = 0
        for y in range(h):
            dy = _f4(y) - cy
            for x in range(w):
                dx = _f4(x) - cx
                au = abs(a00 * dx + a01 * dy)
                av = abs(a10 * dx + a11 * dy)
                k = (((au <= hl) and (av <= hw)) or ((av <= hl) and (au <= hw))) and \
                    np.isfinite(patches[i, y, x])
                keep[i, y * w + x] = k
                c += k
        counts[i] = c


@njit(cache=True, nogil=True)
def _compact(keep, counts, off, patches, bg, wt, sat, lo, hi, has_bg, has_wt, has_sat,
             has_clip, X, Y, G, V, S, Wp, Q, Cc):
    n, h, w = patches.shape
    P = X.shape[1]
    for i in range(n):
        # the kept pixels first, then the others (the order of a stable sort on ~keep)
        k = 0
        for t in range(2):
            for f in range(h * w):
                if k >= P:
                    break
                if keep[i, f] != (t == 0):
                    continue
                y = f // w
                x = f - y * w
                X[i, k] = off[i, 0] + _f4(x)
                Y[i, k] = off[i, 1] + _f4(y)
                ok = t == 0
                V[i, k] = ok
                g = patches[i, y, x] if ok else _ZERO
                G[i, k] = g
                S[i, k] = bg[i, y, x] if (ok and has_bg) else _ZERO
                Wp[i, k] = (wt[i, y, x] if has_wt else _ONE) if ok else _ZERO
                Q[i, k] = sat[i, y, x] if (ok and has_sat) else _ZERO
                c = _ZERO
                if ok and has_clip:
                    if g <= lo:
                        c = -_ONE
                    elif g >= hi:
                        c = _ONE
                Cc[i, k] = c
                k += 1


def gather_cross(patches, origin, ref, c, A, length, width, margin, background=None,
                 weight=None, sat_bg=None, clip=None):
    """``lsm._gather`` for crosses in two compiled passes (the same arrays): each mark's
    pixels within ``margin`` px of its cross, in patch order, padded to the largest count."""
    n, h, w = patches.shape
    f4 = np.float32
    cl = (np.asarray(c, float) - origin).astype(f4)
    Af = np.ascontiguousarray(np.asarray(A, f4).reshape(n, 4))
    hl = f4(0.5 * length + margin)
    hw = f4(0.5 * width + margin)
    pt = np.ascontiguousarray(patches, f4)
    keep = np.empty((n, h * w), np.bool_)
    counts = np.empty(n, np.int64)
    _support(pt, cl, Af, hl, hw, keep, counts)
    P = max(int(counts.max()) if n else 1, 1)
    off = (origin - ref).astype(f4)
    X, Y, G, S, Wp, Q, Cc = (np.empty((n, P), f4) for _ in range(7))
    V = np.empty((n, P), np.bool_)
    z = np.zeros((1, 1, 1), f4)

    def arr(a):
        return z if a is None else np.ascontiguousarray(a, f4)

    lo, hi = (f4(clip[0] + 1e-6), f4(clip[1] - 1e-6)) if clip is not None else (f4(0), f4(0))
    _compact(keep, counts, off, pt, arr(background), arr(weight), arr(sat_bg), lo, hi,
             background is not None, weight is not None, sat_bg is not None, clip is not None,
             X, Y, G, V, S, Wp, Q, Cc)
    return X, Y, G, V, S, Wp, Q, Cc


@njit(inline="always")
def _pivot(A, c, n):
    """Partial pivoting: the row ``piv`` in ``c .. n-1`` with the largest ``|A[piv, c]|``, and
    that magnitude."""
    piv = c
    best = abs(A[c, c])
    for a in range(c + 1, n):
        if abs(A[a, c]) > best:
            best = abs(A[a, c])
            piv = a
    return piv, best


@njit(fastmath=False, cache=True, nogil=True)
def _invert(Nm, g, active, Ninv, ok):
    n, K, _ = Nm.shape
    A = np.empty((K, 2 * K))
    for i in range(n):
        # inactive parameters pinned (row, column 0, diagonal 1, no gradient); a parameter
        # without data too; a touch of Levenberg-Marquardt damping
        for a in range(K):
            for b in range(K):
                A[a, b] = Nm[i, a, b] if (active[a] and active[b]) else 0.0
                A[a, K + b] = 1.0 if a == b else 0.0
            if not active[a]:
                A[a, a] = 1.0
                g[i, a] = 0.0
            if not A[a, a] > 0:
                A[a, a] = 1.0
            A[a, a] *= 1.0 + 1e-6
        # Gauss-Jordan with partial pivoting
        good = True
        for c in range(K):
            piv, best = _pivot(A, c, K)
            if not best > 0 or not np.isfinite(best):
                good = False
                break
            if piv != c:
                for b in range(2 * K):
                    t = A[c, b]
                    A[c, b] = A[piv, b]
                    A[piv, b] = t
            d = 1.0 / A[c, c]
            for b in range(2 * K):
                A[c, b] *= d
            for a in range(K):
                if a != c:
                    f = A[a, c]
                    if f != 0.0:
                        for b in range(2 * K):
                            A[a, b] -= f * A[c, b]
        ok[i] = good
        for a in range(K):
            for b in range(K):
                Ninv[i, a, b] = A[a, K + b]


@njit(fastmath=False, cache=True, nogil=True)
def _advance(Ninv, g, wsum, nact, wrr, p, dc, sig, cov, s0sq):
    n, K, _ = Ninv.shape
    dp = np.empty(K)
    for i in range(n):
        for a in range(K):
            t = 0.0
            for b in range(K):
                t += Ninv[i, a, b] * g[i, b]
            dp[a] = t if np.isfinite(t) else 0.0
        s0 = wrr[i] / max(wsum[i] - nact, 1.0)
        s0sq[i] = s0
        for a in range(2):
            for b in range(2):
                cov[i, a, b] = Ninv[i, a, b] * s0
        sig[i] = np.sqrt(max(0.5 * (cov[i, 0, 0] + cov[i, 1, 1]), 0.0))
        # step limits: centre 1.5 px, shape 5 %, blur within a sane range
        d = np.hypot(dp[0], dp[1])
        k = min(1.0, 1.5 / max(d, 1e-12))
        dp[0] *= k
        dp[1] *= k
        settled = abs(dp[6]) < 0.01
        for a in range(2, 6):
            dp[a] = min(max(dp[a], -0.05), 0.05)
            settled = settled and abs(dp[a]) < 2e-3
        for a in range(K):
            p[i, a] += dp[a]
        p[i, 6] = min(max(p[i, 6], 0.05), 25.0)
        dc[i] = d if settled else max(d, 1.0)


def invert(Nm, g, active):
    """The inverse of N crosses' normal equations ``Nm`` (N, 12, 12) with the parameters
    not ``active`` pinned (and ``g`` zeroed there, in place), a parameter without data
    pinned, and a damping of 1e-6 on the diagonal, as ``lsm._step`` sets them up; by
    Gauss-Jordan elimination (compiled). Returns ``(Ninv, ok)``; ``ok`` False where a
    pivot vanished (the caller then takes the pseudo-inverse)."""
    n, K, _ = Nm.shape
    Ninv = np.empty_like(Nm)
    ok = np.empty(n, np.bool_)
    _invert(Nm, g, np.ascontiguousarray(active, np.bool_), Ninv, ok)
    return Ninv, ok


def advance(Ninv, g, wsum, wrr, nact, p):
    """The rest of ``lsm._step`` after the inversion, compiled: the update ``Ninv g`` (0
    where not finite), the residual variance ``wrr / (wsum - nact)``, the centre's
    covariance and sigma, the step limits, ``p`` advanced in place and the centre update
    (at least 1 px where the shape or blur still moves). Returns ``(dc, sig, cov, s0sq)``."""
    n = len(p)
    dc, sig, s0sq = np.empty(n), np.empty(n), np.empty(n)
    cov = np.empty((n, 2, 2))
    _advance(Ninv, g, wsum, float(nact), wrr, p, dc, sig, cov, s0sq)
    return dc, sig, cov, s0sq


@njit(fastmath=True, cache=True, nogil=True)
def _jtj(J, Jt, Nm, npx):
    # J^T J of one mark over its first ``npx`` pixels (the rest are padding, J = 0: left
    # out, the sums do not depend on the padding, i.e. on which marks share the gather);
    # float32 sums, as BLAS's product in weigh, by rows of J^T
    K = J.shape[2]
    for j in range(npx):
        for a in range(K):
            Jt[a, j] = J[0, j, a]
    for a in range(K):
        for b in range(a, K):
            s = _ZERO
            for j in range(npx):
                s += Jt[a, j] * Jt[b, j]
            Nm[0, a, b] = s
            Nm[0, b, a] = s


@njit(fastmath=False, cache=True, nogil=True)
def _fine(X, Y, G, valid, S, Wp, Qs, Cc, p, active, length, width, alpha, robust, rows, it0,
          max_iter, tol, conv, M, T, Tu, Tv, U, V, R, WR, W, cov, s0sq, h, done, last_it,
          fail):
    n, npx = X.shape
    K = p.shape[1]
    nact = 0
    for a in range(K):
        if active[a]:
            nact += 1
    # one mark's buffers (its rows copied once: contiguous for the step kernels)
    x = np.empty((1, npx), np.float32)
    y = np.empty((1, npx), np.float32)
    gr = np.empty((1, npx), np.float32)
    sb = np.empty((1, npx), np.float32)
    wp = np.empty((1, npx), np.float32)
    qs = np.empty((1, npx), np.float32)
    cc = np.empty((1, npx), np.float32)
    m1 = np.empty((1, npx), np.float32)
    t1 = np.empty((1, npx), np.float32)
    tu = np.empty((1, npx), np.float32)
    tv = np.empty((1, npx), np.float32)
    u1 = np.empty((1, npx), np.float32)
    v1 = np.empty((1, npx), np.float32)
    r1 = np.empty((1, npx), np.float32)
    wr1 = np.empty((1, npx), np.float32)
    w1 = np.empty((1, npx), np.float32)
    vd = np.empty((1, npx), np.bool_)
    J = np.empty((1, npx, K), np.float32)
    q = np.empty((1, K), np.float32)
    pb = np.empty(1)
    g = np.empty((1, K))
    rss, wsum, dc, sig, s0 = np.empty(1), np.empty(1), np.empty(1), np.empty(1), np.empty(1)
    Nm = np.empty((1, K, K))
    Ninv = np.empty((1, K, K))
    N2 = np.empty((1, 2, K), np.float32)
    cv = np.empty((1, 2, 2))
    h1 = np.empty((1, 2, npx), np.float32)
    ok = np.empty(1, np.bool_)
    Jt = np.empty((K, npx), np.float32)
    for i in rows:
        x[0], y[0], gr[0], sb[0], wp[0], qs[0], cc[0] = X[i], Y[i], G[i], S[i], Wp[i], Qs[i], Cc[i]
        vd[0] = valid[i]
        nv = 0  # the pixels up to the last valid one
        for j in range(npx):
            if vd[0, j]:
                nv = j + 1
        pi = p[i:i + 1]
        took = False  # a step completed: its state is in the buffers
        for it in range(it0, max_iter + 1):
            rob = robust and it > 1
            for a in range(K):
                q[0, a] = np.float32(pi[0, a])
            pb[0] = pi[0, 8]
            _kernel(x, y, sb, qs, q, length, width, alpha, m1, t1, tu, tv, u1, v1, J)
            _weigh(gr, m1, vd, wp, cc, sb, x, y, qs, q, pb, rob, r1, wr1, w1, J, g, rss, wsum)
            _jtj(J, Jt, Nm, nv)
            _invert(Nm, g, active, Ninv, ok)
            if not ok[0]:  # a vanishing pivot: this step and the rest by NumPy (which
                fail[i] = it  # write the state)
                took = False
                break
            _advance(Ninv, g, wsum, nact, rss, pi, dc, sig, cv, s0)
            took = True
            last_it[i] = it
            if (rob and it > 2) or not robust:
                sg = 0.0 if np.isnan(sig[0]) else sig[0]
                if dc[0] < max(tol, conv * sg):
                    done[i] = True
                    break
        if took:  # the state of the last step, its influence from its own J and inverse
            for a in range(2):
                for b in range(K):
                    N2[0, a, b] = np.float32(Ninv[0, a, b])
            _influence(N2, J, h1)
            M[i], T[i], Tu[i], Tv[i], U[i], V[i] = m1[0], t1[0], tu[0], tv[0], u1[0], v1[0]
            R[i], WR[i], W[i], h[i] = r1[0], wr1[0], w1[0], h1[0]
            cov[i] = cv[0]
            s0sq[i] = s0[0]


def fine_steps(p, data, length, width, active, robust, rows, it0, max_iter, tol, conv, last,
               converged, opacity=1.0):
    """The fine stage of ``lsm.lsm`` for the crosses ``rows`` from its step ``it0`` on, one
    mark at a time in one compiled pass: each step :func:`cross_model`, :func:`weigh`,
    :func:`invert`, :func:`advance` and :func:`influence` as ``lsm._step`` calls them (the
    normal equations summed in float64), the robust weights from step 2, the convergence
    test ``lsm._converged`` (``conv`` x sigma or ``tol``) from step 3 (every step without
    ``robust``), up to ``max_iter``. Updates ``p`` (N, 12), ``last`` (lsm's state of each
    mark's last step) and ``converged`` in place. Returns ``(last_it, fail)`` (N,) int: the
    last step taken (0: none) and, where a pivot vanished, the step to be taken again by
    NumPy (else -1). ``opacity``: the cross's (:attr:`MarkShape.opacity`)."""
    from softplot import runtime

    n = len(p)
    last_it = np.zeros(n, np.int64)
    fail = np.full(n, -1, np.int64)
    c = np.ascontiguousarray
    X, Y, G, valid, S, Wp, Qs, Cc = (c(a) for a in data)
    L = last
    act = c(active, np.bool_)
    rows = c(rows, np.int64)

    def run(rw):
        _fine(X, Y, G, valid, S, Wp, Qs, Cc, p, act, _f4(length), _f4(width), _f4(opacity),
              bool(robust), rw,
              int(it0), int(max_iter), float(tol), float(conv), L["M"], L["T"], L["Tu"],
              L["Tv"], L["u"], L["v"], L["r"], L["w_rob"], L["w"], L["cov"], L["s0sq"],
              L["h"], converged, last_it, fail)

    # each mark steps alone over its own row of the gathered arrays (its buffers, its sums
    # over its own pixels) and writes only its own rows: the marks in two halves on two
    # threads, where one is idle (runtime.share), give every value of the whole to the bit
    if len(rows) >= SHARE_ROWS and runtime.idle_threads():
        h = len(rows) // 2
        runtime.share(run, [rows[:h], rows[h:]])
    else:
        run(rows)
    return last_it, fail


#: :func:`fine_steps` shares its marks with an idle thread from this many on
SHARE_ROWS = 2


@njit(fastmath=True, cache=True, nogil=True)
def _half_arms(q, X, Y, S, Qs, valid, Tu, Tv, U, V, R, W, width, s0sq, d, var, ms):
    n, npx = X.shape
    for i in range(n):
        den = np.zeros(4)
        num = np.zeros(4)
        rr = np.zeros(4)
        ww = np.zeros(4)
        for j in range(npx):
            u = U[i, j]
            v = V[i, j]
            au, av = abs(u), abs(v)
            if max(au, av) <= width:
                continue  # the centre square: no half-arm
            if au >= av:
                k = 0 if u >= 0 else 2
            else:
                k = 1 if v >= 0 else 3
            w = W[i, j] if valid[i, j] else _ZERO
            b = q[i, 8] - (S[i, j] + q[i, 9] * X[i, j] + q[i, 10] * Y[i, j]
                           + q[i, 11] * Qs[i, j])
            jn = b * (Tv[i, j] if (k == 0 or k == 2) else Tu[i, j])
            r = R[i, j]
            den[k] += w * jn * jn
            num[k] += w * jn * r
            rr[k] += w * r * r
            ww[k] += w
        for k in range(4):
            if den[k] > 0:
                d[i, k] = num[k] / den[k]
                var[i, k] = s0sq[i] / den[k]
            else:
                d[i, k] = 0.0
                var[i, k] = np.inf
            ms[i, k] = rr[k] / max(ww[k], 1e-9)


def half_arms(p, data, last, width):
    """``lsm._half_arm_shifts`` for crosses in one compiled pass: ``(d, var, ms)`` (N, 4)."""
    X, Y, _, valid, S, _, Qs, _ = data
    n = len(p)
    d, var, ms = np.empty((n, 4)), np.empty((n, 4)), np.empty((n, 4))
    c = np.ascontiguousarray
    _half_arms(c(p, np.float32), c(X), c(Y), c(S), c(Qs), c(valid), c(last["Tu"]),
               c(last["Tv"]), c(last["u"]), c(last["v"]), c(last["r"]), c(last["w"]),
               np.float32(width), np.maximum(last["s0sq"], 1e-30), d, var, ms)
    return d, var, ms

@njit(fastmath=False, cache=True, nogil=True)
def _chol_above(Nn, L, tol, A):
    # Cholesky pivots of Nn[:L, :L] - tol I all positive (neighbours._smallest_eig_above)
    for a in range(L):
        for b in range(L):
            A[a, b] = Nn[a, b]
        A[a, a] -= tol
    for c in range(L):
        piv = A[c, c]
        if not piv > 0.0:
            return False
        for a in range(c + 1, L):
            f = A[a, c] / piv
            for b in range(c + 1, L):
                A[a, b] -= f * A[c, b]
    return True


@njit(fastmath=False, cache=True, nogil=True)
def _local_solve(D, w, vals, tol, out, level):
    R, k, C = vals.shape
    Q, _, p = D.shape
    N0 = np.empty((p, p))
    Nn = np.empty((p, p))
    A = np.empty((p, p + C))
    W = np.empty((p, p))
    sq = np.empty(p)
    Dw = np.empty((k, p))
    for r in range(R):
        Dq = D[r % Q]
        for i in range(k):
            for a in range(p):
                Dw[i, a] = Dq[i, a] * w[r, i]
        # each sum over the neighbours in the order i = 0 .. k - 1, four sums at a time
        # (independent chains; the last group's spare ones repeat column p - 1)
        for a in range(p):
            for b in range(a, p, 4):
                b1, b2, b3 = min(b + 1, p - 1), min(b + 2, p - 1), min(b + 3, p - 1)
                t0 = t1 = t2 = t3 = 0.0
                for i in range(k):
                    x = Dw[i, a]
                    t0 += x * Dq[i, b]
                    t1 += x * Dq[i, b1]
                    t2 += x * Dq[i, b2]
                    t3 += x * Dq[i, b3]
                N0[a, b] = t0
                N0[b1, a] = N0[a, b1] = t1
                N0[b2, a] = N0[a, b2] = t2
                N0[b3, a] = N0[a, b3] = t3
                N0[b, a] = t0
        for a in range(p):  # the diagonal's roots once (p roots, not 2 p^2)
            sq[a] = np.sqrt(max(N0[a, a], 1e-300))
        for a in range(p):
            for b in range(p):
                Nn[a, b] = N0[a, b] / (sq[a] * sq[b])
        # the highest degree its neighbours determine (terms 3 plane, 6, 10; 0 none)
        if _chol_above(Nn, p, tol, W):
            lev = p
        else:
            lev = 0
            for L in (3, 6, 10):
                if L >= p or not _chol_above(Nn, L, tol, W):
                    break
                lev = L
        level[r] = lev
        use = max(lev, 3)
        # the normal equations of the terms used (the others pinned at 0), a touch of ridge
        for a in range(p):
            for b in range(p):
                A[a, b] = N0[a, b] if (a < use and b < use) else 0.0
            A[a, a] += 1e-9 if a < use else 1.0 + 1e-9
            for c in range(C):
                A[a, p + c] = 0.0
        # the right-hand sides, as the normal equations' sums: four at a time
        for c in range(C):
            for a in range(0, use, 4):
                a1, a2, a3 = min(a + 1, use - 1), min(a + 2, use - 1), min(a + 3, use - 1)
                t0 = t1 = t2 = t3 = 0.0
                for i in range(k):
                    v = vals[r, i, c]
                    t0 += Dw[i, a] * v
                    t1 += Dw[i, a1] * v
                    t2 += Dw[i, a2] * v
                    t3 += Dw[i, a3] * v
                A[a, p + c] = t0
                A[a1, p + c] = t1
                A[a2, p + c] = t2
                A[a3, p + c] = t3
        # Gaussian elimination with partial pivoting, then back substitution
        for c in range(p):
            piv, best = _pivot(A, c, p)
            if piv != c:
                for b in range(p + C):
                    t = A[c, b]
                    A[c, b] = A[piv, b]
                    A[piv, b] = t
            for a in range(c + 1, p):
                f = A[a, c] / A[c, c]
                if f != 0.0:
                    for b in range(c, p + C):
                        A[a, b] -= f * A[c, b]
        for c in range(C):
            for a in range(p - 1, -1, -1):
                t = A[a, p + c]
                for b in range(a + 1, p):
                    t -= A[a, b] * A[b, p + c]
                A[a, p + c] = t / A[a, a]
            out[r, c] = A[0, p + c]


def local_solve(D, w, vals, tol=1e-6):
    """The constant terms of weighted local polynomial fits, compiled: for each row ``r``
    the design ``D[r % Q]`` ((Q, k, p) in units of the neighbour spacing), the weights
    ``w[r]`` (R, k) and the values ``vals[r]`` (R, k, C); the degree of each fit is the
    highest whose normalised normal equations have no eigenvalue below ``tol`` (none, 3, 6
    or 10 terms; at least the plane's terms are solved), as
    :func:`softplot.marks.neighbours.local_fit` chooses it. Returns ``(c0, level)``:
    (R, C) the fitted value at each query point and (R,) int the terms used (0: none
    determined)."""
    from softplot.runtime import concurrent, thread_map

    vals = np.ascontiguousarray(vals, np.float64)
    D = np.ascontiguousarray(D, np.float64)
    w = np.ascontiguousarray(w, np.float64)
    R, _, C = vals.shape
    Q = D.shape[0]
    out = np.empty((R, C))
    level = np.empty(R, np.int64)
    # a large batch in two parts on the process's threads (the kernel releases the GIL; each
    # row is solved alone, so the figures do not depend on the split): the parts start at a
    # row whose design is D[0] (a multiple of Q), or split the designs with the rows
    h = 0
    if R >= SPLIT_ROWS and concurrent():
        h = R // 2 if Q == R else (R // Q // 2) * Q if R % Q == 0 else 0

    def run(ab):
        a, b = ab
        _local_solve(D[a:b] if Q == R else D, w[a:b], vals[a:b], float(tol), out[a:b],
                     level[a:b])

    thread_map(run, [(0, h), (h, R)] if h > 0 else [(0, R)])
    return out, level


#: rows from which :func:`local_solve` solves a batch in two parts on the process's threads
#: (a variance factor's 24 draws over a grid of 121 crosses: 2904 rows, about 3 ms)
SPLIT_ROWS = 512


_LOADED = False
_LOAD_LOCK = threading.Lock()
#: other modules' compiled passes, compiled (or loaded) by :func:`load` too (:func:`on_load`)
_WARM: list = []


def on_load(warm):
    """Have :func:`load` call ``warm()`` (a module's compilation of its own compiled passes
    on a tiny input); returns ``warm`` (a decorator)."""
    _WARM.append(warm)
    return warm


def load() -> bool:
    """Compile (or load from numba's cache) the kernel now, on a tiny input; returns whether
    it can be used (:data:`AVAILABLE`). The JIT runtime (LLVM) and the machine code are a
    fixed cost of the process, like a library's code; benchmarks call this before they
    measure a scan. Should numba fail to compile it here (an unsupported platform, a broken
    cache), :data:`AVAILABLE` turns False with a warning and LSM uses its NumPy path."""
    global AVAILABLE, _LOADED
    if not AVAILABLE or _LOADED:
        return AVAILABLE
    with _LOAD_LOCK:  # the threads of one detection may ask at once
        if _LOADED or not AVAILABLE:
            return AVAILABLE
        from softplot.marks.template import MarkShape

        z = np.zeros((1, 1), np.float32)
        p = np.zeros((1, 12))
        p[0, 2] = p[0, 5] = 1.0
        p[0, 6] = 1.0
        try:
            data = (z, z, z, z > 0, z, z, z, z)
            M, _, _, _, _, _, J = cross_model(p, data, MarkShape("cross", length=5.0,
                                                                  width=1.0))
            *_, Nm, g, wrr, wsum = weigh(p, data, M, J, True)
            Ninv, _ = invert(Nm, g, np.ones(12, bool))
            half_arms(p, data, dict(Tu=z, Tv=z, u=z, v=z, r=z, w=z, s0sq=np.ones(1)), 1.0)
            advance(Ninv, g, wsum, wrr, 12, p.copy())
            influence(np.eye(12)[None], J)
            scale_columns(J, np.ones(J.shape[:2], np.float32), 7)
            corr_sums(np.zeros((1, 1), np.int64), np.zeros((1, 1), np.int64), z > -1, z,
                      np.zeros((1, 2, 1), np.float32), 1)
            gather_cross(np.zeros((1, 3, 3), np.float32), np.zeros((1, 2)), np.zeros((1, 2)),
                         np.ones((1, 2)), np.eye(2)[None], 2.0, 1.0, 1.0, np.zeros((1, 3, 3)),
                         np.ones((1, 3, 3)), np.zeros((1, 3, 3)), (0.0, 1.0))
            cross_template(MarkShape("cross", length=5.0, width=1.0), np.zeros((1, 2)),
                           np.zeros((1, 2)), np.eye(2)[None], np.ones(1), (3, 3), np.ones(1))
            local_solve(np.ones((1, 3, 3)), np.ones((1, 3)), np.ones((1, 3, 1)))
            state = {k: np.zeros((1, 1), np.float32) for k in ("M", "T", "Tu", "Tv", "u",
                                                                 "v", "r", "w_rob", "w")}
            state.update(cov=np.zeros((1, 2, 2)), s0sq=np.zeros(1),
                         h=np.zeros((1, 2, 1), np.float32))
            fine_steps(p.copy(), data, 5.0, 1.0, np.ones(12, bool), True,
                       np.zeros(1, np.int64), 1, 1, 5e-4, 0.5, state, np.zeros(1, bool))
            for warm in _WARM:
                warm()
        except Exception as exc:  # noqa: BLE001 - any failure of the compiler: NumPy path
            warnings.warn(f"softplot: compiled LSM kernel unavailable ({type(exc).__name__}: "
                          f"{exc}); using NumPy", RuntimeWarning, stacklevel=2)
            AVAILABLE = False
        _LOADED = True
    return AVAILABLE


def ready() -> bool:
    """Whether LSM should call :func:`cross_model` (compiled and working)."""
    return AVAILABLE and (_LOADED or load())
