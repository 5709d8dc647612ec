"""Stage 3 of the reseau path: the lattice of candidates and the crosses' identification.

:func:`fit_lattice` fits the certificate's grid to the candidates of each polarity
(:func:`softplot.marks.grid.fit_grid`: lattice scale/rotation/phase, row/col assignment from
the format's edges the overview shows (:func:`frame_evidence`), projective film -> pixel model
by RANSAC); the better polarity is the scan's. :func:`turn_template` repeats the correlation
with the template turned like the grid when the grid is turned by more than 2 degrees.
:func:`estimate_dpi` gives the scan's resolution from a lattice fitted with a free scale. The
hand-over is :class:`Lattice`.
"""

from __future__ import annotations

import weakref
from dataclasses import dataclass, replace

import numpy as np

from softplot.marks import coarse, grid
from softplot.marks.candidates import (
    ARM_POOL,
    Candidates,
    arm_scored,
    crosses_in,
    peaks_kept,
    removing_scene,
    reseau_candidates,
    search_map,
    sign_map,
)
from softplot.marks.common import MM_PER_INCH, DetectionError, polarity_signs
from softplot.marks.overview import ReseauOverview, reseau_overview
from softplot.marks.template import cross_shape

__all__ = ["Lattice", "fit_lattice", "turn_template", "estimate_dpi", "frame_evidence",
           "seeable", "between_nodes", "reseau_sized", "renamed", "shear_tol", "FRAME_STEP",
           "SCALE_TOL", "SHEAR_TOL",
           "HALF_STEPS", "MIN_PART", "MIN_SPANNING"]

#: the step of grey (over the scan's range) that a film format's edge shows at least
FRAME_STEP = 0.25
#: the fewest crosses of an outer row (column) inside the scan, none of them measured, that
#: move an ambiguous naming off it (:func:`renamed`)
EMPTY_LINE = 3
#: the step of grey (over the scan's range) of the format's edge that a naming moved off an
#: empty outer line shows (:func:`renamed`)
MOVED_EDGE_STEP = 0.4
#: the fraction of a format edge where the film inside must show for the edge's step to be
#: read there only (:func:`frame_evidence`)
EDGE_SHOWN = 0.3
#: a fit of fewer crosses is never a reseau (detection needs at least as many): it does
#: not stop the other polarity from being fitted, and loses to a fit of as many
MIN_FIT = 4
#: a lattice of fewer candidates than this (or the whole grid, when smaller) is not a reseau:
#: a part of 3 x 3 crosses with a few missing still passes
MIN_PART = 6
#: ... unless it has at least this many and reaches the grid's first and last row and column
#: (no other naming is possible), and at least this many crosses are then measured
MIN_SPANNING = 4
#: a fit of at least this share of the crosses a scan can hold is a whole grid (:func:`_rank`)
WHOLE = 0.8
#: the distance (film mm) from a small lattice's node within which a cross crowded out of
#: the candidates is looked for (:func:`_densified`)
NODE_SEARCH_MM = 0.5
#: the rounds of :func:`_densified`
DENSIFY_ROUNDS = 2
#: the least correlation of a peak (the candidates' threshold)
PEAK_MIN = 0.2
#: with the dpi known, the lattice's spacing stays within this fraction of the certificate's
#: pitch at that dpi (film shrinkage and scanner anisotropy are a few tenths of a percent)
SCALE_TOL = 0.03
#: on the second try (:func:`~softplot.marks.candidates.scene_removed`) the lattice keeps
#: the certificate's right angle: the cosine of the angle between its steps within this of
#: 0 (:func:`shear_tol`). Scanner anisotropy and film deformation shear a reseau by well
#: under a tenth of a degree, the peaks' positions a lattice is fitted to by about a pixel
#: over a pitch; render 475's lattice through a row of its crosses and a scene peak was
#: sheared by 13 degrees
SHEAR_TOL = 0.05


@dataclass
class Lattice:
    """The crosses found on a lattice (hand-over of :func:`fit_lattice`).

    Attributes
    ----------
    grid : softplot.marks.grid.GridFit
        ``H`` (3, 3) film mm -> full-resolution pixel system; ``index`` (K,) the peaks
        assigned to crosses, ``node`` (K,) their cross indices (row-major, as
        :meth:`softplot.camera.Reseau.film`); scale (px/mm), rotation (degrees), score.
    sign : int
        The crosses' polarity: +1 bright (a negative), -1 dark (a positive).
    peaks : softplot.marks.coarse.Peaks
        The peaks the lattice was fitted to, ``xy`` (P, 2) overview pixel system.
    ncc : (h, w) ndarray
        The NCC map the peaks come from (overview pixel system offset by ``half``, as
        :class:`~softplot.marks.candidates.Candidates`).
    half : int
        The map's offset (overview px).
    factor : int
        The overview's reduction factor.
    densified : bool
        Some of ``peaks`` were looked for at the nodes of a lattice too small to be a
        reseau (:func:`_densified`), not found among the candidates.
    """

    grid: grid.GridFit
    sign: int
    peaks: coarse.Peaks
    ncc: np.ndarray
    half: int
    factor: int
    densified: bool = False

    def assigned_xy(self) -> np.ndarray:
        """The assigned peaks (K, 2), full-resolution pixel system (order of ``grid.node``)."""
        return coarse.ov_to_full(self.peaks.xy[self.grid.index], self.factor)


_GREY: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _grey_range(ov):
    """``(g, lo, hi)``: the overview's float32 grey ``g`` (overview pixel system) and the 5 and
    95 % points of a subsample of it (about 256 x 256). Computed once per overview object:
    :func:`frame_evidence` (once per polarity fitted) and :func:`seeable` of one lattice
    stage ask for the same ones (an overview that cannot be weakly keyed: each time)."""
    try:
        return _GREY[ov]
    except (KeyError, TypeError):
        pass
    g = ov[:, :] if hasattr(ov, "grey") else np.asarray(ov, np.float32)
    Hh, W = g.shape
    sub = g[:: max(1, Hh // 256), :: max(1, W // 256)]
    lo, hi = np.percentile(sub, [5, 95])
    out = (g, lo, hi)
    try:
        _GREY[ov] = out
    except TypeError:
        pass
    return out


def frame_evidence(ov, f: int, ppm: float, pitch_mm: float | None = None):
    """The evidence of a film format's edge in the overview, for :func:`grid.fit_grid`.

    ``ov`` the overview (overview pixel system, reduction ``f``), ``ppm`` full-resolution px
    per mm. Returns a function of format corners (K, 4, 2) (full-resolution pixel system;
    top-left, top-right, bottom-right, bottom-left) giving, per quadrilateral, the sum over
    its edges that lie in the scan of the step of grey across the edge (median of inside minus
    outside, 0.3 mm either side, along the edge, over the overview's grey range 5-95 %, at
    most 1: near 1 for the unexposed border of a film, small for scene content) less
    :data:`FRAME_STEP`,
    over 4: a shift that puts more of the format's edges on real steps wins, one that puts an
    edge on scene content loses. Edges outside the scan are left out. Given the crosses a
    lattice found (``found`` (n, 2), full-resolution pixel system), the median is taken over
    the places where the film inside the edge could show (grey inside like around the
    crosses, as :func:`seeable` judges) when they are at least :data:`EDGE_SHOWN` of the
    edge: a flat dark region over part of the film (dark rows) hides the edge there.
    """
    g, lo, hi = _grey_range(ov)
    Hh, W = g.shape
    rng = max(float(hi - lo), 1e-6)
    d = max(2.0, 0.3 * ppm / f)

    def sample(p):
        x = np.round((p[..., 0] + 0.5) / f - 0.5).astype(int)
        y = np.round((p[..., 1] + 0.5) / f - 0.5).astype(int)
        ok = (x >= 0) & (x < W) & (y >= 0) & (y < Hh)
        return np.where(ok, g[np.clip(y, 0, Hh - 1), np.clip(x, 0, W - 1)], np.nan), ok

    def clip(a, b, pad):
        """Parameters [t0, t1] of the part of segments a -> b (K, 2) within the scan less
        ``pad`` px (Liang-Barsky), from [0.05, 0.95]; t1 <= t0 where none is."""
        t0, t1 = np.full(len(a), 0.05), np.full(len(a), 0.95)
        dd = b - a
        lim = ((0, pad, W * f - 1 - pad), (1, pad, Hh * f - 1 - pad))
        for k, lo_, hi_ in lim:
            for pk, qk in ((-dd[:, k], a[:, k] - lo_), (dd[:, k], hi_ - a[:, k])):
                with np.errstate(divide="ignore", invalid="ignore"):
                    t = qk / pk
                t0 = np.where(pk < 0, np.maximum(t0, t), t0)
                t1 = np.where(pk > 0, np.minimum(t1, t), t1)
                t1 = np.where((pk == 0) & (qk < 0), -1.0, t1)
        return t0, t1

    level = _level(g, f, max(1.0, 0.1 * pitch_mm * ppm / f) if pitch_mm else 1.0)

    def evidence(corners, found=None):
        corners = np.asarray(corners, float).reshape(-1, 4, 2)
        band = None
        if found is not None and len(found):
            b_lo, b_hi = np.percentile(level(found), [10, 90])
            band = (b_lo - 0.3 * rng, b_hi + 0.3 * rng)
        c = corners.mean(1)  # (K, 2)
        total = np.zeros(len(corners))
        for e in range(4):  # every shift at once, edge by edge
            a, b = corners[:, e], corners[:, (e + 1) % 4]
            tang = (b - a) / np.maximum(np.hypot(*(b - a).T), 1e-9)[:, None]
            n = np.stack([tang[:, 1], -tang[:, 0]], 1)
            n *= np.where(np.sum(n * (0.5 * (a + b) - c), 1) < 0, -1.0, 1.0)[:, None]  # out
            # the part of the edge in the scan, both samples inside: at least 36 overview px
            # of it (edges outside the scan are left out), sampled at 200 points
            t0, t1 = clip(a, b, d * f + f)
            use = np.where((t1 - t0) * np.hypot(*(b - a).T) >= 36.0 * f)[0]
            if use.size == 0:
                continue
            t = t0[use, None] + (t1 - t0)[use, None] * np.linspace(0.0, 1.0, 200)[None, :]
            p = a[use, None, :] + t[..., None] * (b - a)[use, None, :]  # (U, 200, 2)
            gi, _ = sample(p - n[use, None, :] * d * f)
            go, _ = sample(p + n[use, None, :] * d * f)
            # each edge counts at most a full step: on a scan whose grey range is mostly
            # the film's (a low-contrast frame, little border) one edge on the border would
            # otherwise outweigh every other edge, and every shift would score alike
            diff = gi - go
            if band is not None:
                # where the film inside could show the edge, when that is enough of it
                film = (gi >= band[0]) & (gi <= band[1])
                part = film.mean(1) >= EDGE_SHOWN
                diff = np.where(part[:, None] & ~film, np.nan, diff)
            step = np.minimum(np.abs(np.nanmedian(diff, 1)) / rng, 1.0)
            total[use] += step - FRAME_STEP
        return np.clip(total / 4.0, -1.0, 1.0)

    return evidence


def seeable(ov, f: int, ppm: float, pitch_mm: float):
    """Where a cross would show in the scan, for :func:`grid.fit_grid`'s ``seeable``.

    ``ov`` the overview (overview pixel system, reduction ``f``), ``ppm`` full-resolution
    px per mm, ``pitch_mm`` the grid's smaller pitch. Returns a function of positions
    (K, 2) and of the crosses a lattice found (n, 2) (full-resolution pixel system) giving
    (K,) bool: the grey around the position (the
    median of 7 x 7 samples over a fifth of a pitch) lies within the range of the grey
    around the crosses found (their 10-90 %) widened by 0.3 of the overview's range (5-95
    %). A flat dark region (a sky, a shadow) or the unexposed border is not: a cross there
    does not show, however the grid is named.
    """
    g, lo, hi = _grey_range(ov)
    Hh, W = g.shape
    rng = max(float(hi - lo), 1e-6)
    level = _level(g, f, max(1.0, 0.1 * pitch_mm * ppm / f))

    def show(xy, found_xy):
        ref = level(found_xy)
        b_lo, b_hi = np.percentile(ref, [10, 90]) if len(ref) else (lo, hi)
        b = level(xy)
        return (b >= b_lo - 0.3 * rng) & (b <= b_hi + 0.3 * rng)

    return show


def _level(g, f: int, r: float):
    """The grey around positions (K, 2) (full-resolution pixel system) in the overview ``g``
    (reduction ``f``): the median of 7 x 7 samples over +-``r`` overview px, (K,)."""
    Hh, W = g.shape
    off = np.linspace(-r, r, 7)

    def level(xy):
        p = coarse.full_to_ov(np.asarray(xy, float).reshape(-1, 2), f)
        x = np.clip(np.round(p[:, 0, None, None] + off[None, None, :]), 0, W - 1).astype(int)
        y = np.clip(np.round(p[:, 1, None, None] + off[None, :, None]), 0, Hh - 1).astype(int)
        return np.median(g[y, x].reshape(len(p), -1), axis=1)

    return level


def shear_tol() -> float | None:
    """The lattice's largest shear (:data:`SHEAR_TOL` on the second try, which is held to
    the certificate's rectangular grid; None, any, on the first)."""
    return SHEAR_TOL if removing_scene() else None


def fit_lattice(scan, ov: ReseauOverview, cands: Candidates, camera, polarity: str,
                rotate_deg: float, part=None) -> Lattice | None:
    """The certificate's grid fitted to the candidates of each sign ``polarity`` admits; the
    best-scoring fit (the first sign on a tie), or None when no sign gives a lattice.

    ``rotate_deg``: the pixel-system angle of film +x expected (degrees); ``part``: the part
    of the grid the scan shows when the user gives it ((col0, col1, row0, row1) or None).
    A sign whose :attr:`Candidates.bound` cannot beat a fit already made (of at least
    :data:`MIN_FIT` crosses) is not fitted; a fit of fewer crosses loses to one of as many.
    When no fit can be a reseau (:func:`reseau_sized`), each is fitted again with the
    crosses looked for at its nodes (:func:`_densified`), and then, when still none can, to
    the lattice most peaks agree with in number (:func:`_by_count`).
    """
    res = camera.reseau
    f, px_per_mm = ov.factor, ov.px_per_mm
    pmin = min(res.pitch_x, res.pitch_y)
    show = seeable(ov.image, f, px_per_mm, pmin)
    # fit the polarity that can score most first; another one only if it could still win
    fits = {}
    # (a deferred sign's bound lies below every other's: it comes last)
    for sg in sorted(cands.peaks, key=lambda k: -cands.bound[k]) + list(cands.deferred):
        # a fit of too few crosses to be a reseau (junk of the other polarity) prunes none
        done = [g.score for g, _, _ in fits.values()
                if g is not None and len(g.node) >= MIN_FIT]
        if sg in cands.deferred:
            # scored by its arms only when its correlations' bound could still win
            if (done and cands.deferred[sg][0] < max(done)) or not cands.take(sg):
                continue
        pk, bound = cands.peaks[sg], cands.bound[sg]
        if done and bound < max(done):
            continue

        def fit(q, by_count=False):
            # a cross nearer the scan's edge than the correlation map reaches (its offset)
            # has no peak: it is never a missed cross
            return grid.fit_grid(coarse.ov_to_full(q.xy, f), q.score, res,
                                 (scan.width, scan.height), px_per_mm=px_per_mm,
                                 rotate_deg=rotate_deg,
                                 margin_px=max(0.5 * cands.template.length, cands.half) * f,
                                 frame_evidence=frame_evidence(ov.image, f, px_per_mm, pmin),
                                 format_mm=camera.format_mm, scale_tol=SCALE_TOL, part=part,
                                 seeable=show, by_count=by_count, max_shear=shear_tol())

        fits[sg] = (fit(pk), pk, fit)
    dense = set()
    if not any(g is not None and reseau_sized(g.node, res) for g, _, _ in fits.values()):
        # no fit can be a reseau: each looks for the crosses the candidates lack
        for sg, (g, pk, fit) in fits.items():
            if g is not None:
                g2, pk2 = _densified(g, pk, sg, cands, ov, res, fit)
                if g2 is not g:
                    fits[sg] = (g2, pk2, fit)
                    dense.add(sg)
    if not any(g is not None and reseau_sized(g.node, res) for g, _, _ in fits.values()):
        # still none: the lattice most peaks agree with, by number (weak crosses)
        for sg, v in _by_count(fits, res).items():
            if v is not fits[sg]:
                fits[sg] = v
                dense.discard(sg)
    best = None
    n_in = crosses_in(scan, res, px_per_mm)
    for sg in polarity_signs(polarity):  # the best score wins, the first polarity on a tie
        g, pk, _ = fits.get(sg, (None, None, None))
        if g is not None and (best is None or _rank(g, res, n_in) > _rank(best.grid, res, n_in)):
            best = Lattice(grid=g, sign=sg, peaks=pk, ncc=cands.ncc_of(sg), half=cands.half,
                           factor=f, densified=sg in dense)
    return best


def renamed(lat: Lattice, res, measured, shown, size, H, edge, format_mm) -> Lattice | None:
    """An ambiguous naming moved by one row or column off an empty outer line: the lattice
    ``lat`` named again when, at full resolution, an outer row (column) of the grid holds at
    least :data:`EMPTY_LINE` crosses whole inside the scan (``shown``) and not one of them
    measured (``measured``; both (N,) bool, row-major as :meth:`Reseau.film`), the line
    that the move names anew beyond the opposite outer one lies off the scan (``size``
    (width, height) px), and the format's edge of the moved naming (``format_mm``) beside
    the empty line shows a step of grey of at least :data:`MOVED_EDGE_STEP` of the scan's
    range: the lattice's outermost peaks were scene content on the film's border, and the
    crosses the scan holds all keep a name. ``H``: film mm -> pixel system of the measured
    crosses; ``edge``: :func:`frame_evidence` of the scan. None when no move, or more than
    one, fits.
    """
    rows, cols = res.rows, res.cols
    meas = np.asarray(measured, bool).reshape(rows, cols)
    ins = np.asarray(shown, bool).reshape(rows, cols)
    film = res.film().reshape(rows, cols, 2)
    W, Hh = size
    found = grid.apply_h(H, film[meas])
    moves = []
    for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        if (cols if dc else rows) < 3:
            continue
        # the outer line that leaves the grid, and the first one of the other side
        leave = (slice(None), cols - 1 if dc > 0 else 0) if dc else (rows - 1 if dr > 0 else 0,
                                                                      slice(None))
        first = (slice(None), 0 if dc > 0 else cols - 1) if dc else (0 if dr > 0 else rows - 1,
                                                                     slice(None))
        if meas[leave].any() or ins[leave].sum() < EMPTY_LINE:
            continue
        step = (film[0, 1] - film[0, 0]) * dc + (film[1, 0] - film[0, 0]) * dr
        new = grid.apply_h(H, film[first] - step)  # pixel system
        if np.any((new[:, 0] >= 0) & (new[:, 0] <= W - 1) & (new[:, 1] >= 0)
                  & (new[:, 1] <= Hh - 1)):
            continue
        if _edge_step(film, film[leave], step, H, edge, format_mm, found, size) < \
                MOVED_EDGE_STEP:
            continue
        moves.append((dr, dc, step))
    if len(moves) != 1:
        return None
    dr, dc, step = moves[0]
    g = lat.grid
    r, c = g.node // cols + dr, g.node % cols + dc
    keep = (r >= 0) & (r < rows) & (c >= 0) & (c < cols)
    # a cross named (r, c) is at the film position of (r - dr, c - dc) before: film + step
    T = np.array([[1.0, 0.0, -step[0]], [0.0, 1.0, -step[1]], [0.0, 0.0, 1.0]])
    g2 = replace(g, H=g.H @ T, index=g.index[keep], node=(r * cols + c)[keep])
    return replace(lat, grid=g2)


def _edge_step(film, line, step, H, edge, format_mm, found, size) -> float:
    """The step of grey (over the scan's range, :func:`frame_evidence`) across the format's
    edge beside the outer line ``line`` (film mm) of a naming moved by ``step`` (film mm)
    off it; ``film`` (rows, cols, 2) the grid, ``H`` film mm -> pixel system."""
    centre = film.reshape(-1, 2).mean(0) - step  # the moved grid's centre, film mm
    out = line.mean(0) - film.reshape(-1, 2).mean(0)
    k = int(np.argmax(np.abs(out)))
    half = 0.5 * np.asarray(format_mm, float)
    a, b = centre.copy(), centre.copy()
    a[k] = b[k] = centre[k] + np.sign(out[k]) * half[k]
    a[1 - k], b[1 - k] = centre[1 - k] - half[1 - k], centre[1 - k] + half[1 - k]
    p = grid.apply_h(H, np.array([a, b, centre]))  # pixel system
    t = (p[1] - p[0]) / max(float(np.hypot(*(p[1] - p[0]))), 1e-9)
    n = p[2] - p[0] - np.dot(p[2] - p[0], t) * t
    n /= max(float(np.hypot(*n)), 1e-9)  # towards the film
    far = 4.0 * float(sum(size))
    # the edge reaching beyond the scan, the quadrilateral's other edges far off it
    q0, q1 = p[0] - far * t, p[1] + far * t
    corners = np.array([q0, q1, q1 + far * n, q0 + far * n])[None]
    return float(4.0 * edge(corners, found)[0] + FRAME_STEP)


def _rank(g, res, n_in: int | None = None) -> tuple:
    """The order of fits of each sign: one that can be a reseau (:func:`reseau_sized`)
    first, then one that holds :data:`WHOLE` of the ``n_in`` crosses the scan can hold, then
    one of at least :data:`MIN_FIT` crosses, then the higher score. A whole grid decides:
    a scan's bright border full of grain gives the peaks of the crosses' polarity a high
    clutter level (a negative's 25 of 25 clear crosses scored 0.73), and a few noise peaks
    of the other polarity on a lattice can score more."""
    whole = n_in is not None and whole_grid(len(g.node), n_in)
    return reseau_sized(g.node, res), whole, len(g.node) >= MIN_FIT, g.score


def whole_grid(n_nodes: int, n_in: int) -> bool:
    """Does a fit of ``n_nodes`` crosses hold the whole grid of the ``n_in`` crosses the scan
    can hold (:data:`WHOLE` of them, at least :data:`MIN_PART`)?"""
    return n_nodes >= max(MIN_PART, WHOLE * n_in)


def reseau_sized(node, res) -> bool:
    """Can the lattice's crosses ``node`` (indices, row-major) be a reseau: at least
    :data:`MIN_PART` of them (or the whole grid ``res``, when smaller), or at least
    :data:`MIN_SPANNING` reaching the first and last row and column of the grid (a small grid
    over a busy scene shows a few of its crosses among the candidates, but placed so that
    the grid can be named only one way)?"""
    node = np.asarray(node, int)
    if len(node) >= min(MIN_PART, res.count):
        return True
    r, c = node // res.cols, node % res.cols
    return bool(len(node) >= MIN_SPANNING and r.min() == 0 and r.max() == res.rows - 1
                and c.min() == 0 and c.max() == res.cols - 1)


def _nodes_around(node, res) -> np.ndarray:
    """The film positions (mm) of the nodes of every naming of a lattice whose crosses are
    ``node`` (indices, row-major, of the grid ``res``): the lattice's nodes within a grid's
    extent of them less those, (K, 2)."""
    node = np.asarray(node, int)
    r, c = node // res.cols, node % res.cols
    jj, ii = np.mgrid[r.max() - res.rows + 1: r.min() + res.rows,
                      c.max() - res.cols + 1: c.min() + res.cols]
    keep = ~np.isin(jj * res.cols + ii, r * res.cols + c) | (ii < 0) | (ii >= res.cols)
    film = res.film()
    x0 = film[0]
    sx = film[1] - film[0] if res.cols > 1 else np.array([res.pitch_x, 0.0])
    sy = film[res.cols] - film[0] if res.rows > 1 else np.array([0.0, -res.pitch_y])
    return x0 + ii[keep][:, None] * sx + jj[keep][:, None] * sy


def _densified(g, pk, sign, cands: Candidates, ov: ReseauOverview, res, fit):
    """A lattice too small to be a reseau (:func:`reseau_sized`) from peaks looked for at the
    nodes of its every naming: a small grid over a busy scene has crosses that the scene's
    stronger peaks crowd out of the candidates ``pk`` (overview pixel system), though the
    NCC map shows them where the lattice ``g`` (film mm -> full-resolution pixel system) puts
    a cross.

    At every node (:func:`_nodes_around`, placed by an affine model of the lattice's
    crosses), the best correlation of ``sign`` within :data:`NODE_SEARCH_MM`
    (:func:`~softplot.marks.candidates.search_map`), when :data:`PEAK_MIN` or more, joins
    the candidates; ``fit`` (peaks -> fit) fits the lattice again, up to
    :data:`DENSIFY_ROUNDS` times while it grows. Returns (fit, peaks): the largest fit and
    its peaks (``g`` and ``pk`` when none grows)."""
    f = ov.factor
    base = pk
    for _ in range(DENSIFY_ROUNDS):
        # an affine model of the lattice's crosses: a projective one of a few extrapolates
        # badly
        A = np.column_stack([res.film()[g.node], np.ones(len(g.node))])
        sol = np.linalg.lstsq(A, pk.xy[g.index], rcond=None)[0]  # film mm -> overview px
        film = _nodes_around(g.node, res)
        if len(film) == 0:
            break
        at = np.column_stack([film, np.ones(len(film))]) @ sol
        pos, val = search_map(cands.ncc_of(sign), cands.half, sign, at,
                              max(2.0, NODE_SEARCH_MM * ov.px_per_mm / f))
        # no arm evidence asked: a cross at a node of the lattice often has one arm over
        # the scene's lines (the full-resolution fit decides)
        ok = np.isfinite(val) & (val >= PEAK_MIN)
        if not ok.any():
            break
        n = int(ok.sum())
        pk2 = coarse.Peaks(np.vstack([base.xy, pos[ok]]), np.concatenate([base.score, val[ok]]),
                           np.concatenate([base.sign, np.full(n, sign)]))
        g2 = fit(pk2)
        if g2 is None or len(g2.node) <= len(g.node):
            break
        g, pk = g2, pk2
    return g, pk


def _by_count(fits: dict, res) -> dict:
    """``fits`` (sign -> (fit, peaks, fit function)), none of which can be a reseau
    (:func:`reseau_sized`), with each sign's lattice fitted again to the peaks that most
    agree with one in number (not in the sum of their scores) where that one can: a reseau
    of weak crosses (thin, faint or blurred arms the template matches poorly) over a busy
    scene, whose stronger peaks outscore it on a lattice of a few nodes."""
    out = dict(fits)
    for sg, (_, pk, fit) in fits.items():
        g2 = fit(pk, by_count=True)
        if g2 is not None and reseau_sized(g2.node, res):
            out[sg] = (g2, pk, fit)
    return out


def turn_template(lat: Lattice, scan, ov: ReseauOverview, camera, rotate_deg: float,
                  blur_px: float, part=None) -> Lattice:
    """``lat`` again from a correlation with the template turned like its grid, when the grid
    is turned by more than 2 degrees from ``rotate_deg`` (pixel-system degrees); the new
    lattice replaces ``lat`` when it assigns as many crosses or more."""
    g = lat.grid
    if abs((g.rotation_deg - rotate_deg + 180.0) % 360.0 - 180.0) <= 2.0:
        return lat
    res = camera.reseau
    f, ppm = ov.factor, ov.px_per_mm
    pmin = min(res.pitch_x, res.pitch_y)
    shape = cross_shape(camera, ppm)
    J = grid.h_jacobian(g.H, res.film()[g.node].mean(0))[0] / ppm  # where the crosses are
    A_ov = np.linalg.inv(J @ np.diag([1.0, -1.0]))
    shape_ov = cross_shape(camera, ppm / f)
    s_ov = float(np.hypot(blur_px / f, 0.5))
    arm_half = min(0.5 * shape_ov.length, 10.0)
    if removing_scene():
        R2, h2 = sign_map(ov.image, shape_ov, s_ov, lat.sign, A=A_ov, arm_half=arm_half)
    else:
        R2, h2 = coarse.ncc_map(ov.image, shape_ov, s_ov, A=A_ov, arm_half=arm_half)
    n_in = crosses_in(scan, res, ppm)
    pk2 = coarse.find_peaks(R2, h2, min_dist=max(2.0, min(0.35 * res.pitch_x * ppm / f,
                                                          0.5 * shape_ov.length)),
                            threshold=0.2, max_peaks=ARM_POOL * peaks_kept(n_in),
                            sign=lat.sign)
    # scored by their arms (turned like the grid), as the first candidates were
    pk2 = arm_scored(pk2, ov.image, lat.sign, arm_half, shape_ov.width, s_ov, n_in,
                     peaks_kept(n_in), g.rotation_deg)
    g2 = grid.fit_grid(coarse.ov_to_full(pk2.xy, f), pk2.score, res,
                       (scan.width, scan.height), px_per_mm=ppm, rotate_deg=g.rotation_deg,
                       margin_px=max(0.5 * shape.length, h2 * f), max_rotation_deg=3.0,
                       frame_evidence=frame_evidence(ov.image, f, ppm, pmin),
                       format_mm=camera.format_mm, scale_tol=SCALE_TOL, part=part,
                       seeable=seeable(ov.image, f, ppm, pmin), max_shear=shear_tol())
    if g2 is not None and len(g2.node) >= len(g.node):
        return Lattice(grid=g2, sign=lat.sign, peaks=pk2, ncc=R2, half=h2, factor=f,
                       densified=lat.densified)
    return lat


#: the scales tried from the scan's size (x the scale at which the film format fills the scan):
#: a scan shows the format and a margin of up to about a tenth of it, in steps small enough
#: that one is within 2 % of the truth (a lattice started 5 % off drifts by a fifth of a pitch
#: over four pitches)
SIZE_SCALES = np.linspace(1.0, 0.8, 8)


def estimate_dpi(scan, camera, polarity: str, rotate_deg: float, name: str) -> float:
    """The scan's resolution (dpi) from a lattice of its crosses fitted with a free scale.

    A first guess from the scan's size (it holds the format), then candidate scales from the
    peaks' spacing; the best-scoring lattice gives the scale. A
    :class:`~softplot.marks.common.DetectionError` when no regular grid is found.
    """
    res = camera.reseau
    guess = 25.4 * min(scan.width / camera.format_mm[0], scan.height / camera.format_mm[1])
    ppm = guess / MM_PER_INCH
    ov = reseau_overview(scan, res.line_width_mm * ppm, ppm, name)
    f = ov.factor
    # a lattice fitted with a free scale (from the peaks' spacing) gives the dpi; the
    # candidates are those of the lattice stage at the guessed scale (NCC peaks scored by
    # their arms: scene texture correlates as well as crosses do, but shows no arms)
    cands = reseau_candidates(scan, ov, camera, polarity, 1.0).complete()
    best_g = None
    pmin = min(res.pitch_x, res.pitch_y)
    need = max(4, 0.2 * res.count)
    for sg in sorted(cands.peaks, key=lambda k: -cands.bound[k]):  # the likelier sign first
        q = cands.peaks[sg]
        xy = coarse.ov_to_full(q.xy, f)
        # candidate scales: the size-based guess (the scan may show more than the format)
        # and the most frequent neighbour spacing of the strongest peaks (or its double,
        # when peaks also sit half-way between crosses)
        scales = list(ppm * SIZE_SCALES)
        sp = grid.estimate_spacing(xy[np.argsort(-q.score)[: max(int(1.5 * res.count), 8)]])
        if sp is not None:
            scales += [sp / pmin, 2.0 * sp / pmin]
        for k in scales:
            g0 = grid.fit_grid(xy, q.score, res, (scan.width, scan.height), px_per_mm=k,
                               rotate_deg=rotate_deg)
            # a lattice of too few nodes never wins over one of enough (a few strong scene
            # peaks at another scale outscore a small grid's crosses)
            if g0 is not None and (best_g is None or (len(g0.node) >= need, g0.score)
                                   > (len(best_g.node) >= need, best_g.score)):
                best_g = g0
            if g0 is not None and whole_grid(len(g0.node),
                                             crosses_in(scan, res, g0.px_per_mm)):
                # the whole grid the scan can hold: its scale is the scan's (the scales
                # left, each a lattice fit, would cost seconds on a small grid)
                return g0.px_per_mm * MM_PER_INCH
    if best_g is None or len(best_g.node) < need:
        raise DetectionError(f"{name}: cannot estimate the dpi: no regular grid of crosses "
                             f"found (expected {res.rows}x{res.cols} crosses at "
                             f"{res.pitch_x} mm); give --dpi")
    return best_g.px_per_mm * MM_PER_INCH


#: offsets (in pitches) of the places halfway between a lattice's nodes
HALF_STEPS = ((0.5, 0.0), (0.0, 0.5), (0.5, 0.5))


def between_nodes(lat: Lattice, reseau, ncc_ratio: float = 0.8) -> list[tuple[float, float]]:
    """The offsets of :data:`HALF_STEPS` (in pitches, film x and y) where the scan shows
    crosses halfway between the lattice's nodes: a reseau denser than the certificate's
    (the wrong camera, whose pitch is a multiple of the scan's), never a reseau that matches.

    Within the block of nodes the lattice assigned, the NCC map (``lat.ncc`` times the
    polarity, best of 3 x 3 overview px) is read at every node assigned and at every
    halfway place of one offset; the offset has crosses where its places (4 or more)
    correlate, in the median, at least ``ncc_ratio`` times as well as the nodes (crosses
    there correlate as well as the nodes, 0.93-0.98 of them on renders with and without a
    busy scene; scene edges along the bars about 0.65).
    """
    g = lat.grid
    film = reseau.film()
    nodes = film[g.node]
    if len(nodes) < 4:
        return []
    R = lat.ncc * lat.sign
    h, w = R.shape

    def read(xy_film):
        p = coarse.full_to_ov(grid.apply_h(g.H, xy_film), lat.factor) - lat.half
        x = np.round(p[:, 0]).astype(int)
        y = np.round(p[:, 1]).astype(int)
        ok = (x >= 1) & (x < w - 1) & (y >= 1) & (y < h - 1)
        x, y = np.clip(x, 1, w - 2), np.clip(y, 1, h - 2)
        best = np.max([R[y + dy, x + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0)
        return best[ok]

    at_nodes = read(nodes)
    if len(at_nodes) < 4:
        return []
    ref = float(np.median(at_nodes))
    lo, hi = nodes.min(0), nodes.max(0)
    pitch = np.array([reseau.pitch_x, reseau.pitch_y])
    found = []
    for off in HALF_STEPS:
        p = nodes + np.asarray(off) * pitch
        p = p[np.all((p >= lo - 1e-9) & (p <= hi + 1e-9), axis=1)]
        if len(p) < 4:
            continue
        v = read(p)
        if len(v) >= 4 and ref > 0 and np.median(v) >= ncc_ratio * ref:
            found.append(off)
    return found
