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

Each bar of each cross is one estimate; the scan's value is the median over the crosses, its
spread the robust standard deviation (1.4826 x MAD) over them. Bars without contrast (one-armed
crosses, crosses under a dark sky) are left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import map_coordinates, uniform_filter1d
from scipy.special import ndtr

from softplot.marks.template import MarkShape

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
ARM_AGREE = 0.15
#: profiles and guess agree on the line width within these ratios
WIDTH_AGREE = (0.8, 1.25)


@dataclass(frozen=True)
class MarkGeometry:
    """The reseau crosses' size as imaged (mark frame, nominal px = film mm x px per mm).

    ``arm_px`` tip-to-tip length of a bar, ``width_px`` line width; ``*_spread_px`` their
    robust standard deviation over the crosses (NaN with fewer than 3 estimates); ``n`` the
    bars measured; ``source`` "scan" (measured) or "certificate" (the starting guess kept:
    too few crosses could be profiled).
    """

    arm_px: float
    width_px: float
    arm_spread_px: float
    width_spread_px: float
    n: int
    source: str
    #: the scan's blur sigma (px) from the bars' ends (with the profiles' interpolation)
    blur_px: float = float("nan")

    def with_width(self, width_px: float) -> "MarkGeometry":
        """The same geometry with the line width the measuring stage settled on."""
        return MarkGeometry(self.arm_px, float(width_px), self.arm_spread_px,
                            self.width_spread_px, self.n, self.source, self.blur_px)

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
    return float(1.4826 * np.median(np.abs(v - np.median(v))))


def _box(x, b, c, a1, a2, s):
    return b + c * (ndtr((x - a1) / s) - ndtr((x - a2) / s))


def _box_jac(x, b, c, a1, a2, s):
    """Model and derivatives by (b, c, a1, a2, s): (n,) and (n, 5)."""
    z1, z2 = (x - a1) / s, (x - a2) / s
    P = ndtr(z1) - ndtr(z2)
    g1 = np.exp(-0.5 * z1 * z1) / np.sqrt(2.0 * np.pi)
    g2 = np.exp(-0.5 * z2 * z2) / np.sqrt(2.0 * np.pi)
    J = np.stack([np.ones_like(x), P, -c * g1 / s, c * g2 / s,
                  -c * (z1 * g1 - z2 * g2) / s], 1)
    return b + c * P, J


def _lm(resid_jac, p, lo, hi, iterations=30):
    """Levenberg-Marquardt with box bounds (clipped steps) on a small problem: the parameters
    or None when the fit does not converge to finite values."""
    p = np.asarray(p, float)
    r, J = resid_jac(p)
    cost = float(r @ r)
    lam = 1e-3
    for _ in range(iterations):
        N = J.T @ J
        g = J.T @ r
        D = np.diag(np.diag(N)) + 1e-12 * np.eye(len(p))
        try:
            step = np.linalg.solve(N + lam * D, -g)
        except np.linalg.LinAlgError:
            return None
        q = np.clip(p + step, lo, hi)
        r2, J2 = resid_jac(q)
        c2 = float(r2 @ r2)
        if np.isfinite(c2) and c2 < cost:
            done = cost - c2 < 1e-10 * cost
            p, r, J, cost, lam = q, r2, J2, c2, lam * 0.3
            if done:
                break
        else:
            lam *= 10.0
            if lam > 1e8:
                break
    return p if np.isfinite(p).all() else None


def _fit_along(u: np.ndarray, p: np.ndarray, lo: float, hi: float, centre: float = 0.0):
    """Blurred box along a bar: (a1, a2, s, c) or None. Samples within ``centre`` of the
    middle are left out of the fit: where the bars cross, a thin blurred line is darker than
    along its arms (the other bar's blur adds), which the box does not model."""
    du = float(u[1] - u[0])
    ps = uniform_filter1d(p, max(1, int(round(1.0 / du))))
    b0 = float(np.median(np.concatenate([ps[: len(ps) // 8], ps[-len(ps) // 8:]])))
    mid = np.abs(u) <= max(lo, 2.0)
    c0 = float(np.median(ps[mid])) - b0
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

    m = (np.abs(u) >= centre).astype(float)

    def rj(q):
        f, J = _box_jac(u, *q)
        return (f - p) * m, J * m[:, None]

    q = _lm(rj, [b0, c0, a1, a2, 1.0], [-np.inf, 0.0, u[0], 0.0, 0.3],
            [np.inf, np.inf, 0.0, u[-1], 10.0])
    if q is None:
        return None
    b, c, a1, a2, s = q
    return a1, a2, s, c


def _fit_across(v: np.ndarray, q: np.ndarray, s: float, w0: float):
    """Box of width w blurred by ``s`` across a bar: (w, centre, c) or None."""
    b0 = float(np.median(np.concatenate([q[: len(q) // 6], q[-len(q) // 6:]])))
    j = int(np.argmax(q))
    c0 = float(q[j] - b0)
    if not c0 > 0:
        return None
    area = float(np.sum(q - b0) * (v[1] - v[0]))
    w_init = float(np.clip(area / c0, 0.3 * w0, 4.0 * w0))

    def rj(p):
        b, c, v0, w = p
        f, J = _box_jac(v, b, c, v0 - 0.5 * w, v0 + 0.5 * w, s)
        Jp = np.stack([J[:, 0], J[:, 1], J[:, 2] + J[:, 3], 0.5 * (J[:, 3] - J[:, 2])], 1)
        return f - q, Jp

    p = _lm(rj, [b0, c0, float(v[j]), w_init], [-np.inf, 0.0, v[0], 0.05],
            [np.inf, np.inf, v[-1], 8.0 * w0 + 4.0])
    if p is None:
        return None
    b, c, v0, w = p
    return w, v0, c


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
    arms, widths, blurs = [], [], []
    for i in order:
        Ai = np.linalg.inv(A[i])  # mark frame -> pixel offsets
        reach = np.abs(Ai).sum(1) * (H + V) + 3.0
        x0, y0 = xy[i]
        c0 = int(np.floor(x0 - reach[0]))
        r0 = int(np.floor(y0 - reach[1]))
        c1 = int(np.ceil(x0 + reach[0])) + 1
        r1 = int(np.ceil(y0 + reach[1])) + 1
        try:
            win = grey_at((slice(max(r0, 0), max(r1, 0)), slice(max(c0, 0), max(c1, 0))))
        except (ValueError, IndexError):
            continue
        if win.size == 0 or win.shape != (r1 - r0, c1 - c0):
            continue  # the profiles leave the scan
        win = sign * np.asarray(win, np.float32)
        for bar in (0, 1):  # 0: the bar along u (film x), 1: along v
            uu, vv = np.meshgrid(u, v, indexing="xy")  # (len(v), len(u)): rows across
            m = np.stack([uu, vv]) if bar == 0 else np.stack([vv, uu])
            px = Ai @ m.reshape(2, -1)
            s = map_coordinates(win, [px[1] + y0 - r0, px[0] + x0 - c0], order=1,
                                mode="nearest").reshape(uu.shape)
            # the bar's position across (coarse centres are off by up to a few px)
            # (the other bar adds the same to every v within its width: no bias)
            inner = np.abs(u) <= max(lo_half, 3.0)
            q = uniform_filter1d(s[:, inner].mean(1), max(1, int(round(0.5 * w0 / dv))))
            vc = float(v[int(np.argmax(q))])
            band = np.abs(v - vc) <= max(0.5 * w0, 0.75)
            fl = _fit_along(u, s[band].mean(0), lo_half, 0.5 * ARM_RANGE[1] * L0 + 2.0 * w0,
                            centre=min(1.5 * w0 + 2.0, 0.6 * lo_half))
            if fl is None:
                continue
            a1, a2, sb, cb = fl
            # across profile between the bar's ends, away from the other bar
            sel = ((u > a1 + 1.5 * sb) & (u < a2 - 1.5 * sb)
                   & (np.abs(u - 0.5 * (a1 + a2)) > 0.5 * w0 + 1.5 * sb))
            if sel.sum() < 3:
                continue
            fw = _fit_across(v, s[:, sel].mean(1), sb, w0)
            if fw is None:
                continue
            arms.append(a2 - a1)
            widths.append(fw[0])
            blurs.append((cb, sb))
    arms_a, widths_a = np.asarray(arms), np.asarray(widths)
    blur_a = np.asarray(blurs).reshape(-1, 2)[:, 1]
    if len(arms_a) >= 2:
        c = np.asarray(blurs)[:, 0]
        keep = c >= 0.3 * np.median(c)  # bars without contrast: one-armed or dark crosses
        arms_a, widths_a, blur_a = arms_a[keep], widths_a[keep], blur_a[keep]
    if len(arms_a) < 2:
        return MarkGeometry(L0, w0, float("nan"), float("nan"), int(len(arms_a)), "certificate")
    w = float(np.median(widths_a))
    sb = float(np.median(blur_a))
    arm, sa, sw = float(np.median(arms_a)), _robust_std(arms_a), _robust_std(widths_a)
    if not sa <= CONSISTENT[0] * arm:
        # the crosses disagree about their size: scene content along the bars, not the marks
        return MarkGeometry(L0, w0, sa, sw, int(len(arms_a)), "certificate")
    if abs(arm / L0 - 1.0) <= ARM_AGREE:
        # within what a busy scene's profiles miss by: the guess stands
        arm = L0
    if not sw <= CONSISTENT[1] * w:
        w = float("nan")  # the width is not measured: the guess stands (width_candidates)
    return MarkGeometry(arm, w, sa, sw, int(len(arms_a)), "scan", blur_px=sb)


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
    if geom.source != "scan":
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
