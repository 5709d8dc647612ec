"""Stage 2 of the reseau path: candidate crosses, NCC peaks on the overview.

:func:`reseau_candidates` correlates the overview with a cross template rendered from the
certificate at the overview's scale (:func:`softplot.marks.coarse.ncc_map`, in strips of
rows) and keeps the peaks of each admissible sign (bright crosses +1, dark -1), with the most
a lattice of that polarity can score. :func:`search_map` finds the best correlation near given
points (the prediction stage's local search). The hand-over is :class:`Candidates`.

Marks searched each in its own window (fiducials: :func:`window_candidates`) hand over
:class:`WindowCandidates`.
"""

from __future__ import annotations

import contextlib
import contextvars
from dataclasses import dataclass, field
from functools import partial

import numpy as np

from softplot.marks import coarse
from softplot.marks.common import polarity_signs
from softplot.marks.overview import ReseauOverview
from softplot.marks.template import MarkShape, cross_shape
from softplot.runtime import thread_map

__all__ = ["Candidates", "reseau_candidates", "scene_removed", "removing_scene",
           "sign_map", "crosses_in", "arm_evidence", "arm_scored",
           "peaks_kept", "search_map",
           "WindowCandidates", "window_candidates", "ARM_POOL", "ARM_TURNS"]


@dataclass
class Candidates:
    """NCC candidates of the crosses (hand-over of :func:`reseau_candidates`).

    Attributes
    ----------
    ncc : (h, w) ndarray
        Normalised cross-correlation map; ``ncc[i, j]`` is the correlation of the template
        centred on overview pixel ``(x, y) = (j + half, i + half)`` (overview pixel system).
    half : int
        Offset of the map in the overview (the template's half size, overview px).
    peaks : dict
        Sign (+1 bright crosses, -1 dark) -> :class:`softplot.marks.coarse.Peaks` (``xy`` (K, 2)
        overview pixel system, ``score`` (K,) correlation); only signs with 4 peaks or more.
    bound : dict
        Sign -> the highest score a lattice of that sign's peaks can reach (the sum of the
        best peaks, one per cross the scan can hold).
    template : MarkShape
        The cross template at the overview's scale (overview px).
    deferred : dict
        Sign -> ``(upper, score)``: a sign not yet scored by its arms, whose ``bound`` is at
        most ``upper`` (its NCC peaks' own), below every bound in ``bound``; ``score()``
        scores it (:meth:`take`). A lattice search that cannot use it (a fit already beats
        ``upper``) never does.
    maps : dict
        Sign -> the NCC map of that sign's own (same shape and offset as ``ncc``), where the
        signs were correlated apart (:func:`scene_removed`); empty: ``ncc`` serves both.
    """

    ncc: np.ndarray
    half: int
    peaks: dict
    bound: dict
    template: MarkShape
    deferred: dict = field(default_factory=dict)
    maps: dict = field(default_factory=dict)

    def ncc_of(self, sg: int) -> np.ndarray:
        """The NCC map the peaks of sign ``sg`` come from (overview pixel system offset by
        :attr:`half`)."""
        return self.maps.get(sg, self.ncc)

    def take(self, sg: int) -> bool:
        """Score the deferred sign ``sg`` by its arms now: its peaks and bound join
        :attr:`peaks` and :attr:`bound` when it keeps 4 peaks or more (returned)."""
        _, score = self.deferred.pop(sg)
        got = score()
        if got is None:
            return False
        self.peaks[sg], self.bound[sg] = got
        return True

    def complete(self) -> Candidates:
        """Every deferred sign scored (:meth:`take`); returns self."""
        for sg in list(self.deferred):
            self.take(sg)
        return self


def _bound(score: np.ndarray, n_in: int) -> float:
    """The highest score a lattice of peaks with these scores can reach: the sum of the
    ``n_in`` best (with a margin for the order of summation)."""
    return float(np.sort(score)[::-1][:n_in].sum()) * (1.0 + 1e-9) + 1e-9


def crosses_in(scan, res, px_per_mm: float) -> int:
    """The most crosses of the reseau ``res`` a scan can hold at ``px_per_mm`` (either way
    round): a part of the grid shows fewer than the certificate's."""
    lx, ly = res.pitch_x * px_per_mm, res.pitch_y * px_per_mm
    n = max((scan.width / lx + 2) * (scan.height / ly + 2),
            (scan.height / lx + 2) * (scan.width / ly + 2))
    return int(min(res.count, n))


def reseau_candidates(scan, ov: ReseauOverview, camera, polarity: str,
                      s_full: float) -> Candidates:
    """NCC peaks of ``camera``'s crosses on the overview ``ov`` for each sign ``polarity``
    admits ("auto", "positive", "negative"); ``s_full`` the expected blur sigma
    (full-resolution px)."""
    res = camera.reseau
    f, px_per_mm = ov.factor, ov.px_per_mm
    shape_ov = cross_shape(camera, px_per_mm / f)
    s_ov = float(np.hypot(s_full / f, 0.5))
    arm_half = min(0.5 * shape_ov.length, max(6.0, 3.0 * shape_ov.width))
    maps = {}
    if _SCENE_REMOVED.get():
        # each sign correlated with the scene taken away for it (:func:`sign_map`)
        for sg in polarity_signs(polarity):
            maps[sg], h = sign_map(ov.image, shape_ov, s_ov, sg, arm_half=arm_half)
        R = maps[polarity_signs(polarity)[0]]
    else:
        R, h = coarse.ncc_map(ov.image, shape_ov, s_ov, arm_half=arm_half)
    noise_floor = 2e-3
    pitch_ov = min(res.pitch_x, res.pitch_y) * px_per_mm / f
    # the crosses the scan can hold at most (a part of the grid shows fewer than the
    # certificate's): the number of candidates kept and the polarity's bound follow it
    n_in = crosses_in(scan, res, px_per_mm)
    keep = peaks_kept(n_in)
    def peaks_of(sg):
        return coarse.find_peaks(maps.get(sg, R), h,
                                 min_dist=max(2.0, min(0.35 * pitch_ov, arm_half)),
                                 threshold=0.2, max_peaks=ARM_POOL * keep, sign=sg,
                                 image=ov.image, std_half=max(int(arm_half), 2),
                                 min_contrast=noise_floor)

    # each sign's peaks on their own (OpenCV's morphology on the map, which releases the GIL):
    # both signs side by side on the process's threads
    signs = polarity_signs(polarity)
    raw = dict(zip(signs, thread_map(peaks_of, signs), strict=True))

    def scored(sg):
        # the sign's peaks scored by their arms and its bound, or None with fewer than 4
        pk = arm_scored(raw[sg], ov.image, sg, arm_half, shape_ov.width, s_ov, n_in, keep)
        # a grid's score is the sum of its peaks' scores, one peak per cross: at most the
        # sum of the ``count`` best ones
        return None if len(pk) < 4 else (pk, _bound(pk.score, n_in))

    # the arms' scores are at most the correlations (times at most 1): a sign's bound is at
    # most its NCC peaks' (with a margin for the rounding); the sign that can score most is
    # scored first, another only when it could outscore it (else deferred: a fit of the
    # first usually beats it, and its arms are never read)
    upper = {sg: _bound(np.maximum(pk.score, 0.0), n_in) * (1.0 + 1e-6) + 1e-9
             for sg, pk in raw.items()}
    first = max(raw, key=lambda sg: upper[sg]) if raw else None
    got = {first: scored(first)} if raw else {}
    peaks, bound, deferred = {}, {}, {}
    for sg in raw:  # the signs in their order (a tie of bounds keeps it)
        if sg != first and got[first] is not None and upper[sg] < got[first][1]:
            deferred[sg] = (upper[sg], partial(scored, sg))
            continue
        g = got[sg] if sg in got else scored(sg)
        if g is not None:
            peaks[sg], bound[sg] = g
    return Candidates(ncc=R, half=h, peaks=peaks, bound=bound, template=shape_ov,
                      deferred=deferred, maps=maps)


_SCENE_REMOVED = contextvars.ContextVar("scene_removed", default=False)


@contextlib.contextmanager
def scene_removed():
    """Within this context the crosses' candidates (:func:`reseau_candidates`, and the
    turned template's, :func:`softplot.marks.lattice.turn_template`) come from the NCC of
    each sign with the scene taken away (:func:`sign_map`): the detector's second try on a
    scan where the plain correlation found no reseau."""
    token = _SCENE_REMOVED.set(True)
    try:
        yield
    finally:
        _SCENE_REMOVED.reset(token)


def removing_scene() -> bool:
    """Whether :func:`scene_removed` is in force."""
    return _SCENE_REMOVED.get()


def sign_map(image, shape: MarkShape, s: float, sign: int, A=None,
             arm_half: float | None = None) -> tuple[np.ndarray, int]:
    """:func:`softplot.marks.coarse.ncc_map` (``R``, ``h``) of the part of ``image``
    (overview pixel system) narrower than the template's blurred line, of the polarity
    ``sign`` (:func:`softplot.marks.coarse.top_hat` with a disc of radius ``width + 2 s``,
    ``shape`` and ``s`` at the image's scale): over a busy scene the plain NCC of a
    cross is low where the scene's own edges and regions fill its window (a render's crosses
    of contrast 0.45 correlated 0.06-0.35 there), with them taken away 0.4-0.8. Only the
    sign's own extremes mean anything in ``R``."""
    img = coarse.top_hat(image, sign, shape.width + 2.0 * s)
    return coarse.ncc_map(img, shape, s, A=A, arm_half=arm_half)


#: NCC peaks gathered per peak kept: the ones kept are those whose arms show best
ARM_POOL = 4


def peaks_kept(n_in: int) -> int:
    """The candidates kept for a scan that can hold ``n_in`` crosses: three per cross and
    a hundred more (clutter), the best by their arms (:func:`arm_scored`)."""
    return 3 * n_in + 100


def arm_scored(pk, image, sign, arm_half, width, s, n_in, keep, turn_deg=0.0):
    """The NCC peaks ``pk`` (overview pixel system) scored by their arms: each correlation
    times its :func:`arm_evidence` over the ``n_in``-th best evidence (at most 1; the
    crosses the scan can hold show theirs at least as clearly, scene corners, edges and
    JPEG block corners, which correlate as well as faint crosses do, show none). The
    ``keep`` best-scoring ones with any evidence, best first. ``turn_deg``: the arms' turn
    expected (pixel-system degrees), as :func:`arm_evidence`'s."""
    if len(pk) == 0:
        return pk
    ev = arm_evidence(image, pk.xy, sign, arm_half, width, s, turn_deg)
    fin = np.sort(ev[np.isfinite(ev)])[::-1]
    ref = max(float(fin[min(n_in, len(fin)) - 1]) if len(fin) else 0.0, 1e-6)
    score = pk.score * np.clip(ev / ref, 0.0, 1.0)
    order = np.argsort(-score, kind="stable")[:keep]
    order = order[score[order] > 0]
    return coarse.Peaks(pk.xy[order], score[order], pk.sign[order])


#: rotations (degrees from the pixel axes) the arms of :func:`arm_evidence` are read at
ARM_TURNS = np.arange(-20.0, 20.1, 5.0)


def arm_evidence(image, xy, sign: int, arm_half: float, width: float, s: float,
                 turn_deg: float = 0.0) -> np.ndarray:
    """How clearly a cross's arms show around each point (grey units, times ``sign``).

    ``image`` the overview (overview pixel system), ``xy`` (K, 2) points in it, ``sign`` +1
    for bright crosses, -1 for dark ones, ``arm_half`` the half-arm read (overview px),
    ``width`` the line width and ``s`` the blur (overview px). Each of the four half-arms
    (axes turned by ``turn_deg`` (pixel-system degrees) plus each of :data:`ARM_TURNS`)
    gives the mean grey along it, from clear of
    the centre to ``arm_half``, less the mean grey of the nearer of its two flanks (a line
    width and the blur away on either side); a point's evidence is the best over the turns
    of its third-best half-arm (at least three arms of a cross must show) or half the
    weaker arm of its better bar (two opposite arms: a one-armed cross). A step edge, a
    corner, a JPEG block corner or a blot larger than the arms shows no arm (one of its
    flanks matches the line), a scene line one bar.
    Returns (K,) float; -inf for points outside the image.
    """
    K = len(xy)
    out = np.full(K, -np.inf)
    if K == 0:
        return out
    g = image
    Hh, W = g.shape
    r0 = max(1.5, width + s)
    r = np.linspace(r0, max(arm_half, r0 + 1.0), 6)
    d = max(1.5, 1.0 * width + 1.5 * s)
    reach = int(np.ceil(np.hypot(r[-1], d))) + 2
    x0 = np.floor(xy[:, 0]).astype(int)
    y0 = np.floor(xy[:, 1]).astype(int)
    ok = (x0 >= 0) & (x0 < W) & (y0 >= 0) & (y0 < Hh)
    if not ok.any():
        return out
    # the offsets of every read: (turns, 4 arms, line / flank / flank, radii, 2)
    t = np.radians(turn_deg + ARM_TURNS)[:, None] + np.arange(4) * (np.pi / 2)
    u = np.stack([np.cos(t), np.sin(t)], -1)  # (T, 4, 2)
    nrm = np.stack([-u[..., 1], u[..., 0]], -1)
    side = np.array([0.0, d, -d])
    off = (r[None, None, None, :, None] * u[:, :, None, None, :]
           + side[None, None, :, None, None] * nrm[:, :, None, None, :])
    idx = np.flatnonzero(ok)
    best = np.empty(len(idx))
    # the stored image (an overview's native grey levels) with its edge rows and columns
    # repeated beyond it: each point's window is a slice of it
    src, grey = (g.q, g.grey) if isinstance(g, coarse.Overview) else (np.asarray(g), None)
    wins = np.lib.stride_tricks.sliding_window_view(
        np.pad(src, ((reach, reach + 1), (reach, reach + 1)), mode="edge"),
        (2 * reach + 2, 2 * reach + 2))

    def chunk(a):  # a bounded working set, whatever the count
        i = idx[a:a + ARM_CHUNK]
        win = wins[y0[i], x0[i]]  # (k, n, n), the stored values
        win = grey(win) if grey is not None else np.asarray(win, np.float32)
        best[a:a + ARM_CHUNK] = _arm_reads(win, xy[i], x0[i], y0[i], reach, off, sign)

    thread_map(chunk, range(0, len(idx), ARM_CHUNK))  # independent: on the threads
    out[ok] = best
    return out


#: points whose arms :func:`arm_evidence` reads at once (their windows and reads, about
#: 2 MB at a 20-px reach)
ARM_CHUNK = 256


def _arm_reads(win, p, x0, y0, reach, off, sign) -> np.ndarray:
    """:func:`arm_evidence` of the points ``p`` (k, 2) (overview pixel system, ``x0``/``y0``
    their floors, inside the image) from their windows ``win`` (k, n, n) (float32 grey, rows
    and columns ``y0 - reach ..``, ``x0 - reach ..``, the image's edge rows and columns
    repeated beyond it: an arm across the edge keeps its contrast, one along it has none),
    read bilinearly at the offsets ``off`` (T, 4, 3, radii, 2)."""
    fx, fy = p[:, 0] - x0 + reach, p[:, 1] - y0 + reach  # the point in its window
    # the radii outermost: the mean along each arm adds whole slices (the sum in the order
    # of ``mean(-1)``, the same values)
    nr = off.shape[3]
    v = _read(win, fx, fy, np.moveaxis(off, 3, 0).reshape(-1, 2)).reshape(len(p), nr, -1)
    s = v[:, 0].copy()
    for i in range(1, nr):
        s += v[:, i]
    v = (s / np.float32(nr)).reshape((len(p),) + off.shape[:3])
    # (k, T, 4, 3): mean grey along each arm and its flanks
    d1, d2 = v[..., 0] - v[..., 1], v[..., 0] - v[..., 2]
    # above both flanks: a step edge along or across the arm is not a line
    a = sign * np.where(sign > 0, np.minimum(d1, d2), np.maximum(d1, d2))  # (k, T, 4)
    # the second smallest of the four arms (``np.sort(a, axis=2)[..., 1]``)
    lo = np.maximum(np.minimum(a[..., 0], a[..., 1]), np.minimum(a[..., 2], a[..., 3]))
    hi = np.minimum(np.maximum(a[..., 0], a[..., 1]), np.maximum(a[..., 2], a[..., 3]))
    third = np.minimum(lo, hi)
    # three arms, or one bar (two opposite arms: a one-armed cross, or a scene line) at
    # half weight
    bar = np.maximum(np.minimum(a[..., 0], a[..., 2]), np.minimum(a[..., 1], a[..., 3]))
    return np.maximum(third, 0.5 * bar).max(1)


def _read(win, fx, fy, off) -> np.ndarray:
    """Bilinear reads of windows ``win`` (k, n, n) at (fx, fy) (k,) plus offsets ``off``
    (m, 2) (all within the windows): (k, m). The windows are stacked into one image and
    read by ``cv2.remap`` a few hundred at a time (its size limit)."""
    import cv2

    k, n = win.shape[0], win.shape[1]
    out = np.empty((k, len(off)), np.float32)
    step = max(1, 30000 // n)
    ox, oy = off[:, 0].astype(np.float32), off[:, 1].astype(np.float32)
    for a in range(0, k, step):
        b = min(a + step, k)
        img = win[a:b].reshape(-1, n)
        mx = fx[a:b, None].astype(np.float32) + ox
        my = (fy[a:b] + n * np.arange(b - a))[:, None].astype(np.float32) + oy
        cv2.remap(img, mx, my, cv2.INTER_LINEAR, dst=out[a:b],
                  borderMode=cv2.BORDER_REPLICATE)
    return out


def search_map(R, h, sign, xy_ov, radius):
    """Best NCC position of ``sign`` within ``radius`` (overview px) of each point.

    ``R``/``h`` an NCC map and its offset (:class:`Candidates`), ``xy_ov`` (N, 2) overview
    pixel system. Returns the positions (N, 2) (overview px, parabola-refined; NaN where the
    disk holds no map value) and the correlation there (N,) (times ``sign``; -inf for none).
    """
    n = len(xy_ov)
    out = np.full((n, 2), np.nan)
    val = np.full(n, -np.inf)
    if R.size == 0:
        return out, val
    r = max(int(np.ceil(radius)), 1)
    ar = np.arange(-r, r + 1)
    ci = np.round(xy_ov[:, 0] - h).astype(int)
    cj = np.round(xy_ov[:, 1] - h).astype(int)
    ii = cj[:, None] + ar[None, :]
    jj = ci[:, None] + ar[None, :]
    Hh, W = R.shape
    vi = (ii >= 0) & (ii < Hh)
    vj = (jj >= 0) & (jj < W)
    sub = sign * R[np.clip(ii, 0, Hh - 1)[:, :, None], np.clip(jj, 0, W - 1)[:, None, :]]
    disk = (ar[:, None] ** 2 + ar[None, :] ** 2) <= r * r
    ok = vi[:, :, None] & vj[:, None, :] & disk[None]
    sub = np.where(ok, sub, -np.inf)
    flat = sub.reshape(n, -1).argmax(1)
    a, b = np.unravel_index(flat, sub.shape[1:])
    val = sub[np.arange(n), a, b]
    # parabola refinement
    def nb(da, db):
        aa = np.clip(a + da, 0, 2 * r)
        bb = np.clip(b + db, 0, 2 * r)
        v = sub[np.arange(n), aa, bb]
        return np.where(np.isfinite(v), v, val)
    with np.errstate(divide="ignore", invalid="ignore"):
        dxd = nb(0, -1) - 2 * val + nb(0, 1)
        dyd = nb(-1, 0) - 2 * val + nb(1, 0)
        dx = np.where(dxd < 0, 0.5 * (nb(0, -1) - nb(0, 1)) / dxd, 0.0)
        dy = np.where(dyd < 0, 0.5 * (nb(-1, 0) - nb(1, 0)) / dyd, 0.0)
    dx = np.clip(np.nan_to_num(dx), -0.5, 0.5)
    dy = np.clip(np.nan_to_num(dy), -0.5, 0.5)
    good = np.isfinite(val)
    out[good, 0] = (jj[np.arange(n), b] + dx + h)[good]
    out[good, 1] = (ii[np.arange(n), a] + dy + h)[good]
    return out, val


@dataclass
class WindowCandidates:
    """NCC candidates of marks searched each in its own window (hand-over of
    :func:`window_candidates`): per mark ``i``, ``xy[i]`` (K_i, 2) full-resolution pixel
    system, ``score[i]`` (K_i,) correlation, ``sign[i]`` (K_i,) int (+1 bright, -1 dark)."""

    xy: list
    score: list
    sign: list

    def of_sign(self, i: int, sign: int):
        """Mark ``i``'s candidates of ``sign``: positions (K, 2) px and scores (K,)."""
        m = self.sign[i] == sign
        return self.xy[i][m], self.score[i][m]


def window_candidates(ov: ReseauOverview, shapes, pred_full, radius_full: float,
                      blur_px: float, signs, per: int = 6) -> WindowCandidates:
    """NCC peaks of each mark inside its own window of the overview ``ov``.

    ``shapes``: each mark's template at the overview's scale (overview px); ``pred_full``
    (N, 2) the marks' expected positions and ``radius_full`` the windows' half size
    (full-resolution pixel system); ``blur_px`` the expected blur sigma (full-resolution px);
    ``signs`` the admissible signs; at most ``2 per`` peaks per window. Marks of one shape
    (sizes rounded to 0.01 px) share the first one's template.
    """
    F, img = ov.factor, ov.image
    xys, scores, sgns = [], [], []
    cache = {}
    for i, shp in enumerate(shapes):
        key = (shp.kind, round(shp.length, 2), round(shp.width, 2), round(shp.radius, 2),
               round(shp.dot_radius, 2))
        c = coarse.full_to_ov(pred_full[i], F)
        r = radius_full / F
        x0 = int(max(np.floor(c[0] - r), 0))
        y0 = int(max(np.floor(c[1] - r), 0))
        x1 = int(min(np.ceil(c[0] + r) + 1, img.shape[1]))
        y1 = int(min(np.ceil(c[1] + r) + 1, img.shape[0]))
        cand = (np.zeros((0, 2)), np.zeros(0), np.zeros(0, int))
        if x1 - x0 > 4 and y1 - y0 > 4:
            win = img[y0:y1, x0:x1]
            s_ov = float(np.hypot(blur_px / F, 0.5))
            if key not in cache:
                cache[key] = shp
            R, h = coarse.ncc_map(win, cache[key], s_ov)
            if R.size:
                std = coarse.local_std(win, max(int(shp.extent), 2))
                pk = coarse.find_peaks(R, h, min_dist=max(2.0, shp.extent), threshold=0.3,
                                       max_peaks=2 * per, contrast=std, min_contrast=2e-3)
                keep = np.isin(pk.sign, signs)
                pk = pk.select(keep)
                xy = coarse.ov_to_full(pk.xy + [x0, y0], F)
                cand = (xy, pk.score, pk.sign)
        xys.append(cand[0])
        scores.append(cand[1])
        sgns.append(cand[2])
    return WindowCandidates(xy=xys, score=scores, sign=sgns)
