"""Exact rendering of reseau crosses and fiducial marks through the truth mapping.

A mark is exposed onto the film before it deforms, so its shape is defined in **undeformed
film mm**: a union of axis-aligned rectangles and discs (a cross is two bars minus their
common square, counted once; a circle-dot is a disc minus a smaller disc plus a centre dot).

The area of a pixel covered by a mark is integrated as follows. A point of the pixel (pixel
system, the unit square around its centre) is mapped into undeformed film mm through the exact
pixel -> film mapping at the pixel centre (Newton inverse of the deformation) plus the local
Jacobian (the mapping's curvature over one pixel is ~1e-9 mm). Along every pixel-x line of the
pixel a primitive is an interval found in closed form (two slab intersections for a
rectangle, a quadratic for a disc). For a rectangle the interval's ends are linear in the
line's y offset, so the covered length is piecewise linear and the area is integrated exactly
over its break points: crosses are rendered by **exact area integration**. Discs (dots,
circles) use the closed form along x and an ``n``-point midpoint rule along y. Only pixels
within one pixel of a primitive are integrated; all others are 0.

Why exact: point supersampling (n x n) quantises the position of an edge parallel to the
pixel grid to 1/n px, which moves a cross's centroid by up to ~1/(2n) px on an unrotated scan.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softplot.camera import Fiducial


@dataclass(frozen=True)
class MarkShape:
    """A mark's shape around its centre, in undeformed film mm (x right, y up).

    Attributes
    ----------
    kind : str
        "cross", "dot" or "circle-dot".
    rects : ndarray, shape (R, 3)
        Rectangles ``(half_x_mm, half_y_mm, sign)``: the shape's indicator is the signed sum.
    discs : ndarray, shape (D, 2)
        Discs ``(radius_mm, sign)``.
    """

    kind: str
    rects: np.ndarray
    discs: np.ndarray

    @property
    def radius_mm(self) -> float:
        """Radius (film mm) of a circle around the centre that contains the shape."""
        r = [float(np.hypot(h[0], h[1])) for h in self.rects] + [float(d[0]) for d in self.discs]
        return max(r)

    @property
    def area_mm2(self) -> float:
        """Area of the shape, film mm^2."""
        a = sum(4 * h[0] * h[1] * h[2] for h in self.rects)
        return float(a + sum(np.pi * d[0] ** 2 * d[1] for d in self.discs))

    def outline_mm(self, n_circle: int = 32) -> np.ndarray:
        """Points (N, 2) film mm, relative to the centre, on the outer boundary of the shape."""
        pts = []
        for hx, hy, s in self.rects:
            if s > 0:
                pts += [(hx, hy), (-hx, hy), (-hx, -hy), (hx, -hy)]
        ang = np.linspace(0, 2 * np.pi, n_circle, endpoint=False)
        for r, s in self.discs:
            if s > 0:
                pts += list(zip(r * np.cos(ang), r * np.sin(ang)))
        return np.array(pts, float).reshape(-1, 2)


def cross_shape(arm_length_mm: float, line_width_mm: float) -> MarkShape:
    """A cross of two bars ``arm_length_mm`` tip-to-tip and ``line_width_mm`` wide."""
    L, w = arm_length_mm / 2.0, line_width_mm / 2.0
    return MarkShape(
        kind="cross",
        rects=np.array([[L, w, 1.0], [w, L, 1.0], [w, w, -1.0]]),
        discs=np.zeros((0, 2)),
    )


def dot_shape(diameter_mm: float) -> MarkShape:
    """A filled disc."""
    return MarkShape(kind="dot", rects=np.zeros((0, 3)), discs=np.array([[diameter_mm / 2, 1.0]]))


def circle_dot_shape(outer_mm: float, line_width_mm: float, dot_mm: float) -> MarkShape:
    """A ring of outer diameter ``outer_mm`` and stroke ``line_width_mm`` with a centre dot."""
    R = outer_mm / 2.0
    r_in = max(R - line_width_mm, 0.0)
    discs = [[R, 1.0], [r_in, -1.0]]
    if 0 < dot_mm / 2 < r_in:
        discs.append([dot_mm / 2, 1.0])
    return MarkShape(kind="circle-dot", rects=np.zeros((0, 3)), discs=np.array(discs))


def fiducial_shape(f: Fiducial) -> MarkShape:
    """The drawn shape of a certificate fiducial ("custom" is drawn as a cross)."""
    if f.shape == "dot":
        return dot_shape(f.size_mm)
    if f.shape == "circle-dot":
        return circle_dot_shape(f.size_mm, f.line_width_mm, f.dot_mm)
    return cross_shape(f.size_mm, min(f.line_width_mm, 0.5 * f.size_mm))


def _rect_integral(r0x, r0y, jx, jy, hx, hy) -> np.ndarray:
    """Exact area of a pixel covered by the rectangle |x| <= hx, |y| <= hy (film mm).

    The pixel is ``t, delta in [-0.5, 0.5]`` (pixel x, y offsets from its centre); a point of
    it lies at film ``r0 + jx t + jy delta`` relative to the rectangle's centre. On the line
    of a given ``delta`` the rectangle is an interval of ``t`` whose ends are linear in
    ``delta``, so the covered length is piecewise linear in ``delta``; it is integrated
    exactly by the trapezoid rule over all its break points.
    """
    # bounds of t from each slab: A + B * delta; lower and upper share the slope
    lows, ups = [], []
    for r, e, f, h in ((r0x, jx[:, 0], jy[:, 0], hx), (r0y, jx[:, 1], jy[:, 1], hy)):
        e = np.where(np.abs(e) < 1e-9, np.where(e < 0, -1e-9, 1e-9), e)
        a1 = (-h - r) / e
        a2 = (h - r) / e
        slope = -f / e
        lows.append((np.minimum(a1, a2), slope))
        ups.append((np.maximum(a1, a2), slope))
    n = len(r0x)
    zero = np.zeros(n)
    lows.append((np.full(n, -0.5), zero))
    ups.append((np.full(n, 0.5), zero))
    lines = lows + ups
    cuts = [np.full(n, -0.5), np.full(n, 0.5)]
    for i in range(len(lines)):
        for j in range(i + 1, len(lines)):
            (ai, bi), (aj, bj) = lines[i], lines[j]
            db = bi - bj
            with np.errstate(divide="ignore", invalid="ignore"):
                d = np.where(db != 0, (aj - ai) / np.where(db != 0, db, 1.0), -0.5)
            cuts.append(np.clip(d, -0.5, 0.5))
    delta = np.sort(np.column_stack(cuts), axis=1)  # (N, K)
    lo = np.max(np.stack([a[:, None] + b[:, None] * delta for a, b in lows]), axis=0)
    hi = np.min(np.stack([a[:, None] + b[:, None] * delta for a, b in ups]), axis=0)
    length = np.clip(hi - lo, 0.0, None)
    return np.sum(0.5 * (length[:, 1:] + length[:, :-1]) * np.diff(delta, axis=1), axis=1)


def _disc_integral(r0x, r0y, jx, jy, radius, subrows) -> np.ndarray:
    """Area of a pixel covered by the disc |p| <= radius: exact along t, midpoint rule in delta."""
    n = int(subrows)
    delta = (np.arange(n) + 0.5) / n - 0.5
    gx = r0x[:, None] + jy[:, 0:1] * delta
    gy = r0y[:, None] + jy[:, 1:2] * delta
    ex, ey = jx[:, 0:1], jx[:, 1:2]
    a = ex * ex + ey * ey
    b = 2.0 * (gx * ex + gy * ey)
    disc = b * b - 4.0 * a * (gx * gx + gy * gy - radius * radius)
    root = np.sqrt(np.clip(disc, 0.0, None))
    lo = (-b - root) / (2 * a)
    hi = (-b + root) / (2 * a)
    length = np.clip(np.minimum(hi, 0.5) - np.maximum(lo, -0.5), 0.0, None)
    return np.where(disc > 0, length, 0.0).mean(axis=1)


def coverage(
    film_mm: np.ndarray,
    jac_film_per_px: np.ndarray,
    centre_mm: np.ndarray,
    shape: MarkShape,
    subrows: int = 16,
) -> np.ndarray:
    """Fraction of each pixel covered by a mark.

    Rectangles (cross bars) are integrated exactly; discs exactly along pixel x and by an
    ``subrows``-point midpoint rule along pixel y.

    Parameters
    ----------
    film_mm : ndarray, shape (N, 2)
        Undeformed film mm of the pixel centres.
    jac_film_per_px : ndarray, shape (N, 2, 2)
        d(film mm)/d(pixel) at those pixels: column 0 along pixel x, column 1 along pixel y.
    centre_mm : ndarray, shape (N, 2) or (2,)
        Undeformed film mm of the mark centre each pixel belongs to.
    shape : MarkShape
        The mark's shape.
    subrows : int
        Sub-rows per pixel for discs.

    Returns
    -------
    ndarray, shape (N,)
        Covered fraction in [0, 1].
    """
    rel = np.asarray(film_mm, float) - np.asarray(centre_mm, float)
    jx = jac_film_per_px[:, :, 0]  # film mm per pixel x, (N, 2)
    jy = jac_film_per_px[:, :, 1]
    total = np.zeros(len(rel))
    for hx, hy, sign in shape.rects:
        total += sign * _rect_integral(rel[:, 0], rel[:, 1], jx, jy, hx, hy)
    for r, sign in shape.discs:
        total += sign * _disc_integral(rel[:, 0], rel[:, 1], jx, jy, r, subrows)
    return np.clip(total, 0.0, 1.0)


def _band(rel: np.ndarray, margin: np.ndarray, shape: MarkShape) -> np.ndarray:
    """Pixels whose footprint may touch the shape; rel (N, 2) film mm from the centre."""
    keep = np.zeros(len(rel), bool)
    ax, ay = np.abs(rel[:, 0]), np.abs(rel[:, 1])
    for hx, hy, sign in shape.rects:
        if sign > 0:
            keep |= (ax <= hx + margin) & (ay <= hy + margin)
    for r, sign in shape.discs:
        if sign > 0:
            keep |= np.hypot(rel[:, 0], rel[:, 1]) <= r + margin
    return keep


def render_marks(
    mapping,
    centres_mm: np.ndarray,
    shape: MarkShape,
    subrows: int = 16,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Coverage of marks of one shape at the given film positions, as sparse pixel lists.

    Parameters
    ----------
    mapping : TruthMapping
        The scan's complete film mm <-> pixel mapping.
    centres_mm : ndarray, shape (M, 2)
        Undeformed film mm of the mark centres.
    shape : MarkShape
        Shape shared by these marks.
    subrows : int
        Sub-rows per pixel (see :func:`coverage`).

    Returns
    -------
    index : ndarray of int, shape (K,)
        Which mark (0..M-1) each entry belongs to.
    col, row : ndarray of int, shape (K,)
        Pixel column and row (pixel system; may lie outside the image).
    cov : ndarray of float, shape (K,)
        Covered fraction of the pixel, > 0.
    """
    centres = np.asarray(centres_mm, float).reshape(-1, 2)
    m = len(centres)
    if m == 0:
        e = np.zeros(0, int)
        return e, e, e, np.zeros(0)
    p0 = mapping.film_to_pixel(centres)  # (M, 2) px
    jac = mapping.jacobian(centres)  # (M, 2, 2) px per mm
    jinv = np.linalg.inv(jac)  # mm per px
    # window half size in px: image of the bounding circle through the local affine
    rad = shape.radius_mm
    half = int(np.ceil(rad * np.max(np.linalg.norm(jac, axis=2)) * 1.01)) + 2
    off = np.arange(-half, half + 1)
    base = np.round(p0).astype(int)  # (M, 2)
    cols = base[:, 0, None, None] + off[None, None, :]  # (M, 1, S)
    rows = base[:, 1, None, None] + off[None, :, None]  # (M, S, 1)
    cols, rows = np.broadcast_arrays(cols, rows)
    idx = np.broadcast_to(np.arange(m)[:, None, None], cols.shape)
    cols, rows, idx = cols.ravel(), rows.ravel(), idx.ravel()
    dp = np.column_stack([cols - p0[idx, 0], rows - p0[idx, 1]])
    rel = np.einsum("nab,nb->na", jinv[idx], dp)  # approx film mm from the centre
    margin = 0.5 * (np.linalg.norm(jinv[idx, :, 0], axis=1) + np.linalg.norm(jinv[idx, :, 1], axis=1))
    keep = _band(rel, margin * 1.05 + 1e-9, shape)
    cols, rows, idx = cols[keep], rows[keep], idx[keep]
    # exact film coordinates of the selected pixel centres and the local Jacobian
    film = mapping.pixel_to_film(np.column_stack([cols, rows]).astype(float))
    jac_px = mapping.jacobian(film)
    det = jac_px[:, 0, 0] * jac_px[:, 1, 1] - jac_px[:, 0, 1] * jac_px[:, 1, 0]
    jfp = np.empty_like(jac_px)
    jfp[:, 0, 0] = jac_px[:, 1, 1] / det
    jfp[:, 1, 1] = jac_px[:, 0, 0] / det
    jfp[:, 0, 1] = -jac_px[:, 0, 1] / det
    jfp[:, 1, 0] = -jac_px[:, 1, 0] / det
    cov = coverage(film, jfp, centres[idx], shape, subrows)
    nz = cov > 0
    return idx[nz], cols[nz], rows[nz], cov[nz]
