"""Robust reseau-grid fit: lattice from candidate peaks, row/col assignment, projective model.

From NCC candidate peaks (pixel system) that contain the reseau crosses and any number of
false peaks (scene features), this module finds

1. the lattice scale (px per mm; estimated from the nearest-neighbour spacing when the dpi is
   unknown) and rotation (any angle within +-45 degrees of the ``rotate`` hint, i.e. the
   quarter turn the user states) from the difference vectors between neighbouring peaks;
2. the lattice phase by voting (every strong peak proposes itself as a lattice node; the one
   with most peaks on its lattice wins) and an affine lattice fitted to the peaks within a
   quarter of a pitch of a node (scale, rotation, anisotropy, offset);
3. the absolute row/column numbers: the shift of the relative indices that puts most peak
   score on the certificate's grid while predicting no unseen cross inside the image;
4. a projective film-mm -> pixel model by iterated least squares with rejection over the assigned
   peaks, refined by least squares on its inliers.

Film coordinates (mm): x right, y up, reseau row 0 on top. Pixel coordinates: x right, y down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from softplot.camera import Reseau
from softplot.marks import kernels
from softplot.runtime import concurrent, thread_map, threads

__all__ = ["GridFit", "Lattice", "Identification", "fit_grid", "find_lattice", "identify",
           "projective_model", "projective_fit", "apply_h", "h_jacobian", "estimate_spacing"]


def apply_h(H: np.ndarray, xy) -> np.ndarray:
    """Apply a 3x3 projective transform to points (N, 2)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    w = H[2, 0] * xy[:, 0] + H[2, 1] * xy[:, 1] + H[2, 2]
    x = (H[0, 0] * xy[:, 0] + H[0, 1] * xy[:, 1] + H[0, 2]) / w
    y = (H[1, 0] * xy[:, 0] + H[1, 1] * xy[:, 1] + H[1, 2]) / w
    return np.column_stack([x, y])


def h_jacobian(H: np.ndarray, xy) -> np.ndarray:
    """Jacobian d(output)/d(input) of a projective transform at points (N, 2): (N, 2, 2)."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    w = H[2, 0] * xy[:, 0] + H[2, 1] * xy[:, 1] + H[2, 2]
    out = apply_h(H, xy)
    J = np.empty((len(xy), 2, 2))
    for i in range(2):
        for j in range(2):
            J[:, i, j] = (H[i, j] - out[:, i] * H[2, j]) / w
    return J


def projective_fit(src, dst, weights=None) -> np.ndarray:
    """Least-squares projective transform src -> dst (normalised DLT, then Gauss-Newton).

    Falls back to an affine transform for fewer than 5 points (3 or 4 points).
    """
    src = np.asarray(src, float)
    dst = np.asarray(dst, float)
    n = len(src)
    if n < 5 or np.linalg.matrix_rank(src - src.mean(0), tol=1e-9 * (np.abs(src).max() + 1)) < 2:
        A = _affine_fit(src, dst)
        return np.vstack([A, [0.0, 0.0, 1.0]])
    Hm = _dlt(src, dst)
    if Hm is None:
        return np.vstack([_affine_fit(src, dst), [0.0, 0.0, 1.0]])
    wts = np.ones(n) if weights is None else np.asarray(weights, float)
    # Gauss-Newton on the 8 parameters (geometric error in dst units); the DLT start is kept
    # if the iteration misbehaves (degenerate point sets)
    h0 = Hm.ravel()[:8].copy()
    h = h0.copy()
    with np.errstate(all="ignore"):
        for _ in range(5):
            Hc = np.append(h, 1.0).reshape(3, 3)
            x, y = src[:, 0], src[:, 1]
            w = Hc[2, 0] * x + Hc[2, 1] * y + 1.0
            if not np.all(np.abs(w) > 1e-9):
                return np.append(h0, 1.0).reshape(3, 3)
            px = (Hc[0, 0] * x + Hc[0, 1] * y + Hc[0, 2]) / w
            py = (Hc[1, 0] * x + Hc[1, 1] * y + Hc[1, 2]) / w
            r = np.concatenate([dst[:, 0] - px, dst[:, 1] - py])
            z = np.zeros(n)
            o = np.ones(n)
            Jx = np.column_stack([x / w, y / w, o / w, z, z, z, -px * x / w, -px * y / w])
            Jy = np.column_stack([z, z, z, x / w, y / w, o / w, -py * x / w, -py * y / w])
            J = np.vstack([Jx, Jy])
            W = np.sqrt(np.concatenate([wts, wts]))
            if not (np.isfinite(J).all() and np.isfinite(r).all()):
                return np.append(h0, 1.0).reshape(3, 3)
            try:
                dh = np.linalg.lstsq(J * W[:, None], r * W, rcond=None)[0]
            except np.linalg.LinAlgError:
                return np.append(h0, 1.0).reshape(3, 3)
            h += dh
            if np.abs(dh).max() < 1e-12:
                break
    if not np.isfinite(h).all():
        h = h0
    return np.append(h, 1.0).reshape(3, 3)


def _normaliser(p):
    m = p.mean(0)
    d = np.sqrt(((p - m) ** 2).sum(1).mean()) or 1.0
    k = np.sqrt(2.0) / d
    return np.array([[k, 0.0, -k * m[0]], [0.0, k, -k * m[1]], [0.0, 0.0, 1.0]])


def _dlt(src, dst) -> np.ndarray | None:
    """Normalised direct linear transform (Hartley) src -> dst, H[2, 2] = 1."""
    Ts, Td = _normaliser(src), _normaliser(dst)
    s = src @ Ts[:2, :2].T + Ts[:2, 2]
    d = dst @ Td[:2, :2].T + Td[:2, 2]
    n = len(s)
    A = np.zeros((2 * n, 9))
    A[0::2, 0:2] = s
    A[0::2, 2] = 1.0
    A[0::2, 6:8] = -d[:, 0:1] * s
    A[0::2, 8] = -d[:, 0]
    A[1::2, 3:5] = s
    A[1::2, 5] = 1.0
    A[1::2, 6:8] = -d[:, 1:2] * s
    A[1::2, 8] = -d[:, 1]
    h = np.linalg.svd(A, full_matrices=False)[2][-1]
    H = np.linalg.inv(Td) @ h.reshape(3, 3) @ Ts
    if not np.isfinite(H).all() or abs(H[2, 2]) < 1e-15:
        return None
    return H / H[2, 2]


def _affine_fit(src, dst) -> np.ndarray:
    M = np.column_stack([src, np.ones(len(src))])
    sol = np.linalg.lstsq(M, dst, rcond=None)[0]
    return sol.T


def estimate_spacing(xy: np.ndarray) -> float | None:
    """Most frequent nearest-neighbour distance (px) among points: the lattice pitch."""
    if len(xy) < 4:
        return None
    # a peak found twice at one place (within 2 px) is not its own neighbour
    d, _ = cKDTree(xy).query(xy, k=min(4, len(xy)))
    d = np.where(d[:, 1:] > 2.0, d[:, 1:], np.inf).min(axis=1)
    nn = np.sort(d[np.isfinite(d)])
    if len(nn) < 3:
        return None
    lo = np.searchsorted(nn, nn * 0.95)
    hi = np.searchsorted(nn, nn * 1.05, side="right")
    i = int(np.argmax(hi - lo))
    if hi[i] - lo[i] < 3:
        return None
    return float(np.median(nn[lo[i] : hi[i]]))


@dataclass
class GridFit:
    """Result of :func:`fit_grid`.

    Attributes
    ----------
    H : (3, 3) ndarray
        Projective film mm -> pixel.
    index : (K,) int
        Candidate peaks assigned to crosses.
    node : (K,) int
        Their cross index (row-major, as :meth:`Reseau.film`).
    px_per_mm : float
        Mean scale.
    rotation_deg : float
        Rotation of the film x axis in the pixel system (degrees, pixel x towards pixel y).
    rms : float
        RMS residual (px) of the assigned peaks against ``H``.
    score : float
        Sum of the assigned peaks' scores above the clutter's (the median of the scores of
        the peaks off the lattice), in units of the clutter's spread (its 90th percentile
        less its median, at least 0.05).
    ambiguous : bool
        Other row/col shifts fit the crosses and the format's edges as well (a strip through
        the grid, or a dark region over the outer row that hides the format's edge too):
        the best-fitting one (the one nearest the scan's centre among equals) was taken.
    """

    H: np.ndarray
    index: np.ndarray
    node: np.ndarray
    px_per_mm: float
    rotation_deg: float
    rms: float
    score: float
    ambiguous: bool = False


def _random_triplets(rng: np.random.Generator, n: int, count: int) -> np.ndarray:
    """``count`` random triplets of distinct indices in ``[0, n)`` (``n >= 3``), (count, 3)."""
    out = np.empty((0, 3), np.int64)
    while len(out) < count:
        t = rng.integers(0, n, (2 * count, 3))
        t = t[(t[:, 0] != t[:, 1]) & (t[:, 0] != t[:, 2]) & (t[:, 1] != t[:, 2])]
        out = np.concatenate([out, t])
    return out[:count]


def _fold(a: np.ndarray, period: float) -> np.ndarray:
    return (a + 0.5 * period) % period - 0.5 * period


#: bins per lattice pitch of the phase histogram of :func:`_lattice_search` (the true
#: lattice's peaks fall in a window of 2 x 2 bins: an eighth of a pitch)
PHASE_BINS = 16


def _phase_histograms(d, w, lx, ly, thetas):
    """Score-weighted histograms of the lattice phase of points ``d`` (N, 2) (pixel offsets
    from a reference) for lattices of pitch ``lx`` x ``ly`` px turned by each of ``thetas``
    (A,) radians: (A, PHASE_BINS, PHASE_BINS), summed over 2 x 2 bins (circularly).
    Compiled where numba works (:func:`_phase_bins`: the same values to the bit)."""
    if kernels.ready():
        Hs = np.zeros((len(thetas), PHASE_BINS, PHASE_BINS))
        _phase_bins(np.ascontiguousarray(d, float), np.ascontiguousarray(
            np.broadcast_to(w, len(d)), float), float(lx), float(ly), np.cos(thetas),
            np.sin(thetas), Hs)
    else:
        Hs = _phase_counts(d, w, lx, ly, thetas)
    Hs = Hs + np.roll(Hs, -1, 1)
    return Hs + np.roll(Hs, -1, 2)


def _phase_counts(d, w, lx, ly, thetas):
    """The histograms of :func:`_phase_histograms` before the 2 x 2 sums, with NumPy (the
    compiled pass's reference): (A, PHASE_BINS, PHASE_BINS)."""
    nb = PHASE_BINS
    ct, st = np.cos(thetas)[:, None], np.sin(thetas)[:, None]
    u = (d[None, :, 0] * ct + d[None, :, 1] * st) / lx
    v = (-d[None, :, 0] * st + d[None, :, 1] * ct) / ly
    bu = np.floor((u - np.floor(u)) * nb).astype(np.int64) % nb
    bv = np.floor((v - np.floor(v)) * nb).astype(np.int64) % nb
    key = (np.arange(len(thetas))[:, None] * nb + bu) * nb + bv
    return np.bincount(key.ravel(), weights=np.broadcast_to(w, key.shape).ravel(),
                       minlength=len(thetas) * nb * nb).reshape(len(thetas), nb, nb)


@kernels.on_load
def _warm() -> None:
    """Compile (or load from numba's cache) :func:`_phase_bins` on a tiny input
    (:func:`softplot.marks.kernels.load` calls it)."""
    _phase_bins(np.zeros((1, 2)), np.ones(1), 1.0, 1.0, np.ones(1), np.zeros(1),
                np.zeros((1, PHASE_BINS, PHASE_BINS)))


@kernels.njit(cache=True, nogil=True)
def _phase_bins(d, w, lx, ly, ct, st, out):
    # _phase_counts' arithmetic point by point, rotation by rotation (the order bincount adds
    # in): d (N, 2) pixel offsets, w (N,), ct, st (A,) the rotations' cosines and sines, out
    # (A, nb, nb) zeros
    nb = out.shape[1]
    for a in range(ct.size):
        for n in range(d.shape[0]):
            u = (d[n, 0] * ct[a] + d[n, 1] * st[a]) / lx
            v = (-d[n, 0] * st[a] + d[n, 1] * ct[a]) / ly
            bu = int(np.floor((u - np.floor(u)) * nb)) % nb
            bv = int(np.floor((v - np.floor(v)) * nb)) % nb
            out[a, bu, bv] += w[n]


#: a peak agrees with a lattice within this (film mm, at least 3 px): the coarse peaks'
#: error and the film's deformation from an affine lattice; a lattice through clutter
#: rarely meets it at many nodes
AGREE_MM = 0.15
#: phase-histogram maxima of :func:`_lattice_search` tried as lattices: a small grid's crosses
#: pile up no higher than clutter does by chance, the consensus of :func:`find_lattice` decides
HYPOTHESES = 24


def _lattice_search(xy, score, lx, ly, rotate_deg, max_rotation_deg, square,
                    k=HYPOTHESES):
    """Rotations and phases of the lattice of pitch ``lx`` x ``ly`` px that most candidate
    peaks lie on.

    For every rotation within ``max_rotation_deg`` of ``rotate_deg`` (pixel system, degrees;
    a quarter turn folds a square lattice onto itself), the peaks' lattice phases (their
    lattice coordinates modulo one pitch) are histogrammed, weighted by their scores: on the
    reseau's rotation its crosses pile up in one cell of an eighth of a pitch, where clutter
    (scene features, JPEG block corners, grain, noise over flat regions) spreads over all
    phases. The step of the rotations keeps the farthest peak within a tenth of a pitch.
    The ``k`` highest cells (apart by more than a step of rotation or a cell of phase) are
    refined five times finer in rotation. The spacing is never searched: it is the
    certificate's at the given dpi. Returns a list of (theta radians, p0 (2,) a pixel
    position of a lattice node, peaks in the cell), the highest cell first (empty when none
    is found).
    """
    M = len(xy)
    if M < 3:
        return []
    top = np.argsort(-score)[: min(M, 4000)]
    xy, score = xy[top], score[top]
    w = np.maximum(score, 0.0)
    c = np.average(xy, axis=0, weights=w + 1e-12)
    d = xy - c
    extent = float(np.percentile(np.hypot(d[:, 0] / lx, d[:, 1] / ly), 95)) + 1.0
    step = min(0.1 / extent, np.radians(0.5))
    half = np.radians(min(max_rotation_deg, 44.9 if square else 89.9))
    n = int(np.ceil(half / step))
    thetas = np.radians(rotate_deg) + np.arange(-n, n + 1) * step
    Hs = _histograms(d, w, lx, ly, thetas)
    out = []
    cells = _top_cells(Hs, k)
    # five times finer around each, the highest cell within a bin of it: the fine rotations
    # of every cell histogrammed at once (each rotation's histogram is its own)
    sub = np.linspace(-step, step, 11)
    fines = [thetas[a] + sub for a, _ in cells]
    Hall = _histograms(d, w, lx, ly, np.concatenate(fines)) if cells else None
    for i, (_, cell) in enumerate(cells):
        fine = fines[i]
        Hf = Hall[11 * i : 11 * (i + 1)]
        nb = PHASE_BINS
        near = np.zeros((nb, nb), bool)
        for du in (-1, 0, 1):
            for dv in (-1, 0, 1):
                near[(cell[0] + du) % nb, (cell[1] + dv) % nb] = True
        af = int(np.argmax(np.where(near[None], Hf, -np.inf).reshape(len(fine), -1).max(1)))
        Hb = np.where(near, Hf[af], -np.inf)
        bu, bv = np.unravel_index(int(np.argmax(Hb)), Hb.shape)
        got = _phase_node(d, w, lx, ly, float(fine[af]), bu, bv)
        if got is not None:
            out.append((float(fine[af]), c + got[0], got[1]))
    return out


def _histograms(d, w, lx, ly, thetas):
    """:func:`_phase_histograms` of every rotation of ``thetas``, a few at a time (bounded
    work arrays): (A, PHASE_BINS, PHASE_BINS)."""
    chunk = max(1, 2_000_000 // max(len(d), 1))
    return np.concatenate([_phase_histograms(d, w, lx, ly, thetas[k: k + chunk])
                           for k in range(0, len(thetas), chunk)])


def _top_cells(Hs, k):
    """The ``k`` highest (rotation index, (bin u, bin v)) of the histograms ``Hs``
    (A, nb, nb), each apart from the ones before by more than one rotation step or one
    bin of phase (circularly): the highest first."""
    A, nb = Hs.shape[0], Hs.shape[1]
    order = np.argsort(-Hs.ravel(), kind="stable")[: max(64 * k, 256)]
    # the cells within a step of rotation and a bin of phase of a picked one are blocked: the
    # next pick is the first cell of ``order`` not blocked (the same picks as testing each
    # cell against every picked one, without a Python loop over the cells)
    blocked = np.zeros(Hs.shape, bool)
    flat = blocked.reshape(-1)
    picked = []
    pos = 0
    while len(picked) < k and pos < len(order):
        free = ~flat[order[pos:]]
        if not free.any():
            break
        pos += int(np.argmax(free))
        a, u, v = (int(x) for x in np.unravel_index(int(order[pos]), Hs.shape))
        picked.append((a, (u, v)))
        blocked[np.ix_(np.arange(max(a - 1, 0), min(a + 2, A)),
                       np.array([u - 1, u, u + 1]) % nb, np.array([v - 1, v, v + 1]) % nb)] = True
        pos += 1
    return picked


def _phase_node(d, w, lx, ly, theta, bu, bv):
    """A lattice node (pixel offset like ``d``) of the lattice turned by ``theta`` whose
    phase lies in the 2 x 2 cell of bins from (bu, bv): the circular mean of the phases of
    the peaks in it, and their number. None when fewer than 2 peaks are there."""
    nb = PHASE_BINS
    ct, st = np.cos(theta), np.sin(theta)
    u = (d[:, 0] * ct + d[:, 1] * st) / lx
    v = (-d[:, 0] * st + d[:, 1] * ct) / ly
    fu, fv = u - np.floor(u), v - np.floor(v)
    cu, cv = (bu + 1.0) / nb, (bv + 1.0) / nb  # the cell's centre (phase units)
    du, dv = (fu - cu + 0.5) % 1.0 - 0.5, (fv - cv + 0.5) % 1.0 - 0.5
    near = (np.abs(du) <= 1.0 / nb) & (np.abs(dv) <= 1.0 / nb)
    if near.sum() < 2:
        return None
    pu = cu + float(np.average(du[near], weights=w[near] + 1e-12))
    pv = cv + float(np.average(dv[near], weights=w[near] + 1e-12))
    B = np.array([[lx * ct, -ly * st], [lx * st, ly * ct]])
    return B @ np.array([pu, pv]), int(near.sum())


@dataclass
class Lattice:
    """An affine lattice through candidate peaks (pixel system: x right, y down): the hand-over
    of the lattice search to the identification.

    Attributes
    ----------
    p0 : (2,) float
        Pixel position of the lattice node of relative index (0, 0).
    B : (2, 2) float
        Lattice basis (px): column 0 is the step of +1 column, column 1 of +1 row (a node of
        relative index (i, j) lies at ``p0 + B @ (i, j)``).
    idx : (M, 2) int
        Relative (column, row) index of the node nearest every candidate peak.
    cand : (K,) int
        The peaks on the lattice: per node the one closest to it, within the tolerance.
    px_per_mm : float
        The nominal scale the lattice was searched at.
    """

    p0: np.ndarray
    B: np.ndarray
    idx: np.ndarray
    cand: np.ndarray
    px_per_mm: float


@dataclass
class Identification:
    """Absolute rows and columns of a lattice's peaks: the hand-over of the identification
    to the projective model.

    Attributes
    ----------
    cand : (K,) int
        Candidate peaks on crosses of the certificate's grid.
    node : (K,) int
        Their cross index (row-major, as :meth:`Reseau.film`).
    ambiguous : bool
        Other row/col shifts fit the peaks and the format's edges as well.
    """

    cand: np.ndarray
    node: np.ndarray
    ambiguous: bool


def fit_grid(
    xy: np.ndarray,
    score: np.ndarray,
    reseau: Reseau,
    image_size: tuple[int, int],
    px_per_mm: float | None = None,
    rotate_deg: float = 0.0,
    margin_px: float = 0.0,
    max_rotation_deg: float = 20.0,
    frame_evidence=None,
    format_mm: tuple[float, float] | None = None,
    scale_tol: float | None = None,
    part: tuple[int, int, int, int] | None = None,
    seeable=None,
    by_count: bool = False,
    max_shear: float | None = None,
) -> GridFit | None:
    """Fit the reseau lattice to candidate peaks and assign rows and columns.

    Three steps, each with its hand-over: :func:`find_lattice` (an affine :class:`Lattice`
    through the peaks), :func:`identify` (absolute rows and columns, an
    :class:`Identification`) and :func:`projective_model` (the :class:`GridFit`).

    Parameters
    ----------
    xy : (M, 2) float
        Candidate positions (pixel system).
    score : (M,) float
        Their NCC scores (higher is better).
    reseau : Reseau
        The certificate's grid.
    image_size : (width, height)
        Scan size (px).
    px_per_mm : float, optional
        Nominal scale; estimated from the peaks' spacing when None.
    rotate_deg : float
        Known coarse rotation of the scan (0, 90, 180, 270): angle of film +x in the pixel
        system, measured from pixel +x towards pixel +y.
    margin_px : float
        A cross must lie this far inside the image to count as "should have been seen".
    frame_evidence, format_mm : callable and (width, height), optional
        Where several index shifts fit the crosses alike (a part of the grid), the evidence of
        the film format's edge (``format_mm``, centred on the grid) in the image:
        ``frame_evidence(corners, found)`` with the format's corners (K, 4, 2) (pixel system,
        top-left, top-right, bottom-right, bottom-left) of each such shift and the lattice's crosses
        ``found`` (n, 2) (pixel system) returns (K,) figures in [0, 1]
        (:func:`softplot.marks.lattice.frame_evidence`).
    max_rotation_deg : float
        Largest residual rotation accepted.
    scale_tol : float, optional
        With ``px_per_mm`` given (the dpi known): the lattice's spacing along each axis stays
        within this fraction of the certificate's pitch times ``px_per_mm``; ``None`` lets
        the spacing follow the peaks (the dpi being estimated).
    part : (col0, col1, row0, row1), optional
        The part of the grid the scan shows, when the user knows it (half-open ranges of
        columns and rows): the row/col numbering is chosen among the shifts that put the
        found crosses inside it.
    seeable : callable, optional
        ``seeable(xy, found)``: whether a cross at pixel positions (K, 2) would show in the
        scan like the crosses ``found`` (n, 2) ((K,) bool; false over a flat dark region or
        the border): crosses missed there do
        not make another naming less likely (:attr:`GridFit.ambiguous`).
    by_count : bool
        The lattice most peaks agree with, not the one of the highest sum of their scores
        (:func:`find_lattice`).
    max_shear : float, optional
        With ``scale_tol``: the lattices through three peaks whose steps' angle departs from
        a right angle by more (its cosine, :func:`_shear`) are not the reseau's
        (:func:`_robust_lattice`); None admits any above 30 degrees.

    Returns
    -------
    GridFit or None
        None when no lattice is found.
    """
    xy = np.asarray(xy, float)
    score = np.asarray(score, float)
    lat = find_lattice(xy, score, reseau, px_per_mm, rotate_deg, max_rotation_deg, scale_tol,
                       by_count, max_shear)
    if lat is None:
        return None
    ident = identify(lat, score, reseau, image_size, margin_px, frame_evidence, format_mm,
                     part, seeable)
    if ident is None:
        return None
    return projective_model(xy, score, reseau, ident, lat.px_per_mm, scale_tol)


def _shear(Bm) -> np.ndarray:
    """The cosine of the angle between the two steps (columns) of the lattice basis
    ``Bm`` (..., 2, 2) (pixel system): 0 for a rectangular lattice."""
    Bm = np.asarray(Bm, float)
    n = np.hypot(Bm[..., 0, :], Bm[..., 1, :])
    dot = Bm[..., 0, 0] * Bm[..., 0, 1] + Bm[..., 1, 0] * Bm[..., 1, 1]
    return dot / np.maximum(n[..., 0] * n[..., 1], 1e-300)


def _scale_ok(Bm, lx, ly, scale_tol) -> bool:
    """The lattice basis ``Bm`` (2, 2) keeps the certificate's spacing ``lx`` x ``ly`` px
    within ``scale_tol``: a lattice at another spacing is noise, never the reseau. A basis
    whose two steps are less than 30 degrees apart (peaks fitted along one line only) is never
    a reseau's, whatever ``scale_tol``."""
    n = np.hypot(Bm[0], Bm[1])
    if not (np.all(np.isfinite(Bm)) and n.min() > 0
            and abs(Bm[0, 0] * Bm[1, 1] - Bm[0, 1] * Bm[1, 0]) > 0.5 * n[0] * n[1]):
        return False
    if scale_tol is None:
        return True
    n = n / np.array([lx, ly])
    return bool(np.all(np.abs(n - 1.0) <= scale_tol))


def _best_per_node(idx, sel, key_val):
    """Indices of ``sel`` keeping, per lattice node (``idx`` (M, 2)), the peak with the
    smallest key."""
    order = sel[np.argsort(key_val[sel])]
    node_key = idx[order, 0].astype(np.int64) * (1 << 32) + idx[order, 1]
    first = np.unique(node_key, return_index=True)[1]  # first occurrence of each node
    return np.sort(order[first]).astype(int)


def find_lattice(xy, score, reseau: Reseau, px_per_mm=None, rotate_deg=0.0,
                 max_rotation_deg=20.0, scale_tol=None, by_count=False,
                 max_shear=None) -> Lattice | None:
    """The affine lattice of the reseau's pitch through the candidate peaks ``xy`` (M, 2)
    (pixel system) with scores ``score`` (M,).

    Rotations and phases are proposed by :func:`_lattice_search`; each is refined
    (:func:`_lattice_at`: an affine lattice on the peaks within a fifth of a pitch of a
    node, a robust lattice through triplets of nodes, per node the peak closest to it) and
    the one most peaks agree with (within :data:`AGREE_MM` of a node; among equals the one
    nearer ``rotate_deg``, then the one they lie closer to) is kept. Arguments as
    :func:`fit_grid`'s; None when fewer than 3 peaks lie on any lattice. ``by_count``: the
    peaks agree with a lattice by their number, not by the sum of their scores (a reseau of
    weak crosses that a busy scene's stronger peaks outscore); ``max_shear`` as
    :func:`fit_grid`'s."""
    M = len(xy)
    if M < 4:
        return None
    px, py = reseau.pitch_x, reseau.pitch_y
    if px_per_mm is None:
        top = np.argsort(-score)[: max(int(1.5 * reseau.count), 8)]
        sp = estimate_spacing(xy[top])
        if sp is None:
            return None
        px_per_mm = sp / min(px, py)
    lx, ly = px * px_per_mm, py * px_per_mm
    square = abs(lx - ly) < 0.08 * min(lx, ly)
    hyps = _lattice_search(xy, score, lx, ly, rotate_deg, max_rotation_deg, square)
    agree_by = np.ones_like(score) if by_count else score

    def refine(h):
        theta, p0, _ = h
        return _lattice_at(xy, agree_by, theta, p0, lx, ly, min(px, py), scale_tol, max_shear)

    def skipped(n_cell):  # too few peaks in its cell to gather as many as the best lattice
        return best_key is not None and 1.5 * n_cell + 3 < best_key[0]

    best, best_key = None, None
    width = threads() if concurrent() else 1
    i = 0
    while i < len(hyps):
        # the next hypotheses the best lattice so far does not rule out, refined a few at a
        # time on the process's threads (each its own), then taken in their order as one
        # by one: one the batch's earlier ones rule out is dropped (the same lattice)
        batch = []
        while i < len(hyps) and len(batch) < width:
            if not skipped(hyps[i][2]):
                batch.append(hyps[i])
            i += 1
        for h, got in zip(batch, thread_map(refine, batch), strict=True):
            if got is None or skipped(h[2]):
                continue
            p0, Bc, idx, cand, (n_agree, med) = got
            # among equals the lattice nearer the stated turn (in steps of 5 degrees), then
            # the one its peaks lie closer to
            turn = np.degrees(np.arctan2(Bc[1, 0], Bc[0, 0])) - rotate_deg
            key = (n_agree, -round(abs((turn + 180.0) % 360.0 - 180.0) / 5.0), -med)
            if best_key is None or key > best_key:
                best = Lattice(p0=p0, B=Bc, idx=idx, cand=cand, px_per_mm=float(px_per_mm))
                best_key = key
    return best


def _lattice_at(xy, score, theta, p0, lx, ly, pmin, scale_tol, max_shear=None):
    """The lattice near rotation ``theta`` (radians) through node ``p0`` (pixel system):
    (p0, B, idx, cand, (agreeing peaks, their median distance px)), the first four as
    :class:`Lattice` holds them, or None when fewer than 3 peaks lie on it."""
    c, s = np.cos(theta), np.sin(theta)
    # lattice basis in pixels: +1 column, +1 row (row goes down the film = film -y)
    Bc = np.array([[lx * c, -ly * s], [lx * s, ly * c]])
    p0 = np.asarray(p0, float).copy()
    # tolerances in lattice units: a fifth of a pitch to start, then at most ~0.5 mm (film
    # deformation and scanner non-linearity stay far below; coarse grids with 20 mm pitches
    # would otherwise admit scene peaks several millimetres off)
    tol = 0.2
    for _ in range(2):
        f = (xy - p0) @ np.linalg.inv(Bc).T
        idx = np.round(f)
        off = np.abs(f - idx)
        inl = np.maximum(off[:, 0], off[:, 1]) < tol  # (the row max of two columns)
        if inl.sum() < 3:
            return None
        Mx = np.column_stack([np.ones(inl.sum()), idx[inl]])
        sol = np.linalg.lstsq(Mx, xy[inl], rcond=None)[0]
        if not _scale_ok(sol[1:].T, lx, ly, scale_tol):
            break
        p0 = sol[0]
        Bc = sol[1:].T
    f = (xy - p0) @ np.linalg.inv(Bc).T
    idx = np.round(f).astype(int)
    off = np.abs(f - idx)
    inl = np.maximum(off[:, 0], off[:, 1]) < tol
    t_fine = min(0.2, 0.5 / pmin)
    t_agree = min(t_fine, AGREE_MM / pmin)
    p0, Bc, lim_px = _robust_lattice(xy, score, idx, inl, p0, Bc, lx, ly, tol, t_fine,
                                     t_agree, scale_tol, max_shear)
    # every peak against the robust lattice; per node the closest peak within the limit
    for _ in range(2):
        pred_all = p0 + idx @ Bc.T
        dev_px = np.hypot(*(xy - pred_all).T)
        cand = _best_per_node(idx, np.where(dev_px < lim_px)[0], dev_px)
        if len(cand) < 3:
            return None
        Mx = np.column_stack([np.ones(len(cand)), idx[cand]])
        sol = np.linalg.lstsq(Mx, xy[cand], rcond=None)[0]
        if not _scale_ok(sol[1:].T, lx, ly, scale_tol):
            break
        p0, Bc = sol[0], sol[1:].T
    dev = np.hypot(*(xy[cand] - p0 - idx[cand] @ Bc.T).T)
    agree = dev < max(t_agree * float(np.sqrt(abs(np.linalg.det(Bc)))), 3.0)
    return p0, Bc, idx, cand, (float(score[cand][agree].sum()), float(np.median(dev[agree]))
                               if agree.any() else np.inf)


def _robust_lattice(xy, score, idx, inl, p0, Bc, lx, ly, tol, t_fine, t_agree, scale_tol,
                    max_shear=None):
    """The lattice most nodes agree with, over exact affine lattices through triplets of
    peaks on three nodes (among ``inl``, the peaks within ``tol`` pitches of a node: all
    triplets for a few peaks, 300 random ones otherwise).

    A node agrees when one of its peaks lies within :data:`AGREE_MM` (``t_agree`` pitches,
    at least 3 px) of the lattice; among lattices with as many the smallest median of those
    residuals wins. Every peak near a node takes part, not only the best-scoring one: on a
    small grid clutter near a node often scores higher than the cross, and outnumbers the
    crosses (a least median of squares would be clutter's there). Returns (p0, B, lim_px):
    the lattice (the given one when no triplet fits) and the distance (px) within which a
    peak belongs to a node, max(t_fine pitches, 4 robust sigmas). ``max_shear``: as
    :func:`fit_grid`'s."""
    pitch_px = float(np.sqrt(abs(np.linalg.det(Bc))))
    lim_px = tol * pitch_px
    pts = np.where(inl)[0]
    if len(pts) > 400:  # the best-scoring ones: the work stays bounded
        pts = pts[np.argsort(-score[pts], kind="stable")[:400]]
    key = idx[pts, 0].astype(np.int64) * (1 << 32) + idx[pts, 1]
    pts = pts[np.argsort(key, kind="stable")]  # grouped by node
    key = np.sort(key, kind="stable")
    nodes, start = np.unique(key, return_index=True)
    if len(nodes) < 4:
        return p0, Bc, lim_px
    from itertools import combinations

    rng = np.random.default_rng(0)
    if len(pts) <= 40:
        tri = np.array(list(combinations(range(len(pts)), 3)))
    else:
        tri = _random_triplets(rng, len(pts), 300 if len(nodes) > 22 else 2000)
    Mi = np.concatenate([np.ones((len(pts), 1)), idx[pts]], 1)  # (P, 3)
    A3 = Mi[tri]  # (T, 3, 3); peaks on one node or on a line of nodes: singular
    ok = np.abs(np.linalg.det(A3)) > 1e-9
    sol = np.linalg.solve(A3[ok], xy[pts][tri[ok]]) if ok.any() else np.zeros((0, 3, 2))
    if scale_tol is not None and len(sol):
        # exact lattices through three nodes at another spacing are not the reseau (nor,
        # with ``max_shear``, sheared ones)
        nb = np.hypot(sol[:, 1:, 0], sol[:, 1:, 1]) / np.array([lx, ly])
        keep = np.all(np.abs(nb - 1.0) <= scale_tol, 1)
        if max_shear is not None:
            keep &= np.abs(_shear(sol[:, 1:].transpose(0, 2, 1))) <= max_shear
        sol = sol[keep]
    if len(sol):
        # residuals of every peak against every triplet's lattice, one coordinate at a
        # time (two (T, 3) @ (3, P) products); per node its closest peak
        res_px = np.hypot(sol[:, :, 0] @ Mi.T - xy[pts, 0], sol[:, :, 1] @ Mi.T - xy[pts, 1])
        per_node = np.minimum.reduceat(res_px, start, axis=1)
        agree = per_node < max(t_agree * pitch_px, 3.0)
        # agreement weighted by the peaks' scores: the crosses' centres outscore the
        # lattices of weaker peaks along long arms
        w_agree = (res_px < max(t_agree * pitch_px, 3.0)) @ score[pts]
        n_agree = agree.sum(1)
        # the (lower) median of the agreeing nodes' residuals
        srt = np.sort(np.where(agree, per_node, np.inf), axis=1)
        med = srt[np.arange(len(sol)), np.maximum(n_agree - 1, 0) // 2]
        best = int(np.lexsort((med, -w_agree))[0])
        lim_px = max(t_fine * pitch_px, 4.0 * 1.4826 * float(med[best]))
        p0, Bc = sol[best][0], sol[best][1:].T
    return p0, Bc, lim_px


#: the format's edge evidence per step of :func:`_edge_steps`, in units of the mean evidence
#: of a cross
EDGE_WEIGHT = 1.0
#: shifts scoring within this many crosses' evidence of the best are weighed by the edges (a
#: shadow on a negative, clear film as bright as the unexposed border, over the top row and
#: half of the next, whose crosses are then not among the candidates: the crosses favoured
#: the naming two rows off by 5.5 crosses, while the format's edge lay where only the right
#: naming puts it; with 4 its edges were never weighed)
EDGE_REACH = 8.0
#: the lattice rows and columns beyond a naming's format that its edge and the border may fill
#: with peaks (the format's edge, notches, corners): peaks farther out are crosses the naming
#: leaves off its grid, and count against it as peaks off the grid inside the format do
BEYOND = 1


def identify(lat: Lattice, score, reseau: Reseau, image_size, margin_px=0.0,
             frame_evidence=None, format_mm=None, part=None,
             seeable=None) -> Identification | None:
    """Absolute rows and columns of the lattice's peaks: the index shift that fits the
    certificate's grid best.

    Works on a map of relative lattice indices covering every admissible shift: the score of
    a shift is the evidence of the peaks on the grid (their scores above the clutter's,
    :func:`_evidence`) minus that of the peaks off it (inside its format, or more than
    :data:`BEYOND` rows or columns beyond it), minus a penalty for every cross of the grid
    that would lie inside the image without a peak, weak or strong (box sums over integral
    images give all shifts at once), except where no cross could be seen
    (``seeable(xy, found)``: positions (K, 2) and the lattice's crosses (n, 2), pixel
    system -> (K,) bool, false over a flat dark region or the border beyond the format);
    the format's edges the scan shows (:data:`EDGE_WEIGHT` per step of
    :func:`_edge_steps`) decide between shifts the crosses cannot tell apart. The naming is
    ambiguous when another shift scores within two steps of the edges' evidence, or as well
    once the unseeable crosses count as missed: a dark region over the outer row hides the
    format's edge with it. Arguments as :func:`fit_grid`'s; None when fewer than 3 peaks
    fall on the grid.
    """
    cand, p0, Bc = lat.cand, lat.p0, lat.B
    ci, ri = lat.idx[cand, 0], lat.idx[cand, 1]
    W, Hh = image_size
    rows, cols = reseau.rows, reseau.cols
    sc = _evidence(score, cand)
    mean_sc = float(sc.mean()) if sc.size else 1.0
    i_lo, i_hi = int(ci.min()) - cols + 1, int(ci.max()) + cols - 1
    j_lo, j_hi = int(ri.min()) - rows + 1, int(ri.max()) + rows - 1
    ni, nj = i_hi - i_lo + 1, j_hi - j_lo + 1
    S = np.zeros((nj, ni))
    np.add.at(S, (ri - j_lo, ci - i_lo), sc)
    # every peak on a node, weak ones too, shows a cross there (a weak one counts neither for
    # a naming nor against it, :func:`_evidence`; its node is not a missed cross)
    seen_map = np.zeros((nj, ni), bool)
    seen_map[ri - j_lo, ci - i_lo] = True
    jj, ii = np.mgrid[j_lo : j_hi + 1, i_lo : i_hi + 1]
    pos = p0 + np.column_stack([ii.ravel(), jj.ravel()]) @ Bc.T
    inside = ((pos[:, 0] >= margin_px) & (pos[:, 0] <= W - 1 - margin_px)
              & (pos[:, 1] >= margin_px) & (pos[:, 1] <= Hh - 1 - margin_px)).reshape(nj, ni)
    U = (inside & ~seen_map).astype(float)
    hidden = np.zeros_like(U)
    if seeable is not None and U.any():
        k = np.where(U.ravel() > 0)[0]
        found = p0 + lat.idx[cand] @ Bc.T
        hidden.ravel()[k] = ~np.asarray(seeable(pos[k], found), bool)

    def box_sums(Mp, r0=0, r1=rows, c0=0, c1=cols):
        # box of rows r0:r1 x cols c0:c1 of the grid whose row 0, col 0 has the relative
        # index (a, b); the box may reach beyond the grid (zeros beyond the map)
        pr, pc = max(0, -r0, r1 - rows), max(0, -c0, c1 - cols)
        c = np.zeros((nj + 2 * pr + 1, ni + 2 * pc + 1))
        c[1:, 1:] = np.pad(Mp, ((pr, pr), (pc, pc))).cumsum(0).cumsum(1)
        a = np.arange(nj - rows + 1)[:, None] + pr
        b = np.arange(ni - cols + 1)[None, :] + pc
        return c[a + r1, b + c1] - c[a + r0, b + c1] - c[a + r1, b + c0] + c[a + r0, b + c0]

    on = box_sums(S)
    unseen = box_sums(U)
    if part is not None:
        # the user says which part the scan shows: peaks outside it count against a shift
        # as peaks off the grid do
        c0, c1, r0, r1 = part
        on = box_sums(S, r0, r1, c0, c1)
    # grid centre of each shift vs image centre (tie-breaker)
    a = np.arange(nj - rows + 1)[:, None] + j_lo + (rows - 1) / 2.0
    b = np.arange(ni - cols + 1)[None, :] + i_lo + (cols - 1) / 2.0
    off = np.hypot(p0[0] + Bc[0, 0] * b + Bc[0, 1] * a - (W - 1) / 2,
                   p0[1] + Bc[1, 0] * b + Bc[1, 1] * a - (Hh - 1) / 2)
    # peaks off the grid count against a shift, but for those on its format's edge (a
    # quarter pitch or less inside) or up to BEYOND rows or columns beyond it: the edge and
    # the border give peaks, no cross; a cross farther out is one the shift leaves off its grid
    held = sc.sum()
    if format_mm is not None:
        # rows (columns) beyond the grid's last one still inside the format, a quarter
        # pitch clear of its edge
        kx, ky = (max(0, int(np.ceil(0.5 * fmt / pitch - 0.25 - (n - 1) / 2)) - 1)
                  for fmt, pitch, n in ((format_mm[0], reseau.pitch_x, cols),
                                        (format_mm[1], reseau.pitch_y, rows)))
        held = (box_sums(S, -ky, rows + ky, -kx, cols + kx) + held
                - box_sums(S, -ky - BEYOND, rows + ky + BEYOND, -kx - BEYOND, cols + kx + BEYOND))
    total = on - (held - on) - 0.5 * mean_sc * unseen - 1e-6 * off
    # the same, forgiving crosses missed where none could be seen
    lenient = total + 0.5 * mean_sc * box_sums(hidden)
    if frame_evidence is not None and format_mm is not None:
        # shifts the crosses cannot tell apart (a part of the grid: a crop through it, a half
        # frame): the film's format edge, where the scan shows it, decides
        near = np.argwhere((total >= total.max() - EDGE_REACH * mean_sc)
                           | (lenient >= lenient.max() - EDGE_REACH * mean_sc))
        if len(near) > 1:
            # the film beside the edge is judged from the peaks that count as crosses: weak
            # ones in a bright shadow (as bright as the border) would make the shadow film and
            # the edge's step there missing
            ev = _edge_steps(frame_evidence, near, p0, Bc, j_lo, i_lo, reseau, format_mm,
                             p0 + lat.idx[cand[sc > 0]] @ Bc.T)
            total[near[:, 0], near[:, 1]] += EDGE_WEIGHT * mean_sc * ev
            lenient[near[:, 0], near[:, 1]] += EDGE_WEIGHT * mean_sc * ev
    # crosses missed where none could be seen are no evidence against a shift
    ja, ib = np.unravel_index(int(np.argmax(lenient)), lenient.shape)
    # another shift as good (to two steps of the edges' evidence), or as good when the
    # unseeable crosses count as missed (to a hundredth of a cross)
    ambiguous = (int(np.sum(total >= total[ja, ib] - 0.01 * mean_sc)) > 1
                 or int(np.sum(lenient >= lenient[ja, ib] - 2 * EDGE_WEIGHT * mean_sc)) > 1)
    dr = -(ja + j_lo)  # relative index of row 0 is ja + j_lo
    dc = -(ib + i_lo)
    col, row = ci + dc, ri + dr
    ins = (col >= 0) & (col < cols) & (row >= 0) & (row < rows)
    if ins.sum() < 3:
        return None
    return Identification(cand=cand[ins], node=row[ins] * cols + col[ins], ambiguous=ambiguous)


def _evidence(score, cand):
    """What each peak of ``cand`` tells of a cross: its score, or nothing for a peak scoring
    less than half the median of the lattice's peaks (the crosses of a scan score alike; a
    row of peaks along a format's edge, or a scene feature on a node, far less): such a peak
    counts neither for a naming nor against it."""
    sc = score[cand].astype(float)
    if sc.size:
        sc[sc < 0.5 * float(np.median(sc))] = 0.0
    return sc


def _edge_steps(frame_evidence, near, p0, Bc, j_lo, i_lo, reseau: Reseau, format_mm, found):
    """The format's edge evidence of the shifts ``near`` (K, 2) (relative indices of row 0,
    col 0 less (j_lo, i_lo)), in steps of 0.05 (what differs less is noise, and the scan's
    centre decides): (K,) float. ``found`` (n, 2): the lattice's crosses (pixel system)."""
    rows, cols = reseau.rows, reseau.cols
    fx = np.array([-1, 1, 1, -1]) * 0.5 * format_mm[0] / reseau.pitch_x + (cols - 1) / 2
    fy = (rows - 1) / 2 - np.array([1, 1, -1, -1]) * 0.5 * format_mm[1] / reseau.pitch_y
    a = near[:, 0][:, None] + j_lo + fy[None, :]  # (K, 4) lattice row of each corner
    b = near[:, 1][:, None] + i_lo + fx[None, :]
    corners = np.stack([p0[0] + Bc[0, 0] * b + Bc[0, 1] * a,
                        p0[1] + Bc[1, 0] * b + Bc[1, 1] * a], -1)
    ev = frame_evidence(corners, found)
    return np.round(np.nan_to_num(np.asarray(ev, float)) / 0.05)


def projective_model(xy, score, reseau: Reseau, ident: Identification, px_per_mm: float,
                     scale_tol=None) -> GridFit | None:
    """The projective film-mm -> pixel model through the identified peaks: a few rounds of
    least squares with rejection beyond a deformation-tolerant threshold (~0.15 mm; the
    lattice assignment already tolerates +-0.2 pitch, no random sampling needed), and the
    fit's score against the clutter (the peaks off it). None when the model's scale leaves
    ``scale_tol``."""
    cand, node = ident.cand, ident.node
    cols = reseau.cols
    film = reseau.film()[node]
    pix = xy[cand]
    thr = max(3.0, 0.15 * px_per_mm)
    keep = np.ones(len(cand), bool)

    def model_fit(f, q, rc):
        # a projective model needs points spread over at least 3 rows and 3 columns and some
        # redundancy; otherwise it extrapolates wildly: affine then
        if len(f) >= 12 and len(np.unique(rc // cols)) >= 3 and len(np.unique(rc % cols)) >= 3:
            return projective_fit(f, q)
        return np.vstack([_affine_fit(f, q), [0.0, 0.0, 1.0]])

    Hm = model_fit(film, pix, node)
    for _ in range(4):
        rr = np.hypot(*(apply_h(Hm, film) - pix).T)
        med = float(np.median(rr[keep])) if keep.any() else thr
        new_keep = rr < max(thr, 4.0 * 1.4826 * med)
        if new_keep.sum() < 3 or (new_keep == keep).all():
            break
        keep = new_keep
        Hm = model_fit(film[keep], pix[keep], node[keep])
    cand, node = cand[keep], node[keep]
    res = apply_h(Hm, reseau.film()[node]) - xy[cand]
    # the score counts what the assigned peaks hold above the clutter (the peaks off the
    # lattice: their median, in units of its spread from the median to the 90th percentile):
    # a lattice through clutter scores near 0 however many nodes it fills (its peaks are
    # clutter's), the reseau's crosses by their margin over it
    off = np.ones(len(xy), bool)
    off[cand] = False
    c50, c90 = np.percentile(score[off], [50, 90]) if off.sum() >= 10 else (0.2, 0.3)
    # scale and rotation where the crosses are (film mm): a part of the grid far from its
    # centre (a strip of a large reseau) extrapolates the model's perspective to the centre
    J = h_jacobian(Hm, reseau.film()[node].mean(0))[0]
    scale = float(np.sqrt(abs(np.linalg.det(J))))
    if scale_tol is not None and abs(scale / px_per_mm - 1.0) > scale_tol:
        return None  # the model through the assigned peaks is at another spacing: not the reseau
    rot = float(np.degrees(np.arctan2(J[1, 0], J[0, 0])))
    return GridFit(
        H=Hm,
        index=cand,
        node=node,
        px_per_mm=scale,
        rotation_deg=rot,
        rms=float(np.sqrt(np.mean(np.sum(res**2, 1)))) if len(res) else 0.0,
        score=float(np.sum(score[cand] - c50) / max(c90 - c50, 0.05)),
        ambiguous=ident.ambiguous,
    )
