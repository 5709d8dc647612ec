"""Shared fine stage: cut patches, run LSM, decide measured / missing for a set of marks.

All positions are in the pixel system of the full-resolution scan.
"""

from __future__ import annotations

import contextlib
import contextvars
import functools
import threading
import warnings
from dataclasses import dataclass, fields

import cv2
import numpy as np

from softplot.marks import jpegq, scene_tv
from softplot.marks import kernels as _kernels
from softplot.marks import opacity as _opacity
from softplot.marks import scene_tv as _scene_tv  # (``measure``'s argument shadows the name)
from softplot.marks.coarse import _release_rows
from softplot.marks.common import median_rows
from softplot.marks.lsm import LSMResult, _parts, lsm, patch_frame, support_mask
from softplot.marks.template import MarkShape, aperture
from softplot.runtime import concurrent, pooled_map, thread_map

__all__ = ["patches", "Fine", "measure", "measure_one_arm", "bar_share", "AcceptRules",
           "peer_sigma", "contrast_line", "contrast_unlike", "CONTRAST_TOL", "CONTRAST_LEAST",
           "peer_gain", "faint", "merge_fine"]


def patches(scan, centres: np.ndarray, half: int) -> tuple[np.ndarray, np.ndarray]:
    """Square windows of ``2*half+1`` px around integer-rounded centres, float32 grey.

    Pixels outside the scan are NaN. Returns ``(stack (N, h, w), origin (N, 2))`` where
    ``origin`` is the pixel (x, y) of each window's element [0, 0].
    """
    c = np.round(np.asarray(centres, float)).astype(np.int64).reshape(-1, 2)
    n = len(c)
    size = 2 * half + 1
    origin = c - half
    # every pixel is written below: the windows wholly inside by the gather, the others
    # NaN first (pixels outside the scan)
    out = np.empty((n, size, size), np.float32)
    if n == 0:
        return out, origin.astype(float)
    H, W = scan.height, scan.width
    data = scan.data
    inside = ((origin[:, 0] >= 0) & (origin[:, 1] >= 0) & (origin[:, 0] + size <= W)
              & (origin[:, 1] + size <= H))
    simple = data.ndim == 2 and data.dtype.kind in "ui" and not scan.min_is_white
    if simple and inside.any():
        # one gather for all windows that are wholly inside: each a slice of the scan (its
        # rows copied whole, not pixel by pixel)
        k = np.where(inside)[0]
        wins = np.lib.stride_tricks.sliding_window_view(data, (size, size))
        blk = wins[origin[k, 1], origin[k, 0]]
        out[k] = blk * np.float32(1.0 / scan.full_scale)
        todo = np.where(~inside)[0]
    else:
        todo = np.arange(n)
    out[todo] = np.nan
    for i in todo:
        x0, y0 = origin[i]
        xa, ya = max(x0, 0), max(y0, 0)
        xb, yb = min(x0 + size, W), min(y0 + size, H)
        if xb <= xa or yb <= ya:
            continue
        out[i, ya - y0 : yb - y0, xa - x0 : xb - x0] = scan.grey((slice(ya, yb), slice(xa, xb)))
    # the rows these windows read are not needed resident any more (memory-mapped scans)
    _release_rows(data, max(int(origin[:, 1].min()), 0), min(int(origin[:, 1].max()) + size, H))
    return out, origin.astype(float)


@dataclass
class AcceptRules:
    """Thresholds that decide whether a fitted mark is really there ("measured").

    Tuned on synthetic scans with covered, cut and partly dusted crosses (see the tests).
    """

    min_score: float = 0.45
    min_cnr: float = 3.0
    min_parts: int = 3
    min_part_support: float = 0.5
    scale_tol: float = 0.2
    angle_tol_deg: float = 6.0
    max_sigma: float = 0.5
    max_sigma_ratio: float = 6.0
    max_shift_factor: float = 1.5
    #: a cross's bar whose halves have less than this share of the other bar's contrast is
    #: not there (:func:`lone_bar`), one whose halves have more than ``bar_present`` is
    bar_absent: float = 0.5
    bar_present: float = 0.7
    #: a faint mark below ``min_cnr`` or ``min_score`` is still there when its matched-filter
    #: signal-to-noise (:attr:`softplot.marks.lsm.LSMResult.snr`, summed over its pixels) is
    #: at least ``min_snr`` and its score at least ``faint_score`` x the score noise alone
    #: leaves a perfect fit (:func:`faint`): it looks like the mark as far as the noise lets
    #: it (a thin, low-contrast reseau: each cross weak per pixel, strong over its length);
    #: the contrast, score and position tests below keep the fits to noise and scene
    #: content out, so that crosses of a signal-to-noise of 4-5 are measured too
    min_snr: float = 4.0
    faint_score: float = 0.75
    #: ... and only with a contrast of at least this share of its peers' (``gain_ref`` of
    #: :func:`measure`): a faint mark among strong ones is partly hidden (a dark band, the
    #: scan's border), not a faint grid's
    faint_gain: float = 0.5
    #: ... or, with a matched-filter signal-to-noise of at least ``dim_snr``, of at least
    #: ``dim_gain`` of it: a dim region of the film (a dark sky, a shadow) scales down the
    #: contrast of the crosses under it, which stay evident over their length; the fits
    #: where a dark band hides the crosses (noise, a JPEG copy's blocks) keep a tenth or
    #: two of the peers' contrast, and the dim fits on a busy scene's content have
    #: matched-filter signal-to-noise ratios of 6-8
    dim_gain: float = 0.25
    dim_snr: float = 10.0
    #: ... and only this share of ``max_shift`` from the prediction at most (a faint fit
    #: that wandered to the edge of its search had found scene content near the cross)
    faint_shift: float = 0.35


@dataclass
class Fine:
    """Fine-stage results over N marks (pixel system)."""

    xy: np.ndarray
    cov: np.ndarray  # reported (:attr:`softplot.marks.lsm.LSMResult.cov`)
    score: np.ndarray
    cnr: np.ndarray
    ok: np.ndarray
    reason: list
    lsm: LSMResult | None
    A: np.ndarray | None = None
    #: crosses of the first pass: the sharpest scene edge in the footprint over the contrast
    #: (:func:`_footprint_gradient`; NaN where not computed)
    edge: np.ndarray | None = None
    #: joint-scene passes used (:func:`_refit_scene`; 0: the opening's scene)
    scene_tv: int = 0
    #: fitted blur of each mark (px; NaN where not fitted)
    s: np.ndarray | None = None
    #: crosses: the arms each mark was measured with (2; 1: a lone arm, see
    #: :func:`measure_one_arm`; 0 where not measured)
    arms: np.ndarray | None = None
    #: the independent-pixel covariance (the acceptance and outlier tests' precision)
    cov_white: np.ndarray | None = None
    #: the fitted contrast (mark minus background, grey units; NaN where not fitted)
    gain: np.ndarray | None = None
    #: what the scan's JPEG quantisation adds to ``cov`` (px^2, not in it:
    #: :attr:`softplot.marks.lsm.LSMResult.cov_jpeg`)
    cov_jpeg: np.ndarray | None = None
    #: crosses measured as a lone bar: the bar's unit vector (N, 2), pixel system (x, y);
    #: NaN elsewhere (:func:`measure_one_arm`)
    bar: np.ndarray | None = None
    #: the crosses' opacity the fits took (:attr:`MarkShape.opacity`; 1: opaque)
    opacity: float = 1.0

    @property
    def sigma(self) -> np.ndarray:
        """``sqrt((var_x + var_y) / 2)`` of :attr:`cov_white` (px): the tests' precision."""
        c = self.cov if self.cov_white is None else self.cov_white
        return np.sqrt(0.5 * (c[:, 0, 0] + c[:, 1, 1]))

    def rows(self, k) -> "Fine":
        """The marks ``k`` (an index array or slice) of these results."""
        kw = {}
        for f in fields(Fine):
            a = getattr(self, f.name)
            if f.name == "reason":
                kw[f.name] = list(np.array(a, dtype=object)[k])
            elif f.name == "lsm":
                kw[f.name] = None
            elif a is None or f.name in ("scene_tv", "opacity"):
                kw[f.name] = a
            else:
                kw[f.name] = a[k]
        return Fine(**kw)


def _angle(A: np.ndarray) -> np.ndarray:
    return np.degrees(np.arctan2(A[..., 0, 1] - A[..., 1, 0], A[..., 0, 0] + A[..., 1, 1]))


def scene_background(stack: np.ndarray, shape: MarkShape, s: float, sign: int,
                     delta: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """The scene under thin marks, how far to trust it, and its gradient, for each patch.

    A grey opening (bright marks, ``sign > 0``) or closing (dark marks) with a disc wider than
    the blurred stroke (``width + 5 s + 1`` px) removes the cross bars or ring and keeps every
    scene structure larger than the disc, including sharp edges; a 3x3 mean then lowers its
    noise, and where the scene is smooth (a wider mean differs from it by less than about a
    noise sigma) a ``(d + 4)``-px mean replaces it: the closing of a noisy patch is lumpy on
    the scale of the disc. Near a scene edge the estimate may be off by about ``delta`` px of
    position, so pixels get the prior weight ``1 / (1 + (delta |grad S| / noise)^2)``
    (``noise``: the patch's MAD of data minus estimate): scene edges along an arm then carry
    little weight instead of pulling the centre. Filled marks (dots) have no stroke to
    remove: the patch median and unit weights are returned. All patches are filtered at once
    (stacked into one image with a replicated border between them). Returns ``(S, weights,
    |grad S|)`` (px^-1, Sobel / 8; None for dots).
    """
    n, h, w = stack.shape
    fin = np.isfinite(stack)
    if shape.kind == "dot" or n == 0 or not fin.all():
        # patch medians: the dot's background, and the fill of pixels outside the scan
        med = np.median(stack.reshape(n, -1), axis=1)  # NaN for patches crossing the edge
        for i in np.where(~np.isfinite(med))[0]:
            f_i = fin[i]
            med[i] = float(np.median(stack[i][f_i])) if f_i.any() else 0.0
        q = np.where(fin, stack, med[:, None, None]).astype(np.float32)
    else:
        q = np.asarray(stack, np.float32)
    if shape.kind == "dot" or n == 0:
        return np.broadcast_to(med[:, None, None], stack.shape).astype(np.float32), \
            np.ones_like(stack), None
    d = int(np.ceil(shape.width + 5.0 * s + 1.0)) | 1
    # rows of replicated border between the stacked patches: the reach of the closing (twice
    # the disc's radius), the wide mean below and the Sobel, so that no patch's estimate sees
    # its neighbour in the stack (each is that of the patch alone, edges replicated)
    kl = (d + 4) | 1
    pad = 2 * (d // 2) + kl // 2 + 1
    big = np.pad(q, ((0, 0), (pad, pad), (0, 0)), mode="edge").reshape(n * (h + 2 * pad), w)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))
    op = cv2.MORPH_OPEN if sign > 0 else cv2.MORPH_CLOSE
    C = cv2.morphologyEx(big, op, k, borderType=cv2.BORDER_REPLICATE)
    del big
    S = cv2.blur(C, (3, 3))
    # the closing of a noisy patch is lumpy on the scale of the disc; where the scene is
    # smooth a wider mean removes the lumps, near scene edges the 3x3 mean is kept
    SL = cv2.blur(C, (kl, kl))
    del C
    # the patch's noise: MAD of data minus estimate (every third pixel is plenty)
    nz = np.abs(q - S.reshape(n, h + 2 * pad, w)[:, pad : pad + h]).reshape(n, -1)[:, ::3]
    nz = np.maximum(1.4826 * median_rows(nz), 1e-4).astype(np.float32)
    nzb = np.repeat(nz, h + 2 * pad)[:, None]
    # S += al (SL - S) with al = 1 / (1 + ((SL - S) / (0.75 noise))^2), in place (the working
    # set of a chunk of patches bounds the fine stage's memory)
    SL -= S
    al = SL / (np.float32(0.75) * nzb)
    al *= al
    al += np.float32(1.0)
    np.reciprocal(al, out=al)
    SL *= al
    S += SL
    del SL, al
    g = _grad_magnitude(S)
    S = S.reshape(n, h + 2 * pad, w)[:, pad : pad + h]
    g = g.reshape(n, h + 2 * pad, w)[:, pad : pad + h]
    return np.ascontiguousarray(S), _prior_weights(g, nz, delta), g


def peer_gain(fine: Fine, least: int = 3) -> float | None:
    """The accepted marks' median contrast (``|gain|``, grey units) of a :class:`Fine`, or
    None with fewer than ``least`` accepted (or no contrasts): the ``gain_ref`` of refits."""
    if fine.gain is None or fine.ok.sum() < least:
        return None
    g = np.abs(fine.gain[fine.ok])
    g = g[np.isfinite(g)]
    return float(np.median(g)) if g.size >= least else None


def peer_sigma(fine: Fine, least: int = 5) -> float | None:
    """The accepted marks' median precision (px, :attr:`Fine.sigma`) of a :class:`Fine`, or
    None with fewer than ``least`` accepted: the reference of refits' relative precision
    test (:func:`measure`'s ``sigma_ref``)."""
    if fine.ok.sum() < least:
        return None
    return float(np.median(fine.sigma[fine.ok]))


def _grad_magnitude(img: np.ndarray) -> np.ndarray:
    """``|grad img|`` (grey units per px) of a 2-D float32 image: Sobel magnitude / 8.

    The magnitude is NumPy's: OpenCV's ``magnitude`` rounds the last bit differently from
    call to call on the same data (its vector and scalar paths), and through the prior
    weights and the fits over a busy scene that made whole runs differ (a cross 2.9 px apart,
    13-18 gross crosses on one sweep render)."""
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3)
    gx *= gx
    gy *= gy
    gx += gy
    np.sqrt(gx, out=gx)
    gx *= np.float32(1.0 / 8.0)
    return gx


def median_blur(s: np.ndarray, ok: np.ndarray, min_count: int = 5) -> float | None:
    """The blur (px) that later fits hold: the median of the accepted marks' fitted blurs
    ``s[ok]`` (the scanner's and the film's blur, the same for neighbouring marks; a free blur
    lets a fit trade it against scene content along a bar); None with fewer than
    ``min_count`` finite values."""
    v = np.asarray(s, float)[np.asarray(ok, bool)]
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size >= min_count else None


def _prior_weights(grad: np.ndarray, noise: np.ndarray, delta: float) -> np.ndarray:
    """Prior pixel weights ``1 / (1 + (delta |grad S| / noise)^2)`` of a scene estimate whose
    edges may be off by about ``delta`` px: ``grad`` (N, h, w) its gradient magnitude (grey
    units per px), ``noise`` (N,) each patch's noise."""
    wts = grad * (np.float32(delta) / np.asarray(noise, np.float32))[:, None, None]
    wts *= wts
    wts += np.float32(1.0)
    np.reciprocal(wts, out=wts)
    return wts


#: a patch whose opening (:func:`scene_background`) departs from a plane, away from the
#: cross, by no more than this many noise sigmas (RMS) shows a flat scene: the plane is its
#: scene estimate (:func:`plane_scenes`). The opening of a flat, noisy patch departs by
#: 0.05-0.15 sigma (its lumps); the sweep's textures by more where they matter
PLANE_GATE = 0.25


def plane_scenes(stack: np.ndarray, S: np.ndarray, away: np.ndarray, step: float = 0.0,
                 gate: float = PLANE_GATE) -> tuple[np.ndarray, np.ndarray]:
    """Which patches' scene is flat: a plane fitted (least squares) to the opening ``S`` over
    the pixels ``away`` from the cross, and ``S`` departing from it there by at most ``gate``
    times the patch's noise (RMS; the noise the MAD of ``stack - S`` over those pixels), or by
    at most the scan's grey ``step`` (a stored scan shows nothing finer: a JPEG's flat patch
    departs by about one step while its noise, smoothed away, is far less).

    The opening of a flat scene is the background plus the closing's lumps of noise (on the
    scale of its disc) and, where the blurred bars meet, a dip the disc could not close: both
    are noise and a piece of the mark in the scene estimate, where the plane LSM fits with
    the mark (its level and tilt) has none. ``stack``, ``S`` (N, h, w) grey, patch pixel
    system; ``away`` (N, h, w) bool. Returns ``(flat (N,) bool, P (N, h, w) float32)``, ``P``
    the fitted planes (patch pixel system), valid where ``flat``."""
    n, h, w = S.shape
    flat = np.zeros(n, bool)
    P = np.zeros(S.shape, np.float32)
    if n == 0:
        return flat, P
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    X = np.stack([np.ones(h * w), (x.ravel() - w / 2) / w, (y.ravel() - h / 2) / h], 1)
    k = away.reshape(n, -1)
    ok = np.isfinite(stack).reshape(n, -1).all(1) & (k.sum(1) >= 3 * X.shape[1])
    if not ok.any():
        return flat, P
    # every patch's least-squares plane over its own pixels at once: the normal equations
    # (3 x 3 each; the design's columns are centred and scaled, so well conditioned)
    k = k[ok]
    Wk = k.astype(np.float64)
    si = S[ok].reshape(len(k), -1).astype(np.float64)
    G = np.einsum("np,pi,pj->nij", Wk, X, X)
    coef = np.linalg.solve(G, np.einsum("np,pi,np->ni", Wk, X, si)[..., None])[..., 0]
    plane = coef @ X.T  # (n_ok, h * w)
    res = np.where(k, np.abs(stack[ok].reshape(len(k), -1) - si), np.nan)
    noise = 1.4826 * np.nanmedian(res, axis=1)
    dev = np.sqrt(np.sum(np.where(k, si - plane, 0.0) ** 2, 1) / k.sum(1))
    flat[ok] = dev <= np.maximum(gate * noise, step)
    P[ok] = plane.reshape(-1, h, w)
    return flat, P


def _away_from_centre(origin, c0, A0, shape, s0, init_err, stack_shape) -> np.ndarray:
    """The pixels (N, h, w) bool of patches cut at ``origin`` around the crosses ``c0``
    (pixel system; affines ``A0``) beyond ``width / 2 + 3 s0 + init_err + 1`` px of the
    cross's centre, where :func:`plane_scenes` judges the opening: nearer, the blurred bars
    meet and the opening cannot close them; along and beside the bars it removes them, and a
    scene line there is seen."""
    A = np.broadcast_to(np.asarray(A0, float), (len(c0), 2, 2))
    u, v = patch_frame(origin, c0, A, stack_shape)
    return np.hypot(u, v) > 0.5 * shape.width + 3.0 * s0 + init_err + 1.0


def _fit(scan, shape, c0, A0, s0, init_err, sign, fit_shape, scene, drop_part=None,
         scene_tv=0, rules=None, first=None, edges=False, fit_blur=True, tv_select=None,
         groups=None, bg_out=None, scene_bg=None, plane=False):
    """Patches, scene background and LSM for a set of marks (``drop_part``: a half-arm of
    each cross, 0..3 as in :func:`softplot.marks.lsm._parts`, given weight 0; ``scene_tv``:
    passes of the joint scene estimate of :func:`_refit_scene` after the first fit;
    ``first``: that first fit, when it was made already by a call with the same arguments;
    ``tv_select``: the marks the joint scene refits, default all; ``groups``: independent
    sets of marks, see :func:`_refit_scene`; ``bg_out``: a list the opening's scene estimate
    (pixel system, (M, h, w)) of the marks with a scene edge (``edge`` above
    :data:`softplot.marks.scene_tv.EDGE_MIN`) is appended to; ``scene_bg``: that estimate of
    the marks ``tv_select``, with ``first``, from a call with the same arguments: the refit
    with the joint scene then does not compute it again, and gives the same values;
    ``plane``: a flat patch's scene is its plane, :func:`_flat_to_plane`).
    Returns ``(LSMResult, edge)``; ``edge``, with ``edges``: :func:`_footprint_gradient` over
    the fitted contrast, else (and for other marks) NaN."""
    stack, origin = patches(scan, c0, _half(shape, A0, s0, init_err))
    if scene_bg is not None:  # only the joint scene's start is wanted, and was computed
        bg = np.zeros(stack.shape, np.float32)
        bg[np.asarray(tv_select, bool)] = scene_bg
        wt = grad = None
    else:
        bg, wt, grad = scene_background(stack, shape, s0, sign) if scene else (None, None, None)
        if plane and grad is not None and shape.kind == "cross":
            bg, wt = _flat_to_plane(stack, origin, c0, A0, shape, s0, init_err, bg, wt,
                                    1.0 / scan.full_scale)
    keep = None
    if drop_part is not None and shape.kind == "cross":
        A = np.broadcast_to(np.asarray(A0, float), (len(c0), 2, 2))
        u, v = patch_frame(origin, c0, A, stack.shape)
        dp = np.asarray(drop_part)
        keep = _parts(shape, u, v) != (dp[:, None, None] if dp.ndim else dp)
        wt = np.where(keep, 1.0 if wt is None else wt, 0.0).astype(np.float32)
    # a patch the scan's edge cuts (NaN pixels) has no scene figure and no joint scene; the
    # set's other crosses have theirs (one such patch in a chunk took them from all of it)
    whole = np.isfinite(stack).reshape(len(c0), -1).all(1)
    cross = scene and shape.kind == "cross" and bool(whole.any())
    top = _footprint_gradient(grad, origin, c0, A0, shape, s0) if cross and edges else None
    del grad  # not held through LSM (the fine stage's peak memory)
    quant = jpegq.of_scan(scan)
    res = first if first is not None else _lsm(
        stack, origin, c0, A0, shape, bg, wt, s0=s0, init_err=init_err, fit_shape=fit_shape,
        clip=(0.0, 1.0), fit_blur=fit_blur, quant=quant)
    edge = np.full(len(c0), np.nan)
    if cross:
        if top is not None:
            # the sharpest scene edge in the footprint over the cross's contrast
            edge = np.where(whole, top / np.maximum(np.abs(res.gain), 1e-6), np.nan)
            if bg_out is not None and bg is not None:
                bg_out.append(bg[edge > _scene_tv.EDGE_MIN])
        if scene_tv:
            sel = tv_select if whole.all() else whole & (True if tv_select is None
                                                         else np.asarray(tv_select, bool))
            res = _refit_scene(stack, origin, res, bg, keep, shape, fit_shape, scene_tv, sign,
                               rules or AcceptRules(), fit_blur, sel, groups, quant)
    if keep is not None and res.part_gain is not None and res.part_gain.shape[1] == 4:
        # the half-arm left out has no say: not in the support count, not in the one-bar
        # test (its pixels were read at zero weight; an absent bar's half there looked half
        # present and a one-armed cross passed as whole)
        rows = np.arange(len(c0))
        dp = np.broadcast_to(np.asarray(drop_part), (len(c0),))
        res.part_gain[rows, dp] = np.nan
        res.support[rows, dp] = np.nan
    return res, edge


def _flat_to_plane(stack, origin, c0, A0, shape, s0, init_err, bg, wt, step):
    """The scene estimate ``bg`` and prior weights ``wt`` (N, h, w, patch pixel system) with
    every flat patch's (:func:`plane_scenes`, judged :func:`_away_from_centre`; ``step`` the
    scan's grey step) replaced by its plane and unit weights."""
    away = _away_from_centre(origin, c0, A0, shape, s0, init_err, stack.shape)
    flat, P = plane_scenes(stack, bg, away, step)
    if flat.any():
        bg = bg.copy()
        bg[flat] = P[flat]
        wt = wt.copy()
        wt[flat] = 1.0
    return bg, wt


def _half(shape, A0, s0, init_err) -> int:
    """The half-size (px) of the patches :func:`_fit` fits (affines ``A0``, blur ``s0``,
    start error ``init_err``)."""
    sv = np.linalg.svd(A0, compute_uv=False)
    grow = float(1.0 / max(sv.min(), 1e-3))
    s_cap = float(np.hypot(s0, init_err)) if init_err > 0.75 else s0
    return int(np.ceil(shape.extent * grow + 3.0 * s_cap + init_err + 3))


#: a call of :func:`measure` takes the plane as the scene of its patches where this share
#: of its (at least PLANE_LEAST) patches are flat: a scan with a flat scene. Over a busy
#: scene, a flat patch beside its sharp edges may hide a line narrower than the opening's
#: disc (a scratch) that the opening's estimate half followed; and crosses fitted over
#: planes beside others over openings (a corner's by the format edge) differ in their fitted
#: shape, which the shape test then refuses (a 250 dpi scan blurred 2.2 px: 3 corner crosses)
PLANE_SHARE = 1.0
#: ... of at least this many patches (a trial of 8 crosses for the arm length does not)
PLANE_LEAST = 9
#: ... of crosses at least this many blur sigmas long: over the plane a short, blurred cross
#: came out worse than over the opening (a 250 dpi scan blurred 2.2 px, crosses 6 px long:
#: 1.36x its bound against 1.11x; the template's mismatch there, which the opening's
#: estimate partly takes up, is not diagnosed)
PLANE_MIN_LENGTH = 5.0


_PLANE = contextvars.ContextVar("softplot_marks_plane", default=True)
#: a list :func:`flat_scan` appends to when it finds a flat scan (None: nobody asks)
_PLANE_USED = contextvars.ContextVar("softplot_marks_plane_used", default=None)


@contextlib.contextmanager
def plane_watch():
    """Yields a list that is not empty once :func:`measure` took a plane within the
    context."""
    used: list = []
    token = _PLANE_USED.set(used)
    try:
        yield used
    finally:
        _PLANE_USED.reset(token)


@contextlib.contextmanager
def opening_only():
    """Within this context :func:`measure` takes the opening's scene estimate everywhere
    (:func:`flat_scan` says no scan is flat): the detector's fallback where the plane's
    detection found no reseau."""
    token = _PLANE.set(False)
    try:
        yield
    finally:
        _PLANE.reset(token)


def flat_scan(scan, shape, c0, A0, s0, init_err, sign) -> bool:
    """Whether the scene under the crosses at ``c0`` (N, 2, pixel system; affines ``A0``)
    is flat: at least :data:`PLANE_SHARE` of their :data:`PLANE_LEAST` or more patches
    (:func:`plane_scenes`, as :func:`_fit` cuts them), the cross at least
    :data:`PLANE_MIN_LENGTH` blurs ``s0`` long. Never within :func:`opening_only`."""
    n = len(c0)
    if (n < PLANE_LEAST or shape.kind != "cross" or not _PLANE.get()
            or shape.length < PLANE_MIN_LENGTH * s0):
        return False
    rough = 0
    half = _half(shape, A0, s0, init_err)
    for k, m in _growing_chunks(n):  # bounded memory, and a busy scan stops early
        c = c0[k:m]
        A = np.broadcast_to(np.asarray(A0, float), (n, 2, 2))[k:m]
        stack, origin = patches(scan, c, half)
        bg, _, grad = scene_background(stack, shape, s0, sign)
        if grad is None:
            return False
        away = _away_from_centre(origin, c, A, shape, s0, init_err, stack.shape)
        rough += int((~plane_scenes(stack, bg, away, 1.0 / scan.full_scale)[0]).sum())
        if rough > (1.0 - PLANE_SHARE) * n:
            return False
    used = _PLANE_USED.get()
    if used is not None:
        used.append(True)
    return True


#: :func:`flat_scan` judges the patches in chunks that start at this many and double up to
#: :data:`FLAT_CHUNK_MAX`: each patch is judged on its own (its opening and plane), so the
#: chunks decide nothing; on a busy scan the first rough patch ends the test, mostly in the
#: first chunk (a first chunk of 32 computed 28 openings and planes too many)
FLAT_CHUNK_MIN = 4
FLAT_CHUNK_MAX = 32


def _growing_chunks(n: int) -> list[tuple[int, int]]:
    """``[(start, stop), ...]`` covering ``range(n)``: :data:`FLAT_CHUNK_MIN` marks first, each
    next chunk twice the last, at most :data:`FLAT_CHUNK_MAX`."""
    out, k, size = [], 0, FLAT_CHUNK_MIN
    while k < n:
        out.append((k, min(k + size, n)))
        k += size
        size = min(2 * size, FLAT_CHUNK_MAX)
    return out


def _footprint_gradient(grad, origin, c0, A0, shape, s0):
    """The sharpest scene edge in each cross's footprint: the largest gradient ``grad`` of the
    scene estimate (grey units per px, :func:`scene_background`) within ``2.5 s0`` px of the
    drawn bars. Over the cross's contrast it is the scene-edge figure of :func:`_fit`: smooth
    texture stays below 0.1 (the sweep's textured renders: at most 0.09); the blocks, roads
    and discs of a busy scene reach 0.2-0.5."""
    n = grad.shape[0]
    A = np.broadcast_to(np.asarray(A0, float), (n, 2, 2))
    u, v = patch_frame(origin, c0, A, grad.shape)
    near = support_mask(shape, u, v, 2.5 * s0)
    return np.where(near, grad, 0.0).reshape(n, -1).max(1)


def _saturated(bg):
    """Where the scene estimate is saturated (0/1 float32), or None: saturated grey values (at
    the ends of the range) are censored in LSM: they only say "at least this bright"; where
    the scene estimate itself is saturated, the scene's true level beyond the range is a free
    parameter."""
    if bg is None:
        return None
    sb = (bg >= 1.0 - 2e-3) | (bg <= 2e-3)
    return sb.astype(np.float32) if sb.any() else None


#: a refit with the joint scene estimate that moves a cross by more than this (px) from the
#: first fit is not taken (it would be a different solution, not a better scene)
REFIT_MAX_MOVE = 0.5
#: position uncertainty (px) of the joint scene estimate's edges in the prior pixel weights
#: ``1 / (1 + (delta |grad B| / noise)^2)`` (the opening's is 1 px)
REFIT_DELTA = 0.6
#: every cross takes this many joint-scene passes; later passes only the crosses that the last
#: one moved by more than :data:`REFIT_SETTLE` x their sigma (the others have settled)
REFIT_ALL_PASSES = 2
#: a lone bar's contrast is at least this share of the measured crosses' median contrast
#: (:func:`measure_one_arm`), whatever its contrast to noise
LONE_BAR_MIN_GAIN = 0.1
REFIT_SETTLE = 0.25


#: the refit with the joint scene of :func:`measure`'s ``auto_tv`` starts from the opening's
#: estimate its first pass computed (kept for the crosses with a scene edge only); False:
#: computed again (the same values, :func:`_fit`)
REUSE_OPENING = True

#: a single chunk of at least twice this many marks is fitted in two halves on two threads
#: where :func:`softplot.runtime.thread_map` runs concurrently (:func:`_halves`)
SPLIT_MIN = 4


def _halves(idx: np.ndarray) -> list[np.ndarray]:
    """The marks ``idx`` in two halves where :func:`thread_map` runs concurrently (a single
    chunk of marks: refits, retries, rescues; inside a pool thread, where the chunks already
    run side by side, or on one thread: one part). Each mark's scene solve and LSM fit are
    its own (as for any chunking); the first half is the multiple of 4 marks nearest half of
    them, so the template's batches of 4 (:func:`_template`) are those of one part."""
    n = len(idx)
    if n < 2 * SPLIT_MIN or not concurrent():
        return [idx]
    h = 4 * max(1, round(n / 8))
    return [idx[:h], idx[h:]]


def _lsm(stack, origin, c0, A0, shape, bg, wt, **kw) -> LSMResult:
    """:func:`softplot.marks.lsm.lsm` of N patches (pixel system), the two halves of
    :func:`_halves` on two threads where that splits them (the compiled kernels release the
    GIL). ``bg``, ``wt``: the scene estimate and prior pixel weights (N, h, w) or None."""
    n = len(c0)
    A0 = np.broadcast_to(np.asarray(A0, float), (n, 2, 2))

    def one(k):
        b = None if bg is None else bg[k]
        return lsm(stack[k], origin[k], c0[k], A0[k], shape, background=b,
                   weight=None if wt is None else wt[k], sat_bg=_saturated(b), **kw)

    parts = _halves(np.arange(n))
    return one(slice(None)) if len(parts) == 1 else _concat(thread_map(one, parts))


def _refit_pass(stack, origin, res, X, idx, sm, noise_set, keep, shape, fit_shape, fit_blur,
                p, quant=None):
    """Pass ``p`` of :func:`_refit_scene` for the marks ``idx`` that share the blur ``sm``
    (px): the scene under each held cross solved from ``X`` (the last solution, (N, h, w)
    pixel system), its gradient's prior pixel weights, and LSM from the last fit ``res``.
    Each mark's solve and fit are its own: the two halves of :func:`_halves` on two threads
    where that splits them. Returns the LSMResult and the scene ``X`` of the marks ``idx``."""

    def one(k):
        A = res.A[k]
        T = _template(shape, origin[k], res.centre[k], A, res.s[k], stack.shape[1:])
        g = stack[k]
        noise = noise_set[k]
        B, Xk = scene_tv.deconv_tv(g, T, res.level[k], X[k], scene_tv.MU * noise,
                                   np.hypot(sm, np.sqrt(1 / 12)), iters=scene_tv.iterations(p))
        wt = _edge_weights(B, noise, REFIT_DELTA)
        if keep is not None:
            wt = np.where(keep[k], wt, 0.0).astype(np.float32)
        # (without fit_shape the fitted affine is A0's)
        # every refitted cross takes the first REFIT_ALL_PASSES passes: the covariance of
        # the earlier ones (costly with the residuals' correlation) is replaced, except
        # where a later refit is not taken (rare: that cross keeps an independent-pixel one)
        new = lsm(g, origin[k], res.centre[k], A, shape, s0=sm, init_err=0.3,
                  fit_shape=fit_shape, background=B, weight=wt, sat_bg=_saturated(B),
                  clip=(0.0, 1.0), fit_blur=fit_blur, correlated=p >= REFIT_ALL_PASSES - 1,
                  quant=quant if p >= REFIT_ALL_PASSES - 1 else None)
        return new, Xk

    parts = _halves(idx)
    if len(parts) == 1:
        return one(idx)
    out = thread_map(one, parts)
    return _concat([o[0] for o in out]), np.concatenate([o[1] for o in out])


def _refit_scene(stack, origin, res, bg, keep, shape, fit_shape, passes, sign, rules,
                 fit_blur=True, select=None, groups=None, quant=None):
    """LSM again with the scene under each fitted cross estimated jointly with it.

    ``passes`` times: the cross of the last fit (its blurred template ``T`` and its fitted grey
    level ``m``) is held, the scene is the TV-regularised deconvolution (TV weight
    :data:`softplot.marks.scene_tv.MU` x the median noise of the set) of
    :func:`softplot.marks.scene_tv.deconv_tv` (the first from the opening's estimate ``bg``,
    the next from the last solution), its gradient gives the prior pixel weights, and LSM is
    run from the last fit. The alternation converges slowly where a scene edge runs along a
    bar, so it goes on for the crosses that still move: after :data:`REFIT_ALL_PASSES`
    passes, only a cross the last pass moved by more than :data:`REFIT_SETTLE` x its sigma is
    refitted. Only a fit of the expected polarity ``sign`` with the contrast-to-noise of
    ``rules`` is refitted. (The joint scene can make a fit to scene content pass the
    acceptance tests: on a negative read as a positive, 25 of 121 did, and
    :func:`softplot.marks.detect.detect` refuses such a scan because its measured crosses lie
    off any grid.) A cross whose refit fails, changes polarity or moves by more than
    :data:`REFIT_MAX_MOVE` keeps its last fit. ``select`` (N bool, optional): only these
    marks are refitted (the TV weight and blur still from the whole set). ``groups`` (N int,
    optional): independent sets of marks, each refitted as by a call of its own (its own TV
    weight, blur and passes; one solve and one LSM fit for all sets that share the blur).
    ``quant``: the scan's JPEG quantisation variances for LSM's covariance
    (:func:`softplot.marks.jpegq.of_scan`).
    Patches in the pixel system (``origin`` their [0, 0] pixels).
    """
    n = len(res.centre)
    X = np.asarray(bg, np.float32).copy()  # the scene before the blur: the opening's to start
    moved = np.full(n, np.inf)  # px, by the last pass
    gid = np.zeros(n, int) if groups is None else np.asarray(groups)
    sets = [gid == v for v in np.unique(gid)]
    alive = np.ones(n, bool)  # the sets still refitted (a set whose call would have returned)
    for p in range(passes):
        ok = np.all(np.isfinite(res.centre), 1) & np.isfinite(res.s) & np.isfinite(res.noise)
        ok &= np.all(np.isfinite(res.A.reshape(n, 4)), 1)
        ok &= (np.sign(res.gain) == sign) & (res.cnr >= rules.min_cnr)
        # the TV weight from the set's median noise: a patch's own residual MAD grows with the
        # scene's misfit, and TV would flatten the very scenes it is for; it and the blur
        # from all refitted crosses, not from those still moving
        noise_set = np.zeros(n)
        s_med = np.zeros(n)
        for m in sets:
            if not alive[m].any():
                continue
            if not (ok & m).any():
                alive[m] = False
                continue
            # (median_rows: NumPy's median from one partition, the values finite here)
            noise_set[m] = max(float(median_rows(res.noise[ok & m][None])[0]), 1e-4)
            s_med[m] = float(median_rows(res.s[ok & m][None])[0])
        ok &= alive
        if select is not None:
            ok &= select
            for m in sets:
                alive[m] &= (ok & m).any()
        if p >= REFIT_ALL_PASSES:
            ok &= moved > REFIT_SETTLE * np.nan_to_num(res.sigma, nan=0.0)
            for m in sets:
                alive[m] &= (ok & m).any()
        ok &= alive
        if not ok.any():
            return res
        moved[:] = 0.0
        for sm in np.unique(s_med[ok]):  # the sets that share a blur: one solve and fit
            idx = np.where(ok & (s_med == sm))[0]
            new, X[idx] = _refit_pass(stack, origin, res, X, idx, float(sm), noise_set, keep,
                                      shape, fit_shape, fit_blur, p, quant)
            move = np.hypot(*(new.centre - res.centre[idx]).T)
            take = (np.all(np.isfinite(new.centre), 1) & (np.sign(new.gain) == sign)
                    & (move <= REFIT_MAX_MOVE))
            moved[idx[take]] = move[take]
            res = _replace(res, idx[take], new, np.where(take)[0])
    return res


def _template(shape, origin, c, A, s, hw, batch=4):
    """The blurred mark ``T`` (N, h, w) float32 of N patches (pixel system; centres ``c``,
    affines ``A``, blurs ``s``), evaluated a few patches at a time: the template's
    temporaries over whole chunks would double the fine stage's peak memory."""
    n = len(c)
    if shape.kind == "cross" and _kernels.ready():  # compiled: the same values
        margin = np.array([5.0 * float(np.max(s[a - a % batch : a - a % batch + batch])) + 1.0
                           for a in range(n)])
        return _kernels.cross_template(shape, origin, c, A, s, hw, margin)
    T = np.zeros((n,) + tuple(hw), np.float32)
    for a in range(0, n, batch):
        b = slice(a, a + batch)
        u, v = patch_frame(origin[b], c[b], A[b], (len(c[b]),) + tuple(hw))
        sb = np.broadcast_to(np.asarray(s[b], np.float32)[:, None, None], u.shape)
        # beyond 5 blur sigmas (and a pixel) of the bars the template is below 1e-6: left 0
        near = support_mask(shape, u, v, 5.0 * float(np.max(s[b])) + 1.0)
        ap = tuple(np.broadcast_to(x[:, None, None], u.shape)[near] for x in aperture(A[b]))
        T[b][near] = shape.evaluate(u[near], v[near], sb[near], aperture=ap)[0]
    return T


def _edge_weights(B, noise, delta):
    """:func:`_prior_weights` of scene estimates ``B`` (N, h, w), ``|grad B|`` by Sobel / 8
    within each patch, as :func:`scene_background` gives its own."""
    return _prior_weights(_patch_gradients(B), noise, delta)


def _patch_gradients(B):
    """``|grad B|`` (N, h, w) of each patch ``B`` (N, h, w) alone (:func:`_grad_magnitude`,
    OpenCV's reflected border), in one call: the patches stacked with the row their border
    reflects (row 1, row h - 2) above and below each (the same sums in every pixel)."""
    B = np.asarray(B, np.float32)
    n, h, w = B.shape
    if h < 3:
        return np.stack([_grad_magnitude(b) for b in B]).reshape(B.shape)
    big = np.empty((n, h + 2, w), np.float32)
    big[:, 1 : h + 1] = B
    big[:, 0] = B[:, 1]
    big[:, h + 1] = B[:, h - 2]
    return _grad_magnitude(big.reshape(n * (h + 2), w)).reshape(n, h + 2, w)[:, 1 : h + 1]


def _replace(res: LSMResult, at: np.ndarray, new: LSMResult, frm: np.ndarray) -> LSMResult:
    """``res`` with the marks ``at`` taken from ``new``'s marks ``frm``."""
    if at.size == 0:
        return res
    kw = {}
    for f in fields(LSMResult):
        a = getattr(res, f.name)
        if f.name == "iterations":
            kw[f.name] = max(a, new.iterations)
            continue
        if a is None or getattr(new, f.name) is None:
            kw[f.name] = None
            continue
        a = a.copy()
        b = getattr(new, f.name)
        a[at] = b[frm]
        kw[f.name] = a
    return LSMResult(**kw)


def _concat(results: list[LSMResult]) -> LSMResult:
    """One LSMResult of the marks of several (in order)."""
    if len(results) == 1:
        return results[0]
    kw = {f.name: (max(getattr(r, f.name) for r in results) if f.name == "iterations" else
                   np.concatenate([getattr(r, f.name) for r in results]))
          for f in fields(LSMResult)}
    return LSMResult(**kw)


#: a fit whose contrast departs from the accepted marks' contrast line (:func:`contrast_line`)
#: by more than this share of the line's value is not the mark but other content (a scene
#: feature, a JPEG copy's ringing beside a bar: fits of 1.7-2 x their peers' contrast lay
#: 1-4 px off with sigmas of 0.1-0.3 px)
CONTRAST_TOL = 0.7
#: the contrast line is fitted where at least this many marks were accepted
CONTRAST_LEAST = 8


def contrast_line(gain: np.ndarray, level: np.ndarray, ok: np.ndarray,
                  least: int = CONTRAST_LEAST) -> np.ndarray | None:
    """The accepted (``ok``) marks' contrast ``gain`` as a line in the background level under
    them (``level - gain``, grey units): ``(c0, c1)``, contrast = c0 + c1 x background; None
    with fewer than ``least`` accepted. A reseau cross is the film under its opaque lines,
    seen through the mark's opacity: its contrast is the opacity times (that level minus the
    background), linear in the background. Started at the median contrast and fitted three
    times to the marks within 0.3 of the line's value (a few fits on other content have no
    say)."""
    k = np.where(np.asarray(ok, bool) & np.isfinite(gain) & np.isfinite(level))[0]
    if k.size < least:
        return None
    g = np.asarray(gain, float)[k]
    X = np.stack([np.ones(k.size), np.asarray(level, float)[k] - g], 1)
    line = np.array([float(np.median(g)), 0.0])
    for _ in range(3):
        near = np.abs(g - X @ line) <= 0.3 * np.abs(X @ line)
        if near.sum() < max(least // 2, 3):
            break
        line = np.linalg.lstsq(X[near], g[near], rcond=None)[0]
    return line


def contrast_unlike(gain: np.ndarray, level: np.ndarray, line: np.ndarray,
                    tol: float = CONTRAST_TOL) -> np.ndarray:
    """(N,) bool: fits whose contrast departs from :func:`contrast_line`'s ``line`` at their
    background level by more than ``tol`` of the line's value."""
    pred = line[0] + line[1] * (np.asarray(level, float) - np.asarray(gain, float))
    with np.errstate(invalid="ignore"):
        return np.abs(np.asarray(gain, float) - pred) > tol * np.abs(pred)


def _accept(res, c0, A0, s0, sign, rules, anchor, max_shift, sigma_ref=None, gain_ref=None):
    """Acceptance tests: (ok mask, reasons). ``sigma_ref`` (px): the scan's accepted marks'
    median precision, the reference of the relative precision test where these marks are a
    few refits (default: the median of those accepted here, when 5 or more). ``gain_ref``:
    the peers' contrast a faint mark is held to (:func:`faint`; "set": the median of these
    fits of the expected polarity; None: no faint mark is accepted)."""
    n = len(c0)
    reason = [""] * n
    ok = np.ones(n, bool)

    def fail(mask, why):
        for i in np.where(mask & ok)[0]:
            reason[i] = why
        ok[mask] = False

    finite = np.all(np.isfinite(res.centre), 1) & np.isfinite(res.gain)
    fail(~finite, "fit failed")
    fail(np.sign(res.gain) != sign, "no mark of the expected polarity")
    shift = np.hypot(*(res.centre - anchor).T)
    weak = faint(res, rules) & finite & (shift <= rules.faint_shift * max_shift)
    if isinstance(gain_ref, str):
        mine = finite & (np.sign(res.gain) == sign)
        gain_ref = float(np.median(np.abs(res.gain[mine]))) if mine.sum() >= 3 else None
    if gain_ref is None or not np.isfinite(gain_ref):
        weak[:] = False
    else:
        g = np.abs(np.nan_to_num(res.gain))
        dim = (g >= rules.dim_gain * gain_ref) & (np.nan_to_num(res.snr) >= rules.dim_snr)
        weak &= (g >= rules.faint_gain * gain_ref) | dim
    fail((res.cnr < rules.min_cnr) & ~weak, "contrast too low")
    fail((res.score < rules.min_score) & ~weak, "does not look like the mark")
    parts_ok = (res.support >= rules.min_part_support).sum(1)
    need = min(rules.min_parts, res.support.shape[1])
    fail(parts_ok < need, "mark partly hidden")
    if res.part_gain is not None and res.part_gain.shape[1] == 4:
        fail(lone_bar(res.part_gain, res.gain, rules) >= 0, "one bar only")
    fail(shift > max_shift, "moved away from the prediction")
    det0 = np.abs(np.linalg.det(A0))
    det1 = np.abs(np.linalg.det(res.A))
    ratio = np.sqrt(det1 / np.maximum(det0, 1e-12))
    fail(np.abs(ratio - 1.0) > rules.scale_tol, "wrong size")
    dang = np.abs((_angle(res.A) - _angle(A0) + 180.0) % 360.0 - 180.0)
    fail(dang > rules.angle_tol_deg, "wrong orientation")
    sig = res.sigma
    fail(~np.isfinite(sig) | (sig > rules.max_sigma), "imprecise")
    # far less precise than its peers: partly hidden or on conflicting scene content
    if sigma_ref is None and ok.sum() >= 5:
        sigma_ref = float(np.median(sig[ok]))
    if sigma_ref is not None:
        fail(sig > rules.max_sigma_ratio * sigma_ref, "imprecise")
    s_med = float(np.median(res.s[ok])) if ok.any() else s0
    fail(res.s > 3.0 * s_med + 1.5, "too blurred")
    return ok, reason


def faint(res: LSMResult, rules: AcceptRules) -> np.ndarray:
    """(N,) bool: fits that are a faint mark, evident over its pixels though weak per pixel.

    The matched-filter signal-to-noise ``snr`` is at least ``rules.min_snr``, and the score
    at least ``rules.faint_score`` x ``snr / sqrt(snr^2 + npix)``, the correlation of a
    perfect fit with white noise of the fit's own level over its ``npix`` pixels: the residual
    is noise, not scene structure the mark does not explain.
    """
    if res.snr is None:
        return np.zeros(len(res.centre), bool)
    snr = np.nan_to_num(res.snr, nan=0.0)
    expected = snr / np.sqrt(snr**2 + np.maximum(res.npix, 1))
    return (snr >= rules.min_snr) & (res.score >= rules.faint_score * expected)


def _chunks(idx, sets, chunk):
    """The marks ``idx`` in chunks of at most ``chunk`` of each set (``sets`` (N,) int), each
    set split as a call of its own would split it; the j-th chunks of the first and of the
    second half of the sets together (two chunks: work for two threads; the sets are
    independent, so the results do not depend on how they are packed)."""
    subs = []
    for v in np.unique(sets[idx]):
        k = idx[sets[idx] == v]
        subs.append(np.array_split(k, -(-k.size // max(1, int(chunk)))))
    if len(subs) == 1:
        return subs[0]
    h = -(-len(subs) // 2)
    return [np.concatenate([x[j] for x in half if j < len(x)])
            for half in (subs[:h], subs[h:])
            for j in range(max(len(x) for x in half))]


def _take(res: LSMResult, k: np.ndarray) -> LSMResult:
    """The marks ``k`` of ``res``."""
    return LSMResult(**{f.name: (getattr(res, f.name) if f.name == "iterations"
                                 or getattr(res, f.name) is None else getattr(res, f.name)[k])
                        for f in fields(LSMResult)})


def _accept_sets(res, c0, A0, s0, sign, rules, anchor, max_shift, sets, sigma_ref=None,
                 gain_ref=None):
    """:func:`_accept` of each set of marks (``sets`` (N,) int) on its own."""
    vals = np.unique(sets)
    if len(vals) == 1:
        return _accept(res, c0, A0, s0, sign, rules, anchor, max_shift, sigma_ref, gain_ref)
    ok = np.zeros(len(c0), bool)
    why = [""] * len(c0)
    for v in vals:
        k = np.where(sets == v)[0]
        o, w = _accept(_take(res, k), c0[k], A0[k], s0, sign, rules, anchor[k], max_shift,
                       sigma_ref, gain_ref)
        ok[k] = o
        for j, i in enumerate(k):
            why[i] = w[j]
    return ok, why


def merge_fine(n, pieces) -> Fine:
    """One :class:`Fine` of N marks from ``(indices, Fine)`` pieces."""
    f0 = pieces[0][1]
    kw = {}
    for f in fields(Fine):
        a = getattr(f0, f.name)
        if f.name == "lsm":
            kw[f.name] = None
        elif f.name == "scene_tv":
            kw[f.name] = max(getattr(p, f.name) for _, p in pieces)
        elif f.name == "opacity":
            kw[f.name] = min(getattr(p, f.name) for _, p in pieces)
        elif f.name == "reason":
            r = [""] * n
            for k, p in pieces:
                for j, i in enumerate(k):
                    r[i] = p.reason[j]
            kw[f.name] = r
        elif a is None:
            kw[f.name] = None
        else:
            out = np.zeros((n,) + a.shape[1:], a.dtype)
            for k, p in pieces:
                out[k] = getattr(p, f.name)
            kw[f.name] = out
    return Fine(**kw)


#: :func:`measure` refits chunks with the joint scene ahead of its decision
#: (:class:`_Ahead`), on a thread that would otherwise wait for the first pass's last chunk
REFIT_AHEAD = True


def _likely_busy(outs, sign, rules, busy) -> bool:
    """Whether the first fits ``outs`` ((LSMResult, edge, held) of the chunks done so far)
    already show a busy scene: ``busy`` of the edges of the fits of the expected polarity
    ``sign`` with the contrast-to-noise of ``rules`` (what the acceptance tests mostly keep).
    A guess: it only decides what :class:`_Ahead` starts early."""
    e = [o[1][(np.sign(o[0].gain) == sign) & (o[0].cnr >= rules.min_cnr)] for o in outs]
    return bool(e) and busy(np.concatenate(e))


class _Ahead:
    """The first pass of :func:`measure`'s chunks (``run``) with the refit of finished chunks
    with the joint scene (``rerun``) started ahead of the decision: a pool thread that finds
    no first-pass chunk left to start while another is still fitted (it would wait) refits a
    finished chunk, as long as ``likely`` (:func:`_likely_busy`) of the chunks done says the
    scene is busy. Each refit is the one :func:`measure` makes after the decision, on a pool
    thread as there, so the values are the same to the last bit; where the decision is no
    joint scene they are not used (only a waiting thread's time was spent)."""

    def __init__(self, parts, run, rerun, likely):
        self.parts, self.run, self.rerun, self.likely = parts, run, rerun, likely
        self.lock = threading.Lock()
        self.started = 0  # first-pass chunks started
        self.running = 0  # ... and not finished
        self.outs: dict = {}  # chunk -> its first fits, (LSMResult, edge, held)
        self.free: list = []  # finished chunks not refitted
        self.refits: dict = {}  # chunk -> its refit, made ahead

    def first(self, i):
        """The first pass of chunk ``i`` (its ``run``), then refits ahead while the thread
        would wait."""
        with self.lock:
            self.started += 1
            self.running += 1
        o = self.run(self.parts[i])
        with self.lock:
            self.running -= 1
            self.outs[i] = o
            self.free.append(i)
        while True:
            with self.lock:
                if (self.started < len(self.parts) or self.running == 0 or not self.free
                        or not self.likely([self.outs[j] for j in sorted(self.outs)])):
                    break
                j = self.free.pop(0)
            try:
                self.refits[j] = self.rerun(self._item(j))
            except Exception:  # noqa: BLE001 - made again after the decision, if wanted
                break
        return o

    def _item(self, j):
        o = self.outs[j]
        return (self.parts[j], o[0], o[2], o[1])

    def rest(self, items) -> list:
        """The refits of every chunk (``items`` as ``rerun`` takes them): those made ahead,
        the others now (on pool threads, :func:`softplot.runtime.pooled_map`)."""
        todo = [j for j in range(len(items)) if j not in self.refits]
        got = dict(self.refits)
        got.update(zip(todo, pooled_map(self.rerun, [items[j] for j in todo]), strict=True))
        return [got[j] for j in range(len(items))]


def measure(scan, shape: MarkShape, c0: np.ndarray, A0: np.ndarray, s0: float,
            init_err: float, sign: int, rules: AcceptRules | None = None,
            fit_shape: bool = True, scene: bool = True, anchor: np.ndarray | None = None,
            max_shift: float | None = None, chunk: int = 20,
            drop_part: int | None = None, scene_tv: int = 0, auto_tv: int = 0,
            busy=None, blur: float | None = None, sigma_ref: float | None = None,
            contrast: bool = False, gain_ref: float | str | None = None,
            opacity: bool = False) -> Fine:
    """LSM at full resolution from initial centres, then the acceptance tests.

    Marks are fitted in chunks of at most ``chunk`` (bounded memory), on the process's threads;
    the acceptance tests see them all at once. A first pass trusts ``c0`` to
    half a pixel (no capture stage); marks that fail the acceptance tests are fitted again
    from ``anchor`` (the prediction) with the capture stage for ``init_err``, and an accepted
    outcome replaces the first; the retry holds the blur at the median of the first pass's
    accepted marks (when there are 5 or more).

    Parameters
    ----------
    scan : Scan
    shape : MarkShape
        Nominal mark geometry (px).
    c0 : (N, 2)
        Initial centres (pixel system).
    A0 : (N, 2, 2)
        Predicted pixel -> mark-frame affine of each mark (from the global model).
    s0 : float
        Starting blur (px).
    init_err : float
        Largest expected error of ``c0`` (px).
    sign : int
        Expected sign of the mark's gain: -1 dark marks (positive), +1 bright (negative).
    rules : AcceptRules, optional
    anchor, max_shift : (N, 2) and float, optional
        A fitted centre farther than ``max_shift`` px from ``anchor`` (the model's prediction)
        is not accepted; default ``c0`` and ``max_shift_factor * init_err + 1``.
    drop_part : int or (N,) int, optional
        Crosses only: one half-arm (0: +u, 1: +v, 2: -u, 3: -v of the mark frame) gets weight
        0, so the mark is measured from the other three. Per mark: the marks of each value
        are measured as by a call of their own (their own chunks, acceptance tests and joint
        scene's TV weight), batched into common fits where the blur is held (``blur``).
    blur : float, optional
        Hold the blur at this value (px) in every fit instead of estimating it.
    sigma_ref : float, optional
        The precision (px) of the scan's accepted marks (median): a fit more than
        ``rules.max_sigma_ratio`` times less precise is refused ("imprecise"), also where
        only a few marks are fitted (refits, retries; a fit 60 times less precise than its
        peers had locked onto the scene 12 px away). Default: the median of the marks this
        call accepts (when 5 or more); the retry uses the first pass's.
    contrast : bool
        Also refuse fits whose contrast is unlike the accepted marks' (:func:`contrast_unlike`
        of the :func:`contrast_line` of this call's first pass, where it accepts
        :data:`CONTRAST_LEAST` or more; the retry is judged by the same line).
    gain_ref : float or "set", optional
        The contrast (grey units, :attr:`Fine.gain`) of the scan's marks: a faint mark
        (:func:`faint`) is accepted only with at least ``rules.faint_gain`` of it. "set": the
        median of this call's first fits of the expected polarity (all the scan's marks at
        once); None (default): no faint mark is accepted (refits of a few marks).
    opacity : bool
        Crosses of an opaque ``shape`` with ``auto_tv``: where the joint scene is taken, the
        crosses' opacity is first estimated from the scene seen through the bars of the
        first pass's accepted fits (:func:`_estimated_opacity`), and the refits with the
        joint scene (and the retry) fit crosses of that opacity. ``Fine.opacity`` tells
        which was used.
    scene_tv : int
        Crosses only: after the first fit, this many refits with the scene under each cross
        estimated jointly with it (:func:`_refit_scene`); 0 keeps the opening's estimate.
    auto_tv, busy : int and callable, optional
        With ``scene_tv`` 0: when ``busy(edge)`` is true of the :func:`_footprint_gradient` figures
        of the marks the first pass accepted, the first pass is refitted with ``auto_tv``
        joint-scene passes (its fits reused), and so is the retry. ``Fine.scene_tv`` tells
        which was used.
    """
    rules = rules or AcceptRules()
    c0 = np.asarray(c0, float).reshape(-1, 2)
    n = len(c0)
    fit_blur = blur is None
    if blur is not None:
        s0 = float(blur)
    A0 = np.broadcast_to(np.asarray(A0, float), (n, 2, 2))
    if n == 0:
        z = np.zeros(0)
        return Fine(np.zeros((0, 2)), np.zeros((0, 2, 2)), z, z, np.zeros(0, bool), [], None,
                    np.zeros((0, 2, 2)), z, cov_white=np.zeros((0, 2, 2)),
                    cov_jpeg=np.zeros((0, 2, 2)))
    if anchor is None:
        anchor, max_shift = c0, rules.max_shift_factor * init_err + 1.0
    anchor = np.asarray(anchor, float).reshape(-1, 2)
    sets = np.zeros(n, int)
    if drop_part is not None and np.ndim(drop_part):
        drop_part = np.asarray(drop_part).reshape(n)
        vals, sets = np.unique(drop_part, return_inverse=True)
        if len(vals) == 1:
            drop_part = int(vals[0])
        elif fit_blur or (auto_tv and not scene_tv):
            # each set's own blur (or choice of scene model): one call per set
            out = []
            for v in vals:
                k = np.where(drop_part == v)[0]
                out.append((k, measure(scan, shape, c0[k], A0[k], s0, init_err, sign, rules,
                                       fit_shape, scene, anchor[k], max_shift, chunk, int(v),
                                       scene_tv, auto_tv, busy, blur)))
            return merge_fine(n, out)
    multi = sets.max() > 0
    xy = np.full((n, 2), np.nan)
    cov = np.full((n, 2, 2), np.nan)
    cov_w = np.full((n, 2, 2), np.nan)
    cov_j = np.zeros((n, 2, 2))
    score = np.full(n, np.nan)
    cnr = np.full(n, np.nan)
    ok = np.zeros(n, bool)
    Afit = np.full((n, 2, 2), np.nan)
    edge = np.full(n, np.nan)
    s_fit = np.full(n, np.nan)
    gain = np.full(n, np.nan)
    reason = [""] * n
    fast = min(init_err, 0.6)
    passes = [(np.arange(n), fast)]
    plane = bool(scene) and not scene_tv and flat_scan(scan, shape, c0, A0, s0, fast, sign)
    line = None  # the first pass's contrast line (``contrast``)
    for p_i in range(2):
        idx, ie = passes[p_i] if p_i < len(passes) else (None, None)
        if idx is None or idx.size == 0:
            break
        retry = []
        # the retry starts from the model's prediction (the anchor): the first start may have
        # been a scene feature
        starts = c0 if p_i == 0 else anchor

        # the scene-edge figures only where they decide: the first pass of an "auto" call
        want = p_i == 0 and not scene_tv and bool(auto_tv) and busy is not None

        def run(k, starts=starts, ie=ie, tv=scene_tv, want=want, s0=s0, fb=fit_blur,
                shape=shape):
            # with ``want``, the opening's estimate under the crosses with a scene edge is
            # kept for the refit with the joint scene below (not computed twice)
            held = [] if want and REUSE_OPENING else None
            res, e = _fit(scan, shape, starts[k], A0[k], s0, ie, sign, fit_shape, scene,
                          drop_part[k] if multi else drop_part, tv, rules, edges=want,
                          fit_blur=fb, groups=sets[k] if multi else None, bg_out=held,
                          plane=plane)
            return res, e, (held[0] if held else None)

        # chunks are independent: fitted on the process's threads (runtime.thread_map); the
        # acceptance tests then see all marks at once, so the outcome does not depend on how
        # the marks were chunked. A set that fits one chunk (refits, retries) is one: split in
        # two it was slower (the fit of a few marks is mostly Python, which holds the GIL).
        # The chunking does not depend on the thread count (the same results on any machine)
        def rerun(a, starts=starts, ie=ie, tv=auto_tv, s0=s0, fb=fit_blur, shape=shape):
            # the refit with the joint scene (below) of one chunk ``k`` from its first fits:
            # only the crosses with a scene edge in their footprint ``e``
            # (:data:`softplot.marks.scene_tv.EDGE_MIN`): the others keep the opening's fit;
            # ``shape`` the crosses' (with the opacity found, below)
            k, first, held, e = a
            sel = e > _scene_tv.EDGE_MIN
            if not sel.any():
                return first
            return _fit(scan, shape, starts[k], A0[k], s0, ie, sign, fit_shape, scene,
                        drop_part, tv, rules, first, fit_blur=fb, tv_select=sel,
                        scene_bg=held)[0]

        parts = _chunks(idx, sets, chunk)
        idx = np.concatenate(parts)  # (the order of the chunks, set by set)
        ahead = None
        if want and REFIT_AHEAD and len(parts) >= 3 and concurrent():
            ahead = _Ahead(parts, run, rerun, lambda o: _likely_busy(o, sign, rules, busy))
            out = thread_map(ahead.first, range(len(parts)))
        else:
            out = thread_map(run, parts)
        res = _concat([o[0] for o in out])
        if p_i == 0:
            edge[idx] = np.concatenate([o[1] for o in out])
        good, why = _accept_sets(res, starts[idx], A0[idx], s0, sign, rules, anchor[idx],
                                 max_shift, sets[idx], sigma_ref, gain_ref)
        if want and busy(edge[idx][good]):
            # the scene has sharp edges at the marks: the same fits refitted with the joint
            # scene (what a call with scene_tv=auto_tv gives, without fitting twice); the
            # chunks refitted ahead (:class:`_Ahead`) are taken as they are, unless the
            # crosses let the scene show through (then all are refitted as such)
            scene_tv = auto_tv
            items = [(k, o[0], o[2], o[1]) for k, o in zip(parts, out, strict=True)]
            refit = rerun
            if opacity and shape.kind == "cross" and shape.opacity == 1.0:
                a = _estimated_opacity(scan, shape, res, good, A0[idx], s0, ie)
                if a != 1.0:
                    shape, ahead = shape.with_opacity(a), None
                    items = [(k, _seen_through(f, a), h, e) for k, f, h, e in items]
                    refit = functools.partial(rerun, shape=shape)
            res = _concat(ahead.rest(items) if ahead is not None else thread_map(refit, items))
            good, why = _accept(res, starts[idx], A0[idx], s0, sign, rules, anchor[idx],
                                max_shift, sigma_ref, gain_ref)
        if contrast:
            if p_i == 0:
                line = contrast_line(res.gain, res.level, good)
            if line is not None:
                unlike = good & contrast_unlike(res.gain, res.level, line)
                good = good & ~unlike
                for j in np.where(unlike)[0]:
                    why[j] = "contrast unlike its peers'"
        for j, i in enumerate(idx):
            if p_i == 0 or good[j]:
                xy[i], cov[i], Afit[i] = res.centre[j], res.cov[j], res.A[j]
                score[i], cnr[i], ok[i], reason[i] = res.score[j], res.cnr[j], good[j], why[j]
                s_fit[i], gain[i] = res.s[j], res.gain[j]
                cov_w[i], cov_j[i] = res.cov_white[j], res.cov_jpeg[j]
            if not good[j]:
                retry.append(i)
        if p_i == 0 and retry:
            passes.append((np.array(retry, int), max(init_err, fast + 0.2)))
            if sigma_ref is None and good.sum() >= 5:  # the retry judged against the first
                sigma_ref = float(np.median(res.sigma[good]))
            if isinstance(gain_ref, str):  # and held to the first pass's contrast
                mine = np.isfinite(res.gain) & (np.sign(res.gain) == sign)
                gain_ref = float(np.median(np.abs(res.gain[mine]))) if mine.sum() >= 3 else None
            held = median_blur(res.s, good) if fit_blur else None
            if held is not None:
                # the retry holds the accepted marks' median blur (a free blur let fits of
                # marks on conflicting scene content run to 3-25 px)
                s0, fit_blur = held, False
    arms = np.where(ok, 2, 0) if shape.kind == "cross" else None
    return Fine(xy, cov, score, cnr, ok, reason, None, Afit, edge, scene_tv, s_fit, arms,
                cov_w, gain, cov_j, opacity=shape.opacity)


#: :func:`_estimated_opacity` reads at most this many of the accepted crosses (its time is
#: on the busy scans' serial path, between the first pass and the joint scene's refits)
OPACITY_CROSSES = 32


def _estimated_opacity(scan, shape, res, good, A0, s0, init_err) -> float:
    """The opacity (:func:`softplot.marks.opacity.estimate`, :func:`~softplot.marks.opacity.
    shrink`) of the crosses of the fits ``res`` that ``good`` accepted (at most
    :data:`OPACITY_CROSSES`, evenly spread; patches as :func:`_fit` cuts them for affines
    ``A0``, blur ``s0``, start error ``init_err``); 1 where it cannot tell."""
    k = np.where(good)[0]
    if k.size == 0:
        return 1.0
    if k.size > OPACITY_CROSSES:  # evenly over the accepted (a few thousand pixels suffice)
        k = k[np.round(np.linspace(0, k.size - 1, OPACITY_CROSSES)).astype(int)]
    stack, origin = patches(scan, res.centre[k], _half(shape, A0[k], s0, init_err))
    a, se, cnt = _opacity.estimate(stack, origin, shape, res.centre[k], res.A[k], res.s[k],
                                   res.noise[k])
    return _opacity.shrink(a, se, cnt)


def _seen_through(res: LSMResult, a: float) -> LSMResult:
    """Fits of opaque crosses ``res`` as the start of fits of crosses of opacity ``a``: the
    mark's own level from the contrast seen (``gain``, :attr:`LSMResult.gain`)."""
    bg = res.level - res.gain
    out = _take(res, np.arange(len(res.level)))
    out.level = bg + res.gain / a
    return out


def lone_bar(part_gain: np.ndarray, gain: np.ndarray, rules: AcceptRules) -> np.ndarray:
    """Crosses of which only one bar is there, from the contrast of each half-arm alone
    (:attr:`softplot.marks.lsm.LSMResult.part_gain`) relative to the stronger bar's (the mean
    of its halves; the whole cross's contrast is diluted by a missing bar): every half of
    the other bar that has pixels is below ``rules.bar_absent`` of it, every half of this
    one above ``rules.bar_present``. Returns the axis of the bar that is there (0: u,
    1: v) or -1, per cross (a half without weighted pixels, NaN, counts for neither)."""
    r = np.asarray(part_gain, float) * np.sign(np.asarray(gain, float))[:, None]
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: no bar, NaN
        bars = np.stack([np.nanmean(r[:, [0, 2]], 1), np.nanmean(r[:, [1, 3]], 1)], 1)
        ref = np.nanmax(bars, 1)
        q = r / ref[:, None]
    fin = np.isfinite(q)

    def every(a, b, test):
        return (fin[:, a] | fin[:, b]) & (~fin[:, a] | test(q[:, a])) & (~fin[:, b] | test(q[:, b]))

    absent = lambda x: x < rules.bar_absent  # noqa: E731
    there = lambda x: x > rules.bar_present  # noqa: E731
    ok = np.isfinite(ref) & (ref > 0)
    out = np.full(len(r), -1)
    out[ok & every(0, 2, there) & every(1, 3, absent)] = 0
    out[ok & every(1, 3, there) & every(0, 2, absent)] = 1
    return out


def _bars_at(shape: MarkShape, u, v, m, s, ap) -> tuple:
    """:meth:`MarkShape.bars` of N patches (mark-frame ``u``, ``v`` (N, h, w) px, blur ``s``
    px, the footprints ``ap`` of :func:`aperture`, (N,) each) evaluated at the pixels ``m``
    (N, h, w) bool only, 0 elsewhere ((N, h, w) each): the profiles are elementwise,
    so each value is the one the whole patches give, at a fraction of the work (the pixels
    near a cross are a part of its patch)."""
    ap_m = tuple(np.broadcast_to(x[:, None, None], u.shape)[m] for x in ap)
    out = []
    for b in shape.bars(u[m], v[m], s, aperture=ap_m):
        a = np.zeros(u.shape, b.dtype)
        a[m] = b
        out.append(a)
    return tuple(out)


def bar_share(scan, shape: MarkShape, c: np.ndarray, A: np.ndarray, s: float,
              sign: int) -> np.ndarray:
    """The weaker bar's contrast over the stronger's (N,) for crosses at ``c`` (N, 2, pixel
    system) with pixel -> mark-frame affines ``A`` (N, 2, 2) and blur ``s`` (px), without a
    fit: each patch's pixels near the cross (:func:`softplot.marks.lsm.support_mask`) are
    regressed on a plane and on what each bar adds to the cross and the central square
    they share (:meth:`MarkShape.bars`), so that a blurred central square does not lend a
    missing bar its contrast. A contrast of the wrong polarity (``sign``) counts as 0; NaN
    where the regression is singular or neither bar has contrast. Near 1 for a whole cross,
    near 0 for a one-armed one."""
    c = np.asarray(c, float).reshape(-1, 2)
    n = len(c)
    if n == 0 or shape.kind != "cross":
        return np.full(n, np.nan)
    A = np.asarray(A, float).reshape(n, 2, 2)
    grow = float(1.0 / max(np.linalg.svd(A, compute_uv=False).min(), 1e-3))
    # the bars' own parts show within a few blurs of the central square: a long cross is
    # looked at there only (mark-frame half-size ``reach``, px)
    reach = min(shape.extent + 2.5 * s + 1.25, 0.5 * shape.width + 6.0 * s + 6.0)
    half = int(np.ceil(reach * grow + 2))
    stack, origin = patches(scan, c, half)
    u, v = patch_frame(origin, c, A, stack.shape)
    m = (support_mask(shape, u, v, 2.5 * s + 1.25) & np.isfinite(stack)
         & (np.maximum(np.abs(u), np.abs(v)) <= reach))
    bu, bv, core = _bars_at(shape, u, v, m, np.float32(max(s, 0.3)),
                            aperture(A.astype(np.float32)))
    return _bar_regression(stack, m, bu, bv, core, half, sign)


def _bar_regression(stack, m, bu, bv, core, half: int, sign: int) -> np.ndarray:
    """:func:`bar_share`'s regression: each patch of ``stack`` (N, h, w; pixel system, the
    cross at pixel ``(half, half)``) over its pixels ``m`` on a plane, on what each bar adds
    (``bu - core``, ``bv - core``) and on the central square ``core``; the weaker bar's
    contrast over the stronger's, ``(N,)`` (NaN where singular or neither has contrast)."""
    n = len(stack)
    yy, xx = np.mgrid[0 : stack.shape[1], 0 : stack.shape[2]].astype(np.float32)
    X = np.stack(np.broadcast_arrays(m.astype(np.float32), (xx - half) * m, (yy - half) * m,
                                     (bu - core) * m, (bv - core) * m, core * m), -1)
    X = X.reshape(n, -1, 6)
    g = np.where(m, stack, 0.0).reshape(n, -1)
    Xt = X.transpose(0, 2, 1)
    N = np.matmul(Xt, X).astype(float)
    rhs = np.matmul(Xt, g[..., None])[..., 0].astype(float)
    scale = np.sqrt(np.maximum(np.einsum("nii->ni", N), 1e-12))
    Ns = N / scale[:, :, None] / scale[:, None, :]  # unit diagonal: its conditioning
    ok = np.abs(np.linalg.det(Ns)) > 1e-8
    b = np.full((n, 6), np.nan)
    if ok.any():
        b[ok] = np.linalg.solve(Ns[ok], (rhs[ok] / scale[ok])[..., None])[..., 0] / scale[ok]
    con = np.maximum(b[:, 3:5] * sign, 0.0)
    with np.errstate(all="ignore"):
        return np.where(con.max(1) > 0, con.min(1) / con.max(1), np.nan)


def lone_arm_keep(shape: MarkShape, u, v, axis: int) -> np.ndarray:
    """Pixels of a cross's bar along mark-frame axis ``axis`` (0: the u bar, 1: the v bar):
    those nearer that axis than the other, i.e. the two half-arms of the bar and its half of
    the central square (mark-frame ``u``, ``v`` in px)."""
    return np.abs(v) <= np.abs(u) if axis == 0 else np.abs(u) <= np.abs(v)


def _bar_refit(stack, origin, c0, A0, shape, s_fit, blur, bg, wt, fits, axis_of, one,
               max_shift):
    """The lone bars ``one`` (N bool) fitted again with the model of a bar alone
    (:class:`MarkShape` "bar", along mark-frame axis ``axis_of`` (N,) of the cross) over
    every pixel near it, from the position across the bar their first fit gave (``fits``:
    per axis ``(LSMResult, normal across the bar (N, 2), offset across from c0 (N,))``).
    The first fit's model is the whole cross over the bar's pixels nearer its axis than the
    other's: it leaves out the bar's pixels by the centre and keeps the missing bar's
    blurred edges there in the model. ``stack`` (N, h, w) with ``origin`` (N, 2), ``c0``
    (N, 2) pixel system, ``A0`` (N, 2, 2) pixel -> mark-frame affines, ``bg``, ``wt`` the
    scene and prior weights of :func:`scene_background`. Returns ``(offset across from c0
    (N,) px, its variance (N,) px^2, its independent-pixel variance (N,))``, NaN where not
    refitted, where the refit moved more than ``max_shift`` across or changed polarity."""
    n = len(c0)
    out = (np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan))
    k = np.where(one)[0]
    if k.size == 0:
        return out
    ax = axis_of[k]
    A = A0[k].copy()
    A[ax == 1] = A[ax == 1][:, ::-1, :]  # the v bar: its axis as the bar's u
    pick = [fits[int(a)] for a in ax]
    nrm = np.stack([f[1][i] for f, i in zip(pick, k, strict=True)])
    start = np.array([f[2][i] for f, i in zip(pick, k, strict=True)])
    g0 = np.array([f[0].gain[i] for f, i in zip(pick, k, strict=True)])
    res = lsm(stack[k], origin[k], c0[k] + start[:, None] * nrm, A,
              MarkShape("bar", length=shape.length, width=shape.width), s0=s_fit,
              init_err=0.3, fit_shape=False, background=bg[k], weight=wt[k],
              sat_bg=_saturated(bg[k]), clip=(0.0, 1.0), fit_blur=blur is None,
              arm_check=False)
    off = np.einsum("ij,ij->i", res.centre - c0[k], nrm)
    var = np.einsum("ij,ijk,ik->i", nrm, res.cov, nrm)
    var_w = np.einsum("ij,ijk,ik->i", nrm, res.cov_white, nrm)
    good = (np.abs(np.nan_to_num(off, nan=np.inf)) <= max_shift) & np.isfinite(var)
    good &= (var > 0) & (np.sign(res.gain) == np.sign(g0))
    for a, b in zip(out, (off, var, var_w), strict=True):
        a[k[good]] = b[good]
    return out


def _other_bar_absent(fits, sign: int, share: float | np.ndarray, strict: bool = False,
                      min_score: float | np.ndarray | None = None) -> np.ndarray:
    """(N, 2) bool: for each of the two lone-bar fits of N crosses (``fits``, per axis
    ``(LSMResult, ...)``), whether the other bar's fit has less than ``share`` of its
    contrast (of the expected polarity ``sign``; ``strict``: of either sign, and a fit
    that did not run counts as there); with ``min_score``, and this bar's fit correlates
    with its model at least that well (``share``, ``min_score``: a number or (N,))."""
    g = [np.nan_to_num(np.abs(np.where(np.sign(f[0].gain) == sign, f[0].gain, 0.0)), nan=0.0)
         for f in fits]
    other = ([np.nan_to_num(np.abs(f[0].gain), nan=np.inf) for f in fits] if strict else g)
    out = np.stack([other[1] < share * g[0], other[0] < share * g[1]], 1)
    if min_score is not None:
        out &= np.stack([np.nan_to_num(f[0].score, nan=-1.0) >= min_score for f in fits], 1)
    return out


def measure_one_arm(scan, shape: MarkShape, c0: np.ndarray, A0: np.ndarray, s0: float,
                    sign: int, rules: AcceptRules | None = None, *, max_shift: float,
                    cnr_ref: float | None = None, pred_cov: np.ndarray | None = None,
                    blur: float | None = None, gain_ref: float | None = None,
                    absent: float | np.ndarray | None = None,
                    min_score: float | np.ndarray | None = None) -> Fine:
    """Crosses of which only one bar is visible (the other faded, aliased, scratched or
    covered), measured as a line: precise across the bar, nothing along it.

    Each cross is fitted twice from its predicted centre ``c0`` (pixel system) with the
    predicted affine ``A0`` held: once with only the pixels of the u bar, once with only
    those of the v bar (:func:`lone_arm_keep`; the others are left out, as outside the
    scan), scene and robust weights as in :func:`measure`. A bar is accepted when the other
    bar's fit finds less than ``rules.bar_absent`` of its contrast, and its fit
    passes the acceptance tests of ``rules`` for its two half-arms (polarity, contrast to
    noise, correlation with the bar, both half-arms supported, at most ``max_shift`` px
    across from ``c0``) and, with ``cnr_ref`` (the two-armed crosses' median contrast to
    noise), its contrast to noise is at least half that, or, with ``gain_ref`` (their median
    contrast, grey units), its contrast is: a bar of the reseau, not a faint scene line (the
    noise under a lone bar, a scene's or a dark region's, is not the crosses'); with
    ``gain_ref`` its contrast is at least :data:`LONE_BAR_MIN_GAIN` of it in any case. Of two
    accepted bars the better-correlated is kept (a cross whose two bars both pass is a
    whole cross the caller's tests refused: not claimed here). With ``absent`` the other
    bar must be absent more plainly: its fit ran (finite) and its contrast, of either sign,
    is less than ``absent`` of this bar's; with ``min_score`` this bar's correlation with
    its model is at least that (a second look at crosses measured whole; each a number or
    one per cross, (N,)).

    The bar fixes the centre across it only: its tips are the part of a cross that fades
    first, and its length is not known (a certificate's is a starting guess). So the
    centre is the fit's across the bar and the prediction ``c0`` along it; the covariance
    (pixel system) is the fit's variance across the bar and, along it, the variance of
    ``c0`` along the bar: ``t^T pred_cov t`` (``pred_cov`` (N, 2, 2) px^2, pixel system, the
    prediction's covariance; ``t`` the bar's unit vector; None: 1 px^2). The fit across the bar is a
    second one with the model of the bar alone over all its pixels (:func:`_bar_refit`;
    the first one's where that fails). ``Fine.arms`` is 1 where a bar
    was measured, 0 elsewhere; ``Fine.bar`` the measured bar's unit vector ``t`` (pixel
    system), NaN elsewhere.
    """
    rules = rules or AcceptRules()
    c0 = np.asarray(c0, float).reshape(-1, 2)
    n = len(c0)
    A0 = np.broadcast_to(np.asarray(A0, float), (n, 2, 2)).copy()
    pred_cov = (np.broadcast_to(np.eye(2), (n, 2, 2)) if pred_cov is None
                else np.asarray(pred_cov, float).reshape(n, 2, 2))
    out = Fine(np.full((n, 2), np.nan), np.full((n, 2, 2), np.nan), np.full(n, np.nan),
               np.full(n, np.nan), np.zeros(n, bool), ["no bar found"] * n, None,
               A0.copy(), None, 0, np.full(n, np.nan), np.zeros(n, int),
               np.full((n, 2, 2), np.nan))
    out.bar = np.full((n, 2), np.nan)
    if n == 0 or shape.kind != "cross":
        return out
    s_fit = float(blur) if blur is not None else s0
    sv = np.linalg.svd(A0, compute_uv=False)
    grow = float(1.0 / max(sv.min(), 1e-3))
    half = int(np.ceil(shape.extent * grow + 3.0 * s_fit + 3))
    stack, origin = patches(scan, c0, half)
    bg, wt, _ = scene_background(stack, shape, s_fit, sign)
    u, v = patch_frame(origin, c0, A0, stack.shape)
    passed = np.zeros((n, 2), bool)
    fits = []
    for axis in (0, 1):
        keep = lone_arm_keep(shape, u, v, axis)
        st = np.where(keep, stack, np.nan).astype(np.float32)
        res = lsm(st, origin, c0, A0, shape, s0=s_fit, init_err=0.5, fit_shape=False,
                  background=bg, weight=wt, sat_bg=_saturated(bg), clip=(0.0, 1.0),
                  fit_blur=blur is None, arm_check=False)
        parts = (0, 2) if axis == 0 else (1, 3)
        ok = np.all(np.isfinite(res.centre), 1) & np.isfinite(res.gain)
        ok &= np.sign(res.gain) == sign
        ok &= res.cnr >= rules.min_cnr
        ok &= res.score >= rules.min_score
        ok &= np.all(res.support[:, parts] >= rules.min_part_support, 1)
        # across the bar: the normal of the bar in the pixel system (the gradient of the
        # mark-frame coordinate across it)
        nrm = A0[:, 1 - axis, :] / np.linalg.norm(A0[:, 1 - axis, :], axis=1)[:, None]
        across = np.einsum("ij,ij->i", res.centre - c0, nrm)
        ok &= np.abs(np.nan_to_num(across, nan=np.inf)) <= max_shift
        ok &= np.nan_to_num(res.sigma, nan=np.inf) <= rules.max_sigma
        if cnr_ref is not None and cnr_ref > 0:
            strong = res.cnr >= 0.5 * cnr_ref
            if gain_ref is not None and gain_ref > 0:
                strong |= np.abs(np.nan_to_num(res.gain)) >= 0.5 * gain_ref
            ok &= strong
        if gain_ref is not None and gain_ref > 0:
            # and never a bar of almost no contrast: over a region that exposes nothing the
            # 8-bit noise is quantised away, and a fit of no contrast has a large CNR
            ok &= np.abs(np.nan_to_num(res.gain)) >= LONE_BAR_MIN_GAIN * gain_ref
        passed[:, axis] = ok
        fits.append((res, nrm, across))
    # the other bar must be absent: its own fit has less than bar_absent of this bar's
    # contrast (a cross whose second bar is there but was refused - pulled by the scene,
    # partly hidden - is not measured from one bar)
    passed &= _other_bar_absent(fits, sign, rules.bar_absent if absent is None else absent,
                                strict=absent is not None, min_score=min_score)
    one = passed.sum(1) == 1
    axis_of = np.argmax(passed, 1)
    bar = _bar_refit(stack, origin, c0, A0, shape, s_fit, blur, bg, wt, fits, axis_of, one,
                     max_shift)
    for i in np.where(one)[0]:
        res, nrm, across = fits[int(axis_of[i])]
        nv = nrm[i]
        tv = np.array([-nv[1], nv[0]])
        if np.isfinite(bar[0][i]):  # the bar's own model
            off, var_n, var_w = bar[0][i], bar[1][i], bar[2][i]
        else:
            off = across[i]
            var_n = float(nv @ res.cov[i] @ nv)
            var_w = float(nv @ res.cov_white[i] @ nv)
        out.xy[i] = c0[i] + off * nv
        var_t = float(tv @ pred_cov[i] @ tv)
        out.cov[i] = var_n * np.outer(nv, nv) + var_t * np.outer(tv, tv)
        out.cov_white[i] = var_w * np.outer(nv, nv) + var_t * np.outer(tv, tv)
        out.score[i], out.cnr[i], out.s[i] = res.score[i], res.cnr[i], res.s[i]
        out.ok[i], out.reason[i], out.arms[i], out.bar[i] = True, "", 1, tv
    for i in np.where(passed.all(1))[0]:
        out.reason[i] = "both bars seen but the cross refused"
    return out
