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
                pts += list(zip(r * np.cos(ang), r * np.sin(ang), strict=False))
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
    lo = hi = None
    for a, b in lows:
        v = a[:, None] + b[:, None] * delta
        lo = v if lo is None else np.maximum(lo, v, out=lo)
    for a, b in ups:
        v = a[:, None] + b[:, None] * delta
        hi = v if hi is None else np.minimum(hi, v, out=hi)
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


def _inv2(j: np.ndarray) -> np.ndarray:
    """Inverse of a stack of 2 x 2 matrices (N, 2, 2)."""
    det = j[:, 0, 0] * j[:, 1, 1] - j[:, 0, 1] * j[:, 1, 0]
    out = np.empty_like(j)
    out[:, 0, 0] = j[:, 1, 1] / det
    out[:, 1, 1] = j[:, 0, 0] / det
    out[:, 0, 1] = -j[:, 0, 1] / det
    out[:, 1, 0] = -j[:, 1, 0] / det
    return out


def area_coverage(
    mapping,
    centres_mm: np.ndarray,
    shape: MarkShape,
    subrows: int = 16,
    affine: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Exact area coverage of marks of one shape, as sparse pixel lists.

    Parameters
    ----------
    mapping : TruthMapping
        The scan's complete film mm <-> pixel mapping.
    centres_mm : ndarray, shape (M, 2)
        Undeformed film mm of the mark centres.
    shape : MarkShape
        Shape shared by these marks.
    subrows : int
        Sub-rows per pixel for discs (see :func:`coverage`).
    affine : bool
        Map through each mark's local affine (the mapping's value and Jacobian at the mark
        centre) instead of the full mapping.

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
    jinv = _inv2(jac)  # mm per px
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
    rel = np.einsum("nab,nb->na", jinv[idx], dp)  # local-affine film mm from the centre
    margin = 0.5 * (np.linalg.norm(jinv[idx, :, 0], axis=1)
                    + np.linalg.norm(jinv[idx, :, 1], axis=1))
    keep = _band(rel, margin * 1.05 + 1e-9, shape)
    cols, rows, idx, rel = cols[keep], rows[keep], idx[keep], rel[keep]
    if affine:
        film = centres[idx] + rel
        jfp = jinv[idx]
    else:  # exact film coordinates of the pixel centres and the local Jacobian there
        film = mapping.pixel_to_film(np.column_stack([cols, rows]).astype(float))
        jfp = _inv2(mapping.jacobian(film))
    cov = coverage(film, jfp, centres[idx], shape, subrows)
    nz = cov > 0
    return idx[nz], cols[nz], rows[nz], cov[nz]


#: below this blur (px) marks are area-sampled and blurred discretely with the image
MIN_FOURIER_SIGMA = 0.4


def _sinc(x: np.ndarray) -> np.ndarray:
    """sin(pi x) / (pi x), float32 in and out."""
    y = np.float32(np.pi) * x
    safe = np.where(y == 0, np.float32(1.0), y)
    return np.where(y == 0, np.float32(1.0), np.sin(safe) / safe)


def _spectrum(shape: MarkShape, ex: np.ndarray, ey: np.ndarray) -> np.ndarray:
    """Fourier transform of the shape's indicator at film frequencies (ex, ey) cycles/mm."""
    out = np.zeros(np.broadcast_shapes(ex.shape, ey.shape), np.float32)
    cache: dict[tuple[int, float], np.ndarray] = {}

    def sinc_of(axis: int, h: float) -> np.ndarray:
        key = (axis, float(h))
        if key not in cache:
            cache[key] = _sinc(np.float32(2 * h) * (ex if axis == 0 else ey))
        return cache[key]

    for hx, hy, sign in shape.rects:
        out += np.float32(sign * 4 * hx * hy) * sinc_of(0, hx) * sinc_of(1, hy)
    if len(shape.discs):
        from scipy.special import j1

        rho = np.hypot(ex, ey)
        safe = np.where(rho > 0, rho, np.float32(1.0))
        for r, sign in shape.discs:
            val = np.where(rho > 0, r * j1(np.float32(2 * np.pi * r) * safe) / safe, np.pi * r * r)
            out += np.float32(sign) * val.astype(np.float32)
    return out


def _fold(a: np.ndarray, w: int, jmax: int, axis: int) -> np.ndarray:
    """Sum frequency samples j = -jmax..jmax (along ``axis``) onto DFT bins j mod w."""
    n = a.shape[axis]
    p = -(-n // w) * w
    pad = [(0, 0)] * a.ndim
    pad[axis] = (0, p - n)
    a = np.pad(a, pad)
    shp = a.shape[:axis] + (p // w, w) + a.shape[axis + 1 :]
    return np.roll(a.reshape(shp).sum(axis=axis), -jmax, axis=axis)


def blurred_windows(
    p0: np.ndarray,
    jac: np.ndarray,
    shape: MarkShape,
    sigma: float,
    eps: float = 1e-8,
    chunk_values: int = 2_000_000,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact images of affine-mapped marks through a Gaussian optic and a pixel-box sensor.

    The value of pixel ``n`` is ``(c * G_sigma * box)(n)``: the mark's indicator ``c`` (the
    shape mapped by ``pixel = p0 + jac (film - centre)``) blurred by a Gaussian of ``sigma`` px
    and integrated over the unit pixel. It is computed from the closed-form Fourier transform
    (``sinc`` for rectangles, ``J1`` for discs) on a frequency grid fine enough for the window
    (spacing 1/W) and wide enough for the Gaussian (up to where it falls below ``eps``),
    folded (aliased exactly as point sampling does) and inverted by one FFT per mark.

    Parameters
    ----------
    p0 : ndarray, shape (M, 2)
        Pixel position of each mark centre.
    jac : ndarray, shape (M, 2, 2)
        d(pixel)/d(film mm) at each mark centre.
    shape : MarkShape
        The shape (undeformed film mm).
    sigma : float
        Gaussian blur, pixels (>= MIN_FOURIER_SIGMA).

    Returns
    -------
    windows : ndarray, shape (M, W, W)
        Pixel values (coverage units: a pixel wholly inside the mark, unblurred, is 1).
    origin : ndarray of int, shape (M, 2)
        Pixel (col, row) of each window's element [0, 0].
    """
    m = len(p0)
    outline = shape.outline_mm()
    ext = np.abs(np.einsum("mab,kb->mka", jac, outline)).max(axis=(0, 1))  # (2,) px
    half = int(np.ceil(max(ext) + 0.5 + 5 * sigma)) + 3
    w = 2 * half
    origin = np.round(p0).astype(int) - half
    q = p0 - origin  # mark centre in window coordinates
    kmax = np.sqrt(np.log(1 / eps) / (2 * np.pi**2 * sigma**2))
    jmax = int(np.ceil(kmax * w))
    j = np.arange(-jmax, jmax + 1)
    xi = j / w  # cycles per px
    filt = (np.exp(-2 * np.pi**2 * sigma**2 * xi**2) * np.sinc(xi)).astype(np.float32)
    det = np.abs(jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0])
    out = np.empty((m, w, w))
    n = len(j)
    step = max(1, chunk_values // (n * n))
    xr = xi.astype(np.float32)[None, None, :]
    yr = xi.astype(np.float32)[None, :, None]
    for a in range(0, m, step):
        b = min(m, a + step)
        jt = jac[a:b].astype(np.float32)
        # film frequency eta = jac^T xi: eta_x = J00 xi_x + J10 xi_y, eta_y = J01 xi_x + J11 xi_y
        etx = jt[:, 0, 0, None, None] * xr + jt[:, 1, 0, None, None] * yr
        ety = jt[:, 0, 1, None, None] * xr + jt[:, 1, 1, None, None] * yr
        spec = _spectrum(shape, etx, ety)
        gain = det[a:b, None, None] * filt[None, None, :] * filt[None, :, None]
        spec *= gain.astype(np.float32)
        phx = np.exp(-2j * np.pi * xi[None, :] * q[a:b, 0, None]).astype(np.complex64)  # (B, n)
        phy = np.exp(-2j * np.pi * xi[None, :] * q[a:b, 1, None]).astype(np.complex64)
        # fold frequency j onto DFT bin j mod W (the exact aliasing of point sampling)
        fx = _fold(spec * phx[:, None, :], w, jmax, axis=2)  # (B, n, W)
        folded = _fold(fx * phy[:, :, None], w, jmax, axis=1)  # (B, W, W)
        out[a:b] = np.fft.ifft2(folded.astype(np.complex128)).real
    return out, origin


def _edges(shape: MarkShape) -> list[tuple]:
    """Boundary pieces of every primitive: (start, end or None, normal-or-None, sign).

    Rectangles give four straight edges ``(a, b, n, sign)`` (film mm, outward normal);
    discs one circle ``(radius, None, None, sign)``.
    """
    out = []
    for hx, hy, sign in shape.rects:
        for a, b, n in (
            ((-hx, hy), (hx, hy), (0.0, 1.0)),
            ((hx, -hy), (-hx, -hy), (0.0, -1.0)),
            ((hx, hy), (hx, -hy), (1.0, 0.0)),
            ((-hx, -hy), (-hx, hy), (-1.0, 0.0)),
        ):
            out.append((np.array(a), np.array(b), np.array(n), float(sign)))
    for r, sign in shape.discs:
        out.append((np.array(float(r)), None, None, float(sign)))
    return out


def _p1d(t: np.ndarray, sigma: float) -> np.ndarray:
    """1-D PSF: Gaussian(sigma) convolved with the unit pixel box, at offsets t (px)."""
    from scipy.special import erf

    k = 1.0 / (np.sqrt(2.0) * sigma)
    return 0.5 * (erf((t + 0.5) * k) - erf((t - 0.5) * k))


def curvature_windows(
    mapping,
    centres_mm: np.ndarray,
    shape: MarkShape,
    p0: np.ndarray,
    jac: np.ndarray,
    sigma: float,
    origin: np.ndarray,
    w: int,
    step_px: float = 0.5,
) -> np.ndarray:
    """The image of the difference between each mark through the full mapping and through
    its local affine, blurred by the Gaussian optics and the pixel box.

    The full mapping moves the boundary of the affine-mapped mark by
    ``delta = film_to_pixel(f) - (p0 + jac (f - c))`` (a few 1e-3 px); to first order in
    ``delta`` the indicator changes by a layer on the boundary of density ``delta . n``
    (outward normal, pixel length by Nanson's formula ``|det J| J^-T n_film``). That layer is
    integrated along every edge (nodes every ``step_px``) against the separable PSF. The
    neglected second order is ~delta^2 / sigma, below 1e-4 of the mark's signal.

    Returns
    -------
    ndarray, shape (M, W, W)
        Correction to add to :func:`blurred_windows` (coverage units).
    """
    m = len(centres_mm)
    out = np.zeros((m, w, w))
    det = np.abs(jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0])
    jinv_t = np.transpose(_inv2(jac), (0, 2, 1))  # J^-T
    scale = float(np.max(np.linalg.norm(jac, axis=1)))  # px per mm, upper bound
    h = min(step_px, sigma / 1.5)  # midpoint rule on a Gaussian-smooth integrand
    half = int(np.ceil(3.5 * sigma + 1.0))
    offs = np.arange(-half, half + 1)
    for a, b, n, sign in _edges(shape):
        if b is None:  # circle of radius a
            r = float(a)
            k = max(16, int(np.ceil(2 * np.pi * r * scale / h)))
            th = (np.arange(k) + 0.5) * (2 * np.pi / k)
            rel = r * np.column_stack([np.cos(th), np.sin(th)])  # (K, 2) film mm
            nrm = np.column_stack([np.cos(th), np.sin(th)])
            ds = np.full(k, 2 * np.pi * r / k)
        else:
            length = float(np.hypot(*(b - a)))
            k = max(2, int(np.ceil(length * scale / h)))
            t = (np.arange(k) + 0.5) / k
            rel = a[None, :] + t[:, None] * (b - a)[None, :]
            nrm = np.broadcast_to(n, rel.shape)
            ds = np.full(k, length / k)
        film = centres_mm[:, None, :] + rel[None, :, :]  # (M, K, 2)
        exact = mapping.film_to_pixel(film.reshape(-1, 2)).reshape(film.shape)
        affine = p0[:, None, :] + np.einsum("mab,kb->mka", jac, rel)
        delta = exact - affine  # (M, K, 2) px
        npx = np.einsum("mab,kb->mka", jinv_t, nrm) * det[:, None, None]  # (M, K, 2)
        weight = sign * np.einsum("mka,mka->mk", delta, npx) * ds[None, :]  # (M, K) px^2
        # splat the weighted nodes through the separable PSF into each window
        sx = affine[:, :, 0] - origin[:, None, 0]  # window coordinates of the nodes
        sy = affine[:, :, 1] - origin[:, None, 1]
        cols = np.floor(sx).astype(int)[:, :, None] + offs  # (M, K, S)
        rows = np.floor(sy).astype(int)[:, :, None] + offs
        px = _p1d(cols - sx[:, :, None], sigma) * weight[:, :, None]
        py = _p1d(rows - sy[:, :, None], sigma)
        cols = np.clip(cols, 0, w - 1)
        rows = np.clip(rows, 0, w - 1)
        mk = np.broadcast_to(np.arange(m)[:, None, None, None], (m, k, len(offs), len(offs)))
        flat = (mk * w + rows[:, :, :, None]) * w + cols[:, :, None, :]
        vals = py[:, :, :, None] * px[:, :, None, :]
        out += np.bincount(flat.ravel(), vals.ravel(), minlength=m * w * w).reshape(m, w, w)
    return out


def render_marks(
    mapping,
    centres_mm: np.ndarray,
    shape: MarkShape,
    blur_sigma_px: float,
    subrows: int = 16,
    curvature: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:
    """Images of marks of one shape, as sparse pixel lists.

    With ``blur_sigma_px >= MIN_FOURIER_SIGMA`` the marks are imaged physically - blurred by
    the optics *before* the sensor samples them - so that a sampled mark's intensity
    centroid is its true position (to the aliasing of a band-limited image, ~1e-5 px). The
    mark through its local affine (exact value and Jacobian of the mapping at its centre) is
    rendered in closed form by :func:`blurred_windows`; the remaining curvature of the
    mapping across the mark (its boundary moves by a few 1e-3 px against the local affine) is
    added by :func:`curvature_windows`, to first order and through the same PSF. Against an
    independent quadrature of the deformed mark's centroid over its film shape this agrees
    to 1e-5 px. Below that blur the marks are exact-area coverage through the full mapping
    (to be blurred with the image).

    Parameters
    ----------
    mapping : TruthMapping
        The scan's complete film mm <-> pixel mapping.
    centres_mm : ndarray, shape (M, 2)
        Undeformed film mm of the mark centres.
    shape : MarkShape
        Shape shared by these marks.
    blur_sigma_px : float
        Scanner Gaussian blur, pixels.
    subrows : int
        Sub-rows per pixel for discs in the area coverage.
    curvature : bool
        Add the curvature term (skip it only when the mapping is affine).

    Returns
    -------
    index, col, row : ndarray of int, shape (K,)
        Mark (0..M-1), pixel column and row of each entry (pixel system, may be outside).
    value : ndarray of float, shape (K,)
        Mark weight of the pixel (coverage units).
    blurred : bool
        True if the values are already blurred (add them after the image blur).
    """
    centres = np.asarray(centres_mm, float).reshape(-1, 2)
    m = len(centres)
    if m == 0 or blur_sigma_px < MIN_FOURIER_SIGMA:
        return (*area_coverage(mapping, centres, shape, subrows), False)
    p0 = mapping.film_to_pixel(centres)
    jac = mapping.jacobian(centres)
    win, origin = blurred_windows(p0, jac, shape, blur_sigma_px)
    if curvature:
        win += curvature_windows(mapping, centres, shape, p0, jac, blur_sigma_px, origin,
                                 win.shape[1])
    idx, rr, cc = np.nonzero(np.abs(win) > 1e-9)
    return idx, cc + origin[idx, 0], rr + origin[idx, 1], win[idx, rr, cc], True
