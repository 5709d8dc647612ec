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
from scipy.optimize import least_squares
from scipy.special import ndtr

from softplot.marks.template import MarkShape

__all__ = ["MarkGeometry", "estimate_geometry", "ARM_RANGE", "WIDTH_RANGE"]

#: admissible true arm length, times the starting guess (certificate or default)
ARM_RANGE = (0.3, 3.0)
#: admissible true line width, times the starting guess
WIDTH_RANGE = (0.35, 3.0)
#: crosses profiled (the best-scoring ones)
MAX_MARKS = 24


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


def _fit_along(u: np.ndarray, p: np.ndarray, lo: float, hi: float):
    """Blurred box along a bar: (a1, a2, s, c) or None."""
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
    try:
        fit = least_squares(
            lambda q: _box(u, q[0], q[1], q[2], q[3], q[4]) - p,
            [b0, c0, a1, a2, 1.0],
            bounds=([-np.inf, 0.0, u[0], 0.0, 0.3], [np.inf, np.inf, 0.0, u[-1], 10.0]),
            x_scale=[abs(c0), abs(c0), 1.0, 1.0, 1.0], max_nfev=60)
    except ValueError:
        return None
    b, c, a1, a2, s = fit.x
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
    try:
        fit = least_squares(
            lambda p: _box(v, p[0], p[1], p[2] - 0.5 * p[3], p[2] + 0.5 * p[3], s) - q,
            [b0, c0, float(v[j]), w_init],
            bounds=([-np.inf, 0.0, v[0], 0.05], [np.inf, np.inf, v[-1], 8.0 * w0 + 4.0]),
            x_scale=[abs(c0), abs(c0), 1.0, 1.0], max_nfev=60)
    except ValueError:
        return None
    b, c, v0, w = fit.x
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
    V = max(3.0 * WIDTH_RANGE[1] * w0, 6.0) + 3.0
    du = 0.5 if L0 < 200 else 1.0
    dv = float(np.clip(w0 / 6.0, 0.2, 0.5))
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
            inner = (np.abs(u) >= 2.0 * w0 + 2.0) & (np.abs(u) <= max(lo_half, 2.0 * w0 + 3.0))
            if inner.sum() < 2:
                inner = np.abs(u) <= max(lo_half, 3.0)
            q = s[:, inner].mean(1)
            fa = _fit_across(v, q, 1.0, w0)
            if fa is None:
                continue
            band = np.abs(v - fa[1]) <= max(0.5 * fa[0], 0.75)
            fl = _fit_along(u, s[band].mean(0), lo_half, 0.5 * ARM_RANGE[1] * L0 + 2.0 * w0)
            if fl is None:
                continue
            a1, a2, sb, cb = fl
            # across profile between the bar's ends, away from the other bar
            sel = ((u > a1 + 0.1 * (a2 - a1) + sb) & (u < a2 - 0.1 * (a2 - a1) - sb)
                   & (np.abs(u - 0.5 * (a1 + a2)) > 0.5 * fa[0] + sb + 1.0))
            if sel.sum() < 3:
                continue
            fw = _fit_across(v, s[:, sel].mean(1), sb, w0)
            if fw is None:
                continue
            arms.append(a2 - a1)
            widths.append(fw[0])
            blurs.append((cb, fw[2]))
    arms_a, widths_a = np.asarray(arms), np.asarray(widths)
    if len(arms_a) >= 2:
        c = np.asarray(blurs)[:, 0]
        keep = c >= 0.3 * np.median(c)  # bars without contrast: one-armed or dark crosses
        arms_a, widths_a = arms_a[keep], widths_a[keep]
    if len(arms_a) < 2:
        return MarkGeometry(L0, w0, float("nan"), float("nan"), int(len(arms_a)), "certificate")
    return MarkGeometry(float(np.median(arms_a)), float(np.median(widths_a)),
                        _robust_std(arms_a), _robust_std(widths_a), int(len(arms_a)), "scan")
