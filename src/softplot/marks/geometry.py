"""Mark geometry from the scan: the arm length and line width of the reseau crosses as imaged.

A certificate's ``arm_length_mm`` and ``line_width_mm`` are nominal (often absent, sometimes
wrong by a factor of two); the least-squares measurement needs the crosses' real size (a
template longer than the real arms models background as mark). This stage measures both on
the crosses the lattice found, before the measuring stage, from one-dimensional profiles in
each cross's mark frame (u along film x, v along film -y, nominal px: film mm x px per mm):

* along each bar: the mean over a band across the bar, fitted with a blurred box
  ``b + c (Phi((u - a1)/s) - Phi((u - a2)/s))``: tip-to-tip length ``a2 - a1`` and the blur
  ``s`` of the scan (the bar's ends are step edges);
* across each bar, between its ends and away from the other bar: the mean profile, fitted
  with a box of width ``w`` blurred by that ``s``.

The profiles of the bars (each normalised by its own contrast) are combined sample by sample
by their median, and the scan's values are the fits to that median profile: a thin line
under a wide blur has little contrast per sample, and the median ignores the few bars that
scene content, a fault or a larger centre cross make different. Each bar is also fitted
alone: the spread reported is the robust standard deviation (1.4826 x MAD) of those fits, and
their median must agree with the median profile's length (else the profiles follow scene
content along the bars and the starting guess stands). Bars without contrast (one-armed
crosses, crosses under a dark sky) are left out.

With numba (:func:`softplot.marks.kernels.ready`) the profiles' samples and their
Levenberg-Marquardt fits run compiled, bar by bar (:func:`_bilinear_at`, :func:`_lm_boxes`):
the samples are NumPy's to the bit, the fits take NumPy's steps with the sums in another
order (the same values to about 1e-12 px; a fit along a flat valley of its cost, e.g. the
width of a line hardly wider than the blur, stops within 1e-6 px of NumPy's).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.special import erf, ndtr

from softplot.marks import kernels
from softplot.marks.common import median1, median_rows
from softplot.marks.template import MarkShape
from softplot.runtime import concurrent, thread_map

__all__ = ["MarkGeometry", "estimate_geometry", "width_candidates", "ARM_RANGE", "WIDTH_RANGE"]

#: admissible true arm length, times the starting guess (certificate or default)
ARM_RANGE = (0.3, 3.0)
#: admissible true line width, times the starting guess
WIDTH_RANGE = (0.35, 3.0)
#: crosses profiled (the best-scoring ones)
MAX_MARKS = 10
#: a line is resolved (its width measured, not taken from the guess) when at least this many
#: times the blur sigma wide
WIDTH_RESOLVED = 1.5
#: the profiles measure the arm length (line width) when their robust spread over the
#: crosses is at most this fraction of it
CONSISTENT = (0.1, 0.5)
#: profiles and guess agree on the arm length within this fraction: the guess stands
ARM_AGREE = 0.05
#: the median of the bars' own arm lengths agrees with their median profile's within
#: ``CONSISTENT[0]`` of it or this many px (short arms), else the profiles are not the marks'
ARM_AGREE_PX = 2.0
#: a line wider than this fraction of the arm length is not a cross's: not measured
MAX_WIDTH = 0.35
#: profiles and guess agree on the line width within these ratios
WIDTH_AGREE = (0.8, 1.25)


@dataclass(frozen=True)
class MarkGeometry:
    """The reseau crosses' size as imaged (mark frame, nominal px = film mm x px per mm).

    ``arm_px`` tip-to-tip length of a bar, ``width_px`` line width; ``*_spread_px`` their
    robust standard deviation over the crosses (NaN with fewer than 3 estimates); ``n`` the
    bars measured; ``source`` "scan" (measured), "certificate" (the starting guess kept:
    too few crosses could be profiled) or "fit" (the arm chosen by the least-squares fits of
    the best crosses where the profiles left it in doubt).
    """

    arm_px: float
    width_px: float
    arm_spread_px: float
    width_spread_px: float
    n: int
    source: str
    #: the scan's blur sigma (px) from the bars' ends (with the profiles' interpolation)
    blur_px: float = float("nan")
    #: the crosses' centres relative to the positions profiled (mark frame px, u and v):
    #: the median midpoint of each bar's ends along it, (0, 0) where fewer than 3 bars of
    #: an axis agree (a prediction off along the arms, e.g. a lattice of peaks on long arms)
    offset_px: tuple = (0.0, 0.0)

    def with_width(self, width_px: float) -> "MarkGeometry":
        """The same geometry with the line width the measuring stage settled on."""
        return replace(self, width_px=float(width_px))

    def with_arm(self, arm_px: float) -> "MarkGeometry":
        """The same geometry with the arm length the measuring stage settled on (``source``
        "fit": the least-squares fit of the best crosses chose it)."""
        return replace(self, arm_px=float(arm_px), source="fit")

    def shape(self) -> MarkShape:
        """The cross template of this geometry (mark frame px)."""
        return MarkShape("cross", length=float(self.arm_px), width=float(self.width_px))

    def to_json(self, px_per_mm: float) -> dict:
        """The ``mark_geometry`` key of a detection's JSON (film mm)."""
        def mm(v):
            return None if not np.isfinite(v) else round(float(v) / px_per_mm, 5)

        return {
            "arm_length_mm": mm(self.arm_px),
            "line_width_mm": mm(self.width_px),
            "spread": {"arm_length_mm": mm(self.arm_spread_px),
                       "line_width_mm": mm(self.width_spread_px)},
            "n": int(self.n),
            "source": self.source,
        }


def _robust_std(v: np.ndarray) -> float:
    if len(v) < 3:
        return float("nan")
    return float(1.4826 * median1(np.abs(v - median1(v))))


def _box(x, b, c, a1, a2, s):
    return b + c * (ndtr((x - a1) / s) - ndtr((x - a2) / s))


def _box_jac(x, b, c, a1, a2, s, cols=5):
    """Model and derivatives by (b, c, a1, a2, s): (..., n) and (..., n, cols), the
    parameters broadcast against the samples ``x`` (e.g. (K, 1) each for K profiles); the
    columns past the fifth (``cols`` > 5) are left for the caller to fill (written in place:
    no stacked copy)."""
    z1, z2 = (x - a1) / s, (x - a2) / s
    P = ndtr(z1) - ndtr(z2)
    g1 = np.exp(-0.5 * z1 * z1) / np.sqrt(2.0 * np.pi)
    g2 = np.exp(-0.5 * z2 * z2) / np.sqrt(2.0 * np.pi)
    f = b + c * P
    J = np.empty(np.broadcast_shapes(f.shape, np.shape(s)) + (cols,))
    J[..., 0] = 1.0
    J[..., 1] = P
    J[..., 2] = -c * g1 / s
    J[..., 3] = c * g2 / s
    J[..., 4] = -c * (z1 * g1 - z2 * g2) / s
    return f, J


def _lm(resid_jac, p, lo, hi, iterations=30):
    """Levenberg-Marquardt with box bounds (clipped steps) on K small problems at once, each
    fitted as it would be alone (its own damping, its own stop).

    ``p`` (K, n) starting values, ``lo``, ``hi`` bounds (broadcast to (K, n));
    ``resid_jac(q, k)`` the residuals (len(k), m) and Jacobians (len(k), m, n) of the problems
    ``k`` (indices into K) at the parameters ``q`` (len(k), n). Returns (K, n): the
    parameters, a row of NaN where a fit does not converge to finite values."""
    p = np.array(p, float)
    K, n = p.shape
    lo, hi = np.broadcast_to(lo, p.shape), np.broadcast_to(hi, p.shape)
    r, J = resid_jac(p, np.arange(K))
    cost = np.einsum("km,km->k", r, r)
    lam = np.full(K, 1e-3)
    active = np.ones(K, bool)
    failed = np.zeros(K, bool)
    diag = np.arange(n)
    for _ in range(iterations):
        a = np.where(active)[0]
        if a.size == 0:
            break
        Jt = J[a].transpose(0, 2, 1)
        M = Jt @ J[a]
        g = (Jt @ r[a][..., None])[..., 0]
        M[:, diag, diag] += lam[a, None] * (M[:, diag, diag] + 1e-12)
        step, bad = _solve(M, -g)
        failed[a[bad]] = True
        active[a[bad]] = False
        a, step = a[~bad], step[~bad]
        q = np.clip(p[a] + step, lo[a], hi[a])
        r2, J2 = resid_jac(q, a)
        c2 = np.einsum("km,km->k", r2, r2)
        ok = np.isfinite(c2) & (c2 < cost[a])
        done = ok & (cost[a] - c2 < 1e-10 * cost[a])
        k = a[ok]
        p[k], r[k], J[k], cost[k] = q[ok], r2[ok], J2[ok], c2[ok]
        lam[k] *= 0.3
        k = a[~ok]
        lam[k] *= 10.0
        active[a[done]] = False
        active[k[lam[k] > 1e8]] = False
    p[failed | ~np.isfinite(p).all(1)] = np.nan
    return p


def _solve(M, b):
    """``M x = b`` for a stack of systems (K, n, n), (K, n): ``x`` and whether each ``M`` is
    singular (its row of ``x`` NaN)."""
    singular = np.zeros(len(b), bool)
    try:
        return np.linalg.solve(M, b[..., None])[..., 0], singular
    except np.linalg.LinAlgError:
        out = np.full(b.shape, np.nan)
        for k in range(len(b)):
            try:
                out[k] = np.linalg.solve(M[k], b[k])
            except np.linalg.LinAlgError:
                singular[k] = True
        return out, singular


#: the compiled fits' models (:func:`_lm_boxes`): the blurred box along a bar with the other
#: bar's cross-section (:func:`_fit_along`), a box of free width and centre across a bar at a
#: given blur (:func:`_fit_across`)
_ALONG, _ACROSS = 0, 1
_SQRT1_2 = math.sqrt(0.5)
_SQRT_2PI = math.sqrt(2.0 * math.pi)
#: |z| beyond which the compiled fits take the normal CDF as 0 or 1 and its density as 0
_ZCUT = 9.0

njit = kernels.njit


@njit(inline="always")
def _ndtr(a):
    # the standard normal CDF as scipy.special.ndtr computes it (from erf near 0, erfc beyond)
    x = a * _SQRT1_2
    z = abs(x)
    if z < _SQRT1_2:
        return 0.5 + 0.5 * math.erf(x)
    y = 0.5 * math.erfc(z)
    return 1.0 - y if x > 0 else y


@njit(inline="always")
def _cdf_pdf(z):
    # ndtr(z) and the standard normal density; beyond |z| = _ZCUT exactly 0 or 1 and 0 (the
    # CDF rounds to 1 there, and the tails are below 1e-18)
    if z >= _ZCUT:
        return 1.0, 0.0
    if z <= -_ZCUT:
        return 0.0, 0.0
    return _ndtr(z), math.exp(-0.5 * z * z) / _SQRT_2PI


@njit(cache=True, nogil=True)
def _box_model(kind, x, data, q, h, s_fix, r, J):
    # residuals r (m,) and Jacobian J (m, n) of one profile ``data`` (m,) sampled at x (m,)
    # at the parameters q: kind _ALONG (b, c, a1, a2, s, k) as _fit_along's rj, _ACROSS
    # (b, c, v0, w) at the blur s_fix as _fit_across's rj; returns the cost r.r
    b, c = q[0], q[1]
    if kind == _ALONG:
        a1, a2, s = q[2], q[3], q[4]
    else:
        a1, a2, s = q[2] - 0.5 * q[3], q[2] + 0.5 * q[3], s_fix
    cost = 0.0
    for i in range(x.size):
        z1, z2 = (x[i] - a1) / s, (x[i] - a2) / s
        P1, g1 = _cdf_pdf(z1)
        P2, g2 = _cdf_pdf(z2)
        P = P1 - P2
        f = b + c * P
        d1, d2 = -c * g1 / s, c * g2 / s
        J[i, 0] = 1.0
        J[i, 1] = P
        if kind == _ALONG:
            k = q[5]
            zp, zm = (x[i] + h) / s, (x[i] - h) / s
            Pp, gp = _cdf_pdf(zp)
            Pm, gm = _cdf_pdf(zm)
            L = Pp - Pm
            J[i, 1] += k * L
            J[i, 2] = d1
            J[i, 3] = d2
            J[i, 4] = -c * (z1 * g1 - z2 * g2) / s - c * k * (zp * gp - zm * gm) / s
            J[i, 5] = c * L
            f += c * k * L
        else:
            J[i, 2] = d1 + d2
            J[i, 3] = 0.5 * (d2 - d1)
        r[i] = f - data[i]
        cost += r[i] * r[i]
    return cost


@njit(cache=True, nogil=True)
def _lu_solve(M, g, x):
    # x = -M^-1 g by Gaussian elimination with partial pivoting (M, g overwritten); False
    # where a pivot is exactly 0 (as LAPACK's gesv reports a singular M)
    n = g.size
    for c in range(n):
        piv = c
        for a in range(c + 1, n):
            if abs(M[a, c]) > abs(M[piv, c]):
                piv = a
        if M[piv, c] == 0.0:
            return False
        if piv != c:
            for b in range(n):
                M[c, b], M[piv, b] = M[piv, b], M[c, b]
            g[c], g[piv] = g[piv], g[c]
        for a in range(c + 1, n):
            f = M[a, c] / M[c, c]
            for b in range(c, n):
                M[a, b] -= f * M[c, b]
            g[a] -= f * g[c]
    for a in range(n - 1, -1, -1):
        t = -g[a]
        for b in range(a + 1, n):
            t -= M[a, b] * x[b]
        x[a] = t / M[a, a]
    return True


@njit(cache=True, nogil=True)
def _lm_boxes(kind, x, data, p, lo, hi, h, s_fix, iterations, out):
    # _lm's Levenberg-Marquardt, problem by problem, on the model _box_model(kind): out (K, n)
    K, n = p.shape
    m = x.size
    r, r2 = np.empty(m), np.empty(m)
    J, J2 = np.empty((m, n)), np.empty((m, n))
    M, g = np.empty((n, n)), np.empty(n)
    step, q = np.empty(n), np.empty(n)
    for k in range(K):
        pk = p[k].copy()
        cost = _box_model(kind, x, data[k], pk, h, s_fix, r, J)
        lam = 1e-3
        failed = False
        for _ in range(iterations):
            for a in range(n):
                for b in range(a, n):
                    t = 0.0
                    for i in range(m):
                        t += J[i, a] * J[i, b]
                    M[a, b] = t
                    M[b, a] = t
                t = 0.0
                for i in range(m):
                    t += J[i, a] * r[i]
                g[a] = t
            for a in range(n):
                M[a, a] += lam * (M[a, a] + 1e-12)
            if not _lu_solve(M, g, step):
                failed = True
                break
            for a in range(n):
                q[a] = min(max(pk[a] + step[a], lo[k, a]), hi[k, a])
            c2 = _box_model(kind, x, data[k], q, h, s_fix, r2, J2)
            if np.isfinite(c2) and c2 < cost:
                done = cost - c2 < 1e-10 * cost
                pk[:] = q
                r, r2 = r2, r
                J, J2 = J2, J
                cost = c2
                lam *= 0.3
                if done:
                    break
            else:
                lam *= 10.0
                if lam > 1e8:
                    break
        ok = not failed
        for a in range(n):
            ok = ok and np.isfinite(pk[a])
        for a in range(n):
            out[k, a] = pk[a] if ok else np.nan


def _lm_compiled(kind, x, data, p, lo, hi, h=0.0, s_fix=1.0, iterations=30):
    """:func:`_lm` on the blurred box ``kind`` (:data:`_ALONG`, :data:`_ACROSS`), compiled:
    each problem fitted alone in one pass (the same steps, damping and stops; the sums in
    another order, so the values agree to rounding, not to the bit). ``x`` (m,) the samples
    (mark frame px), ``data`` (K, m) the profiles, ``p`` (K, n) the starting values, ``lo``,
    ``hi`` the bounds (broadcast to (K, n)); ``h`` the other bar's half width (px, along),
    ``s_fix`` the blur (px, across). Returns (K, n), NaN rows as :func:`_lm`'s."""
    p = np.array(p, float)
    out = np.empty_like(p)
    lo, hi = (np.ascontiguousarray(np.broadcast_to(np.asarray(b, float), p.shape))
              for b in (lo, hi))
    x = np.ascontiguousarray(x, float)
    data = np.ascontiguousarray(data, float)

    def part(k):  # problems k (a slice) alone: each problem's fit is its own
        _lm_boxes(kind, x, data[k], p[k], lo[k], hi[k], float(h), float(s_fix),
                  int(iterations), out[k])

    # two halves on the process's threads (the pass releases the GIL)
    K = len(p)
    half = K // 2 if K >= LM_SPLIT and concurrent() else K
    thread_map(part, [slice(0, half), slice(half, K)] if half < K else [slice(0, K)])
    return out


#: problems from which :func:`_lm_compiled` fits two halves on the process's threads
LM_SPLIT = 8


def _compiled(flag) -> bool:
    """Whether the profiles' fits and samples run compiled: ``flag``, or where it is None,
    whether the compiled kernels work (:func:`softplot.marks.kernels.ready`)."""
    return kernels.ready() if flag is None else bool(flag)


@kernels.on_load
def warm() -> None:
    """Compile (or load from numba's cache) the profiles' compiled fits on a tiny input
    (:func:`softplot.marks.kernels.load` calls it)."""
    u = np.linspace(-4.0, 4.0, 9)
    one = np.exp(-u * u)[None]
    _lm_compiled(_ALONG, u, one, [[0.0, 1.0, -1.0, 1.0, 1.0, 0.0]], -np.inf, np.inf, h=0.5,
                 iterations=1)
    _lm_compiled(_ACROSS, u, one, [[0.0, 1.0, 0.0, 1.0]], -np.inf, np.inf, iterations=1)
    _bilinear(np.zeros((2, 2), np.float32), u, u, compiled=True)


def _along_start(u: np.ndarray, p: np.ndarray, lo: float, hi: float, centre: float):
    """Starting level, contrast and ends ``(b0, c0, a1, a2)`` of the blurred box along a bar
    (profile ``p`` sampled at ``u``, mark frame px), or None where the profile shows no bar
    of an admissible length (``lo``, ``hi`` its least and greatest half length)."""
    du = float(u[1] - u[0])
    ps = uniform_filter1d(p, max(1, int(round(1.0 / du))))
    b0 = float(median1(np.concatenate([ps[: len(ps) // 8], ps[-len(ps) // 8:]])))
    # the arm's level beside the crossing (where a thin blurred line is darker)
    au = np.abs(u)
    c_mid = float(median1(ps[au <= max(lo, 2.0)])) - b0
    ring = (au <= max(lo, 2.0) + centre) & (au >= centre)
    c0 = float(median1(ps[ring])) - b0 if ring.sum() >= 2 else c_mid
    if not c0 > 0.3 * c_mid:  # the arms are shorter than the crossing's reach
        c0 = c_mid
    if not c0 > 0:
        return None
    half = ps - b0 > 0.5 * c0
    i0 = int(np.argmin(np.abs(u)))
    if not half[i0]:
        return None
    r = i0
    while r + 1 < len(u) and half[r + 1]:
        r += 1
    left = i0
    while left - 1 >= 0 and half[left - 1]:
        left -= 1
    a1, a2 = float(u[left]), float(u[r])
    if a2 - a1 < 2.0 * lo * 0.8 or a2 - a1 > 2.0 * hi:
        return None
    return b0, c0, a1, a2


def _fit_along(u: np.ndarray, profiles, lo: float, hi: float, centre: float = 0.0,
               s0: float = 1.0, width: float = 1.0, *, compiled: bool | None = None) -> list:
    """Blurred box along each bar (``profiles`` (K, len(u)), sampled at ``u``, mark frame
    px), fitted in one batch: per profile (a1, a2, s, c) or None. Where the bars cross, a
    thin blurred line is darker than along its arms (the other bar's blur adds): the model
    adds the other bar's cross-section (a line of ``width`` px, blurred alike) with a free
    level, and the arm's starting level is read beyond ``centre`` px of the middle. ``s0``:
    the starting blur (px); ``compiled`` whether the fit runs compiled (:func:`_compiled`).
    """
    profiles = np.asarray(profiles, float).reshape(-1, len(u))
    starts = [_along_start(u, p, lo, hi, centre) for p in profiles]
    k_ok = np.array([i for i, st in enumerate(starts) if st is not None], int)
    out: list = [None] * len(profiles)
    if k_ok.size == 0:
        return out
    h = 0.5 * max(width, 0.05)
    # the crossing's excess over the arm, per unit arm level, is 1 / P0 - 1 (P0: a line's
    # blurred peak over its full level); at most that of a line half as wide as ``width``
    # at the starting blur
    s_i = float(np.clip(s0, 0.3, 10.0))
    k_max = 1.0 / max(float(erf(0.5 * h / (s_i * np.sqrt(2.0)))), 1e-3) - 1.0
    data = profiles[k_ok]

    def rj(q, k):
        qc = q[:, :, None]  # (k, 6, 1): each parameter against the samples
        f, J = _box_jac(u, *np.moveaxis(qc[:, :5], 1, 0), cols=6)
        # the other bar where it crosses: its cross-section, blurred alike, at k x the level
        zp, zm = (u + h) / qc[:, 4], (u - h) / qc[:, 4]
        L = ndtr(zp) - ndtr(zm)
        gp = np.exp(-0.5 * zp * zp) / np.sqrt(2.0 * np.pi)
        gm = np.exp(-0.5 * zm * zm) / np.sqrt(2.0 * np.pi)
        J[..., 5] = qc[:, 1] * L
        J[..., 1] += qc[:, 5] * L
        J[..., 4] += -qc[:, 1] * qc[:, 5] * (zp * gp - zm * gm) / qc[:, 4]
        return f + qc[:, 1] * qc[:, 5] * L - data[k], J

    p0 = [[b0, c0, a1, a2, s_i, 0.0] for b0, c0, a1, a2 in (starts[i] for i in k_ok)]
    lo_q, hi_q = [-np.inf, 0.0, u[0], 0.0, 0.3, 0.0], [np.inf, np.inf, 0.0, u[-1], 10.0, k_max]
    q = (_lm_compiled(_ALONG, u, data, p0, lo_q, hi_q, h=h) if _compiled(compiled)
         else _lm(rj, p0, lo_q, hi_q))
    for i, qi in zip(k_ok, q, strict=True):
        if np.isfinite(qi).all():
            b, c, a1, a2, s, _ = qi
            out[i] = (a1, a2, s, c)
    return out


def _fit_across(v: np.ndarray, profiles, s: float, w0: float, *,
                compiled: bool | None = None) -> list:
    """Box of width w blurred by ``s`` across each bar (``profiles`` (K, len(v)), sampled
    at ``v``, mark frame px), fitted in one batch: per profile (w, centre, c) or None;
    ``compiled`` whether the fit runs compiled (:func:`_compiled`)."""
    profiles = np.asarray(profiles, float).reshape(-1, len(v))
    out: list = [None] * len(profiles)
    p0, k_ok = [], []
    for i, q in enumerate(profiles):
        b0 = float(median1(np.concatenate([q[: len(q) // 6], q[-len(q) // 6:]])))
        j = int(np.argmax(q))
        c0 = float(q[j] - b0)
        if not c0 > 0:
            continue
        area = float(np.sum(q - b0) * (v[1] - v[0]))
        w_init = float(np.clip(area / c0, 0.3 * w0, 4.0 * w0))
        p0.append([b0, c0, float(v[j]), w_init])
        k_ok.append(i)
    if not k_ok:
        return out
    data = profiles[k_ok]

    def rj(p, k):
        pc = p[:, :, None]  # (k, 4, 1): each parameter against the samples
        b, c, v0, w = pc[:, 0], pc[:, 1], pc[:, 2], pc[:, 3]
        f, J = _box_jac(v, b, c, v0 - 0.5 * w, v0 + 0.5 * w, s)
        Jp = np.stack([J[..., 0], J[..., 1], J[..., 2] + J[..., 3],
                       0.5 * (J[..., 3] - J[..., 2])], -1)
        return f - data[k], Jp

    lo_p, hi_p = [-np.inf, 0.0, v[0], 0.05], [np.inf, np.inf, v[-1], 8.0 * w0 + 4.0]
    p = (_lm_compiled(_ACROSS, v, data, p0, lo_p, hi_p, s_fix=s) if _compiled(compiled)
         else _lm(rj, p0, lo_p, hi_p))
    for i, pi in zip(k_ok, p, strict=True):
        if np.isfinite(pi).all():
            b, c, v0, w = pi
            out[i] = (w, v0, c)
    return out


def estimate_geometry(grey_at, xy: np.ndarray, A: np.ndarray, guess: MarkShape, sign: int,
                      *, pitch_px: float, score: np.ndarray | None = None,
                      max_marks: int = MAX_MARKS) -> MarkGeometry:
    """Arm length and line width of the crosses at ``xy`` as imaged.

    Parameters
    ----------
    grey_at : callable
        ``grey_at((rows, cols))`` -> float grey of that pixel window (e.g. ``Scan.grey``).
    xy : (K, 2)
        Approximate cross centres (pixel system, within a few line widths).
    A : (K, 2, 2)
        Pixel -> mark-frame affine of each cross (mark frame: u along film x, v along film -y,
        nominal px).
    guess : MarkShape
        Starting guess (certificate or default): the search covers :data:`ARM_RANGE` and
        :data:`WIDTH_RANGE` times it.
    sign : int
        +1 bright marks, -1 dark marks.
    pitch_px : float
        Smallest reseau pitch (mark-frame px): the profiles stay within half of it.
    score : (K,), optional
        Coarse scores: the best ``max_marks`` crosses are profiled.

    Returns
    -------
    MarkGeometry
        The guess itself (``source`` "certificate") when fewer than 2 bars could be profiled.
    """
    xy = np.asarray(xy, float).reshape(-1, 2)
    A = np.asarray(A, float).reshape(-1, 2, 2)
    order = np.argsort(-np.asarray(score)) if score is not None else np.arange(len(xy))
    order = order[:max_marks]
    L0, w0 = float(guess.length), float(guess.width)
    H = min(0.5 * ARM_RANGE[1] * L0 + 4.0 * w0 + 6.0, 0.45 * pitch_px)
    V = max(1.5 * WIDTH_RANGE[1] * w0 + 3.0, 6.0) + 3.0
    du = 0.5 if ARM_RANGE[0] * L0 < 30 else 1.0
    dv = float(np.clip(w0 / 4.0, 0.25, 1.0))
    u = np.arange(-H, H + 1e-9, du)
    v = np.arange(-V, V + 1e-9, dv)
    lo_half = 0.5 * ARM_RANGE[0] * L0
    hi_half = 0.5 * ARM_RANGE[1] * L0 + 2.0 * w0
    centre = min(1.5 * w0 + 2.0, 0.6 * lo_half)
    grid = _sample_grid(u, v)
    # each cross's profiles its own: sampled on the process's threads (the samples are
    # compiled and release the GIL)
    bars = thread_map(lambda i: _bar_profiles(grey_at, xy[i], A[i], u, v, grid, w0, lo_half,
                                              sign, H, V), order)
    axis = [k for pair in bars if pair is not None for k, b in enumerate(pair) if b is not None]
    bars = [b for pair in bars if pair is not None for b in pair if b is not None]
    if bars:
        # the blurred line's half width at half maximum across the bars: the blur it
        # implies (a Gaussian's is 1.18 sigma) starts the fits, and the crossing, darker
        # over about that reach plus two sigmas, is left out of them
        hw = float(median1(np.array([b[3] for b in bars], float)))
        s_g = max(hw / 1.18, 0.5)
        centre = max(centre, hw + 1.5 * s_g)
    else:
        s_g = 1.0
    if len(bars) >= 2:
        c = np.array([b[2] for b in bars])
        # bars without contrast (one-armed crosses, crosses under a dark sky) are left out
        c_min = 0.3 * median1(c)
        axis = [k for k, ck in zip(axis, c, strict=True) if ck >= c_min]
        bars = [b for b, ck in zip(bars, c, strict=True) if ck >= c_min]
    if len(bars) < 2:
        return MarkGeometry(L0, w0, float("nan"), float("nan"), len(bars), "certificate")
    # one fit to the median of the bars' normalised profiles: robust to the few bars that
    # scene content, a fault or a larger centre cross make different, and far less noisy
    # than each bar alone (a thin line under a wide blur has little contrast per sample)
    # and each bar alone (the spread over the scan), in one batch
    fits = _fit_along(u, [_median_profile([b[0] / b[2] for b in bars])]
                      + [b[0] / b[2] for b in bars], lo_half, hi_half, centre=centre,
                      s0=s_g, width=w0)
    fl, one = fits[0], fits[1:]
    if fl is None:
        return MarkGeometry(L0, w0, float("nan"), float("nan"), len(bars), "certificate")
    a1, a2, sb, _ = fl
    arm = a2 - a1
    arms_a = np.array([f[1] - f[0] for f in one if f is not None])
    sa = _robust_std(arms_a)
    offset = _centre_offset(one, axis, arm)
    if len(arms_a) < 3 or not abs(float(median1(arms_a)) - arm) <= max(
            CONSISTENT[0] * arm, ARM_AGREE_PX):
        # the bars alone do not agree with their median profile: scene content along the
        # bars, not the marks
        return MarkGeometry(L0, w0, sa, float("nan"), len(bars), "certificate")
    # across each bar, between its ends and away from the other bar (where the bars are
    # too short for that, beside the other bar only)
    sel = (u > a1 + 1.5 * sb) & (u < a2 - 1.5 * sb) & (np.abs(u - 0.5 * (a1 + a2))
                                                        > 0.5 * w0 + 1.5 * sb)
    if sel.sum() < 3:
        sel = (u > a1 + 0.5 * sb) & (u < a2 - 0.5 * sb) & (np.abs(u) > 0.5 * w0 + sb)
    w, sw = float("nan"), float("nan")
    if sel.sum() >= 3:
        acr = [b[1](sel).mean(1) for b in bars]
        fits = _fit_across(v, acr, sb, w0)
        widths_a = np.array([f[0] for f in fits if f is not None])
        sw = _robust_std(widths_a)
        # the bars' across profiles centred (each on its own fitted centre) and normalised
        fm = []
        for q, f in zip(acr, fits, strict=True):
            if f is not None and f[2] > 0:
                b0 = float(median1(np.concatenate([q[: len(q) // 6], q[-len(q) // 6:]])))
                fm.append(np.interp(v + f[1], v, (q - b0) / f[2]))
        fw = _fit_across(v, _median_profile(fm), sb, w0)[0] if len(fm) >= 2 else None
        if fw is not None:
            w = float(fw[0])
        if (len(widths_a) >= 3 and not sw <= CONSISTENT[1] * w) or not w <= MAX_WIDTH * arm:
            w = float("nan")  # the width is not measured: the guess stands
    if abs(arm / L0 - 1.0) <= ARM_AGREE:
        # within what a busy scene's profiles miss by: the guess stands
        arm = L0
    return MarkGeometry(float(arm), w, sa, sw, len(bars), "scan", blur_px=float(sb),
                        offset_px=offset)


def _centre_offset(fits, axis, arm) -> tuple:
    """The crosses' centre relative to the profiled positions (mark frame px, u and v): per
    axis the median midpoint of that axis's bars' fitted ends (``fits`` of
    :func:`_fit_along`, ``axis`` 0 for bars along u, 1 along v), where at least 3 bars agree
    on it within a tenth of the arm ``arm`` (px); else 0."""
    out = [0.0, 0.0]
    for k in (0, 1):
        mid = np.array([0.5 * (f[0] + f[1]) for f, a in zip(fits, axis, strict=True)
                        if f is not None and a == k])
        if len(mid) >= 3 and _robust_std(mid) <= CONSISTENT[0] * arm:
            out[k] = float(median1(mid))
    return (out[0], out[1])


def _median_profile(profiles: list) -> np.ndarray:
    """The sample-wise median of equally sampled profiles."""
    return median_rows(np.stack(profiles, 1))


def _bar_profiles(grey_at, xy, A, u, v, grid, w0, lo_half, sign, H, V):
    """The two bars' profiles of the cross at ``xy`` (pixel system; ``A`` its pixel ->
    mark-frame affine; ``grid`` the samples' mark-frame positions, :func:`_sample_grid`):
    for each bar ``(along, columns, contrast, half width)``, ``along`` the
    mean over a band across the bar (as long as ``u``, background removed), ``columns(sel)``
    the samples (len(v), sel.sum()) of the columns ``sel`` (bool, len(u)) with the bar along
    ``u``, ``contrast`` the bar's level over the
    background near the centre, ``half width`` the blurred line's at half maximum (px);
    None for a bar without contrast, None for both where the profiles leave the scan."""
    Ai = np.linalg.inv(A)  # mark frame -> pixel offsets
    reach = np.abs(Ai).sum(1) * (H + V) + 3.0
    x0, y0 = xy
    c0 = int(np.floor(x0 - reach[0]))
    r0 = int(np.floor(y0 - reach[1]))
    c1 = int(np.ceil(x0 + reach[0])) + 1
    r1 = int(np.ceil(y0 + reach[1])) + 1
    try:
        win = grey_at((slice(max(r0, 0), max(r1, 0)), slice(max(c0, 0), max(c1, 0))))
    except (ValueError, IndexError):
        return None
    if win.size == 0 or win.shape != (r1 - r0, c1 - c0):
        return None  # the profiles leave the scan
    win = sign * np.asarray(win, np.float32)
    dv = float(v[1] - v[0])
    # where both bars (0: the bar along u, film x; 1: along v) are sampled, each
    # (len(v), len(u)): rows across; only the samples used are interpolated
    px = Ai @ grid
    rows = (px[:, 1] + y0 - r0).reshape(2, len(v), len(u))
    cols = (px[:, 0] + x0 - c0).reshape(2, len(v), len(u))
    inner = np.abs(u) <= max(lo_half, 3.0)
    core = _bilinear(win, rows[:, :, inner], cols[:, :, inner])
    out = []
    for bar in (0, 1):
        # the bar's position across (coarse centres are off by up to a few px)
        # (the other bar adds the same to every v within its width: no bias)
        q = uniform_filter1d(core[bar].mean(1), max(1, int(round(0.5 * w0 / dv))))
        j = int(np.argmax(q))
        vc = float(v[j])
        # the band across the bar: the blurred line's half maximum (a thin line under a
        # wide blur is several pixels wide), at least the drawn line
        qb = float(median1(np.concatenate([q[: len(q) // 6], q[-len(q) // 6:]])))
        half = q - qb > 0.5 * (q[j] - qb)
        lo_j, hi_j = j, j
        while lo_j > 0 and half[lo_j - 1]:
            lo_j -= 1
        while hi_j + 1 < len(q) and half[hi_j + 1]:
            hi_j += 1
        bw = float(np.clip(0.5 * (v[hi_j] - v[lo_j]), max(0.5 * w0, 0.75), 0.5 * w0 + 4.0))
        band = np.abs(v - vc) <= bw
        p = _bilinear(win, rows[bar][band], cols[bar][band]).mean(0)
        n8 = max(len(p) // 8, 1)
        b0 = float(median1(np.concatenate([p[:n8], p[-n8:]])))
        c = float(median1(p[np.abs(u) <= max(lo_half, 2.0)])) - b0

        def columns(sel, r=rows[bar], k=cols[bar]):
            return _bilinear(win, r[:, sel], k[:, sel])

        out.append((p - b0, columns, c, 0.5 * (v[hi_j] - v[lo_j])) if c > 0 else None)
    return out


def _sample_grid(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The mark-frame samples (px) of both bars' profiles, (2, 2, len(v) x len(u)): bar 0
    along u (rows across it along v), bar 1 along v; coordinates (u, v) on the second axis."""
    uu, vv = np.meshgrid(u, v, indexing="xy")
    return np.stack([np.stack([uu, vv]), np.stack([vv, uu])]).reshape(2, 2, -1)


def _bilinear(img: np.ndarray, rows: np.ndarray, cols: np.ndarray, *,
              compiled: bool | None = None) -> np.ndarray:
    """Linear interpolation of ``img`` (2-D, at least 2 x 2) at fractional ``rows``,
    ``cols`` (pixel system of ``img``), beyond its edge the edge's value (what
    ``scipy.ndimage.map_coordinates(img, [rows, cols], order=1, mode="nearest")`` gives);
    in ``img``'s dtype, laid out in memory as ``rows`` (as NumPy's arithmetic lays it out:
    a later sum over an axis adds in the same order). Compiled (``compiled``,
    :func:`_compiled`): the same operations in one pass, the same values to the bit
    (:func:`_bilinear_numpy`)."""
    rows, cols = np.asarray(rows), np.asarray(cols)
    if not _compiled(compiled) or not _same_layout(rows, cols):
        return _bilinear_numpy(img, rows, cols)
    out = np.empty_like(rows, dtype=img.dtype)  # NumPy's layout of the result (order "K")
    flat = out.ravel(order="K")
    if not np.shares_memory(flat, out):  # a layout no flat view follows: NumPy's pass
        return _bilinear_numpy(img, rows, cols)
    _bilinear_at(np.ascontiguousarray(img), rows.ravel(order="K"), cols.ravel(order="K"),
                 flat)
    return out


def _same_layout(rows: np.ndarray, cols: np.ndarray) -> bool:
    """Whether ``rows`` and ``cols`` are float64 arrays of one shape and one memory layout
    (the compiled :func:`_bilinear` pairs their elements in memory order)."""
    return (rows.dtype == cols.dtype == np.float64 and rows.shape == cols.shape
            and rows.strides == cols.strides)


@njit(cache=True, nogil=True)
def _bilinear_at(img, rows, cols, out):
    # _bilinear_numpy's arithmetic sample by sample (float64 weights, the result rounded to
    # img's dtype): rows, cols (m,) pixel system of img, out (m,)
    h, w = img.shape
    for n in range(rows.size):
        r = min(max(rows[n], 0.0), h - 1.0)
        c = min(max(cols[n], 0.0), w - 1.0)
        i = min(int(r), h - 2)
        j = min(int(c), w - 2)
        tr, tc = r - i, c - j
        top = img[i, j] * (1.0 - tc) + img[i, j + 1] * tc
        bottom = img[i + 1, j] * (1.0 - tc) + img[i + 1, j + 1] * tc
        out[n] = top * (1.0 - tr) + bottom * tr


def _bilinear_numpy(img: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """:func:`_bilinear` with NumPy (the reference of the compiled pass)."""
    h, w = img.shape
    r = np.clip(rows, 0.0, h - 1.0)
    c = np.clip(cols, 0.0, w - 1.0)
    i = np.minimum(r.astype(np.intp), h - 2)
    j = np.minimum(c.astype(np.intp), w - 2)
    tr, tc = r - i, c - j
    f = img.ravel()
    k = i * w + j
    top = f[k] * (1.0 - tc) + f[k + 1] * tc
    bottom = f[k + w] * (1.0 - tc) + f[k + w + 1] * tc
    return (top * (1.0 - tr) + bottom * tr).astype(img.dtype)


def width_candidates(geom: MarkGeometry, guess_px: float) -> list[float]:
    """Line widths (px) worth a least-squares trial, the guess first.

    The profiles measure a resolved line (at least :data:`WIDTH_RESOLVED` blur sigmas wide)
    well on a clean scan, but a busy scene biases them, and a line narrower than the blur has
    the blur's profile whatever its width. So the guess stands unless the profiles contradict
    it (a ratio beyond :data:`WIDTH_AGREE`); then the measured width and steps of sqrt(2)
    from the guess towards it (or, for an unresolved line, towards the blur) are tried too,
    and the least-squares fit of the crosses decides (:func:`best_width`).
    """
    w0 = float(guess_px)
    if geom.source not in ("scan", "fit"):
        return [w0]
    w = float(geom.width_px)
    if not np.isfinite(w):
        return [w0]
    if np.isfinite(geom.blur_px) and w < WIDTH_RESOLVED * geom.blur_px:
        w = max(w, 0.5 * geom.blur_px)
    r = w / w0
    if WIDTH_AGREE[0] <= r <= WIDTH_AGREE[1]:
        return [w0]
    steps = int(min(np.ceil(abs(np.log(r)) / np.log(np.sqrt(2.0))), 4))
    out = [w0] + [w0 * r ** (k / steps) for k in range(1, steps + 1)]
    return [float(np.clip(x, WIDTH_RANGE[0] * w0, WIDTH_RANGE[1] * w0)) for x in out]
