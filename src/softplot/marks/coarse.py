"""Coarse search: a reduced overview of the scan and normalised cross-correlation peaks.

The overview is built block by block straight from ``Scan.data`` (``cv2.resize`` with
``INTER_AREA`` on strips of rows), so a huge or memory-mapped scan is never converted to float
as a whole. Overview pixel ``(i, j)`` averages the full-resolution pixels
``[f*i, f*i + f - 1] x [f*j, f*j + f - 1]``, hence (pixel system, centre convention)::

    x_full = f * x_overview + (f - 1) / 2
"""

from __future__ import annotations

import mmap
from dataclasses import dataclass

import cv2
import numpy as np

from softplot.marks.template import MarkShape, render
from softplot.runtime import thread_map

__all__ = ["overview", "overview_compact", "Overview", "ov_to_full", "full_to_ov", "ncc_map",
           "find_peaks", "Peaks", "local_std", "top_hat"]

#: bytes of native scan rows reduced at a time by :func:`overview`
_STRIP_BYTES = 1 << 21
#: float32 bytes of image rows correlated (and of map rows searched for peaks) at a time
_NCC_STRIP_BYTES = 1 << 18


def _rows_view(blk: np.ndarray) -> np.ndarray:
    """``blk`` itself when OpenCV can read it in place (rows of contiguous pixels, e.g. a
    column range of a C-ordered scan), else a contiguous copy."""
    if blk.strides[-1] == blk.itemsize and (blk.ndim == 2 or blk.strides[-2] ==
                                            blk.shape[-1] * blk.itemsize):
        return blk
    return np.ascontiguousarray(blk)


def _release_rows(data: np.ndarray, r0: int, r1: int) -> None:
    """Drop rows ``[r0, r1)`` of a read-only ``numpy.memmap`` scan from the resident set.

    Once the overview has read a strip, its file pages are not needed in this process; they
    stay in the system's page cache and are mapped back (minor faults) if touched again, as
    the fine stage does for the windows around the marks. The scan's pixels are then never
    resident all at once. Anything else (arrays in memory, writable or copy-on-write maps)
    is left alone.
    """
    mm = getattr(data, "_mmap", None)
    if (mm is None or getattr(data, "mode", None) != "r" or data.base is not mm
            or not data.flags.c_contiguous or data.ndim < 2):
        return
    try:
        base = int(data.offset) % mmap.ALLOCATIONGRANULARITY  # array start within the map
        ps = mmap.PAGESIZE
        a = -(-(base + r0 * data.strides[0]) // ps) * ps
        b = (base + r1 * data.strides[0]) // ps * ps
        if b > a:
            mm.madvise(mmap.MADV_DONTNEED, a, b - a)
    except (AttributeError, OSError, ValueError):
        pass


def ov_to_full(xy, factor: int) -> np.ndarray:
    """Overview pixel coordinates -> full-resolution pixel coordinates."""
    return np.asarray(xy, float) * factor + 0.5 * (factor - 1)


def full_to_ov(xy, factor: int) -> np.ndarray:
    """Full-resolution pixel coordinates -> overview pixel coordinates."""
    return (np.asarray(xy, float) - 0.5 * (factor - 1)) / factor


def overview(scan, factor: int, window: tuple[slice, slice] | None = None) -> np.ndarray:
    """Grey overview of a scan (or of a window of it), reduced by an integer factor.

    Parameters
    ----------
    scan : softplot.io.Scan
        The scan; only ``data``, ``channels``, ``full_scale``, ``min_is_white`` and ``grey``
        are used.
    factor : int
        Reduction factor (>= 1); rows and columns beyond a multiple of it are dropped.
    window : (slice, slice), optional
        Full-resolution window (rows, cols) with unit steps; default the whole scan.

    Returns
    -------
    ndarray
        float32 grey in [0, 1], shape ``(h // factor, w // factor)``, overview pixel system.
    """
    f = max(int(factor), 1)
    data = scan.data
    r0, r1, c0, c1 = 0, data.shape[0], 0, data.shape[1]
    if window is not None:
        r0, r1, _ = window[0].indices(data.shape[0])
        c0, c1, _ = window[1].indices(data.shape[1])
    H, W = (r1 - r0) // f, (c1 - c0) // f
    out = np.empty((max(H, 0), max(W, 0)), np.float32)
    if H <= 0 or W <= 0:
        return out
    ch = scan.channels
    native = data.dtype in (np.uint8, np.uint16) and ch in (1, 2, 3, 4)
    row_bytes = (c1 - c0) * (data.dtype.itemsize if native else 4) * max(ch, 1)
    step = max(1, _STRIP_BYTES // max(row_bytes * f, 1)) * f
    scale = np.float32(1.0 / scan.full_scale)
    for a in range(0, H * f, step):
        b = min(a + step, H * f)
        rows = slice(r0 + a, r0 + b)
        cols = slice(c0, c0 + W * f)
        if native:
            blk = data[rows, cols]
            if blk.ndim == 3:
                blk = blk[..., :3] if ch >= 3 else blk[..., 0]
            blk = _rows_view(blk)
            if f > 1:
                red = cv2.resize(blk, (W, (b - a) // f), interpolation=cv2.INTER_AREA)
            else:
                red = blk
            if red.ndim == 3:
                red = red.astype(np.float32)
                g = 0.299 * red[..., 0] + 0.587 * red[..., 1] + 0.114 * red[..., 2]
            else:
                g = red
            np.multiply(g, scale, out=out[a // f : b // f], dtype=np.float32)
            _release_rows(data, r0 + a, r0 + b)
        else:
            g = scan.grey((rows, cols))
            out[a // f : b // f] = cv2.resize(g, (W, (b - a) // f),
                                              interpolation=cv2.INTER_AREA) if f > 1 else g
            continue
        if scan.min_is_white:
            np.subtract(np.float32(1.0), out[a // f : b // f], out=out[a // f : b // f])
    if not native:
        return out
    np.minimum(out, np.float32(1.0), out=out)
    return out


class Overview:
    """A grey overview stored compactly: the reduced native grey levels (uint8 / uint16) when
    the scan is single-channel 8 or 16 bit (a quarter or half of the float32 bytes), else the
    float32 grey itself.

    Indexing (``ov[rows]``, ``ov[iy, ix]``, ...) returns float32 grey in [0, 1], exactly the
    values :func:`overview` gives, converted only for the pixels asked for; ``shape``,
    ``size`` and ``ndim`` are those of the overview (overview pixel system).
    """

    def __init__(self, q: np.ndarray, scale=None, invert: bool = False):
        self.q = q
        self.scale = None if scale is None else np.float32(scale)
        self.invert = bool(invert)
        self.shape = q.shape
        self.size = q.size
        self.ndim = q.ndim

    def grey(self, a: np.ndarray) -> np.ndarray:
        """Stored values -> float32 grey (the arithmetic of :func:`overview`)."""
        if self.scale is None:
            return a
        g = np.multiply(a, self.scale, dtype=np.float32)
        if self.invert:
            np.subtract(np.float32(1.0), g, out=g)
        np.minimum(g, np.float32(1.0), out=g)
        return g

    def __getitem__(self, key) -> np.ndarray:
        return self.grey(self.q[key])

    def __array__(self, dtype=None, copy=None):
        g = self.grey(self.q)
        return g if dtype is None else g.astype(dtype)


def overview_compact(scan, factor: int) -> Overview:
    """The whole scan's overview (as :func:`overview`) stored compactly (:class:`Overview`).

    For a single-channel 8/16-bit scan the reduced grey levels are kept in the scan's own
    dtype (at factor 1 the scan's pixels themselves, no copy); other scans fall back to the
    float32 overview.
    """
    f = max(int(factor), 1)
    data = scan.data
    if not (data.dtype in (np.uint8, np.uint16) and scan.channels in (1, 2)):
        return Overview(overview(scan, f))
    H, W = data.shape[0] // f, data.shape[1] // f
    scale = 1.0 / scan.full_scale
    if f == 1 and data.ndim == 2:
        return Overview(data, scale, scan.min_is_white)
    q = np.empty((max(H, 0), max(W, 0)), data.dtype)
    if H <= 0 or W <= 0:
        return Overview(q, scale, scan.min_is_white)
    row_bytes = data.shape[1] * data.dtype.itemsize * max(scan.channels, 1)
    step = max(1, _STRIP_BYTES // max(row_bytes * f, 1)) * f

    def strip(a):  # disjoint rows of q; OpenCV releases the GIL: strips run on the threads
        b = min(a + step, H * f)
        blk = data[a:b, : W * f]
        if blk.ndim == 3:
            blk = blk[..., 0]
        blk = _rows_view(blk)
        q[a // f : b // f] = (cv2.resize(blk, (W, (b - a) // f), interpolation=cv2.INTER_AREA)
                              if f > 1 else blk)
        _release_rows(data, a, b)

    thread_map(strip, range(0, H * f, step))
    return Overview(q, scale, scan.min_is_white)


def ncc_map(image: np.ndarray, shape: MarkShape, s: float, A=None,
            arm_half: float | None = None) -> tuple[np.ndarray, int]:
    """Normalised cross-correlation of ``image`` with a rendered mark template.

    Parameters
    ----------
    image : (H, W) float32 or Overview
        Grey image (overview or full-resolution window); read in strips of rows.
    shape : MarkShape
        Mark at the image's scale (px).
    s : float
        Template blur (px).
    A : (2, 2), optional
        Pixel -> mark-frame affine (rotation) of the template.
    arm_half : float, optional
        Shorten a cross's bars to this half-length (px) for tolerance to rotation.

    Returns
    -------
    R : (H - 2h, W - 2h) float32
        ``TM_CCOEFF_NORMED``; ``R[i, j]`` belongs to image pixel ``(x, y) = (j + h, i + h)``.
        Positive for a bright mark, negative for a dark one.
    h : int
        Template half-size (the offset above).
    """
    if arm_half is not None and shape.kind == "cross":
        shape = MarkShape("cross", length=min(shape.length, 2.0 * arm_half), width=shape.width)
    tpl = render(shape, s, A=A)
    h = tpl.shape[0] // 2
    th = tpl.shape[0]
    H, W = image.shape
    if H < th or W < tpl.shape[1]:
        return np.zeros((0, 0), np.float32), h
    # correlated in strips of rows: OpenCV's work buffers (float64 integral images, DFT
    # tiles) then stay a few megabytes whatever the image size
    R = np.empty((H - th + 1, W - tpl.shape[1] + 1), np.float32)
    step = max(64, _NCC_STRIP_BYTES // (4 * W))

    def strip(a):  # disjoint rows of R; OpenCV releases the GIL: strips run on the threads
        b = min(a + step, R.shape[0])
        R[a:b] = cv2.matchTemplate(np.ascontiguousarray(image[a : b + th - 1], np.float32),
                                   tpl, cv2.TM_CCOEFF_NORMED)
        np.nan_to_num(R[a:b], copy=False, nan=0.0, posinf=0.0, neginf=0.0)

    thread_map(strip, range(0, R.shape[0], step))
    return R, h


def top_hat(image, sign: int, radius: float) -> np.ndarray:
    """What of ``image`` (grey, (H, W) ndarray or :class:`Overview`; its pixel system) is
    narrower than a disc of ``radius`` px, of the polarity ``sign``: for +1 (bright marks)
    the image less its grey opening, for -1 (dark marks) less its grey closing, as float32
    of the image's shape. A cross's lines, narrower than the disc, stay whole; the scene's
    regions, edges and gradients wider than it go (0 there)."""
    g = image[:, :] if isinstance(image, Overview) else np.asarray(image, np.float32)
    r = max(int(np.ceil(radius)), 1)
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    op = cv2.MORPH_OPEN if sign > 0 else cv2.MORPH_CLOSE
    return np.subtract(g, cv2.morphologyEx(g, op, k), dtype=np.float32)


def local_std(image: np.ndarray, half: int) -> np.ndarray:
    """Standard deviation of ``image`` over ``(2*half+1)^2`` boxes (same shape, float32)."""
    k = (2 * half + 1, 2 * half + 1)
    m = cv2.boxFilter(image, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
    m2 = cv2.boxFilter(image * image, cv2.CV_32F, k, borderType=cv2.BORDER_REFLECT)
    return np.sqrt(np.maximum(m2 - m * m, 0.0))


@dataclass
class Peaks:
    """NCC peaks: positions (image pixel system), correlation values and signs."""

    xy: np.ndarray
    score: np.ndarray
    sign: np.ndarray

    def __len__(self) -> int:
        return len(self.score)

    def select(self, m) -> "Peaks":
        return Peaks(self.xy[m], self.score[m], self.sign[m])


def find_peaks(R: np.ndarray, offset: int, min_dist: float, threshold: float,
               max_peaks: int, sign: int = 0, contrast: np.ndarray | None = None,
               min_contrast: float = 0.0, image: np.ndarray | None = None,
               std_half: int = 2) -> Peaks:
    """Local extrema of an NCC map with sub-pixel (parabola) positions.

    Parameters
    ----------
    R : ndarray
        NCC map from :func:`ncc_map`.
    offset : int
        Its offset ``h`` (image pixel = map index + h).
    min_dist : float
        Minimum distance between peaks (px).
    threshold : float
        Minimum ``|R|``.
    max_peaks : int
        Keep the strongest ones.
    sign : int
        +1 bright marks only, -1 dark only, 0 both.
    contrast : ndarray, optional
        Local standard deviation of the image (same shape as the image): peaks where it is
        below ``min_contrast`` are dropped (flat areas give meaningless correlations).
    image, std_half : ndarray, int, optional
        Instead of ``contrast``: the image itself; the standard deviation over the
        ``(2*std_half+1)^2`` window at each peak is computed only there.
    """
    if R.size == 0:
        return Peaks(np.zeros((0, 2)), np.zeros(0), np.zeros(0, int))
    rad = max(int(min_dist), 1)
    k = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * rad + 1, 2 * rad + 1))
    signs = (1, -1) if sign == 0 else (sign,)
    found = _local_maxima(R, k, rad, threshold, signs)
    out = []
    for sg in signs:
        iy, ix = found[sg]
        if iy.size == 0:
            continue
        v = R[iy, ix] if sg > 0 else -R[iy, ix]
        if iy.size > 4 * max_peaks:
            keep = np.argpartition(-v, 4 * max_peaks)[: 4 * max_peaks]
            iy, ix, v = iy[keep], ix[keep], v[keep]
        S = R if sg > 0 else _Negated(R)
        # sub-pixel parabola through the 3x3 neighbourhood
        H, W = S.shape
        ym, yp = np.clip(iy - 1, 0, H - 1), np.clip(iy + 1, 0, H - 1)
        xm, xp = np.clip(ix - 1, 0, W - 1), np.clip(ix + 1, 0, W - 1)
        dx_den = S[iy, xm] - 2 * v + S[iy, xp]
        dy_den = S[ym, ix] - 2 * v + S[yp, ix]
        with np.errstate(divide="ignore", invalid="ignore"):
            dx = np.where(dx_den < 0, 0.5 * (S[iy, xm] - S[iy, xp]) / dx_den, 0.0)
            dy = np.where(dy_den < 0, 0.5 * (S[ym, ix] - S[yp, ix]) / dy_den, 0.0)
        dx = np.clip(np.nan_to_num(dx), -0.5, 0.5)
        dy = np.clip(np.nan_to_num(dy), -0.5, 0.5)
        xy = np.column_stack([ix + dx + offset, iy + dy + offset])
        if contrast is not None:
            cx = np.clip(np.round(xy[:, 0]).astype(int), 0, contrast.shape[1] - 1)
            cy = np.clip(np.round(xy[:, 1]).astype(int), 0, contrast.shape[0] - 1)
            ok = contrast[cy, cx] >= min_contrast
            xy, v = xy[ok], v[ok]
        elif image is not None and len(v):
            ar = np.arange(-std_half, std_half + 1)
            cx = np.round(xy[:, 0]).astype(int)[:, None] + ar
            cy = np.round(xy[:, 1]).astype(int)[:, None] + ar
            cx = np.clip(cx, 0, image.shape[1] - 1)
            cy = np.clip(cy, 0, image.shape[0] - 1)
            win = _gather_windows(image, cy, cx).reshape(len(v), -1)
            ok = win.std(1) >= min_contrast
            xy, v = xy[ok], v[ok]
        out.append(Peaks(xy, v.astype(float), np.full(len(v), sg)))
    if not out:
        return Peaks(np.zeros((0, 2)), np.zeros(0), np.zeros(0, int))
    p = Peaks(np.concatenate([o.xy for o in out]), np.concatenate([o.score for o in out]),
              np.concatenate([o.sign for o in out]))
    order = np.argsort(-p.score)[:max_peaks]
    return p.select(order)


def _gather_windows(image, cy: np.ndarray, cx: np.ndarray) -> np.ndarray:
    """``image[cy[:, :, None], cx[:, None, :]]`` (float32 grey) by flat indexing (faster)."""
    src = image.q if isinstance(image, Overview) else image
    if src.ndim == 2 and src.flags.c_contiguous:
        win = np.take(src.reshape(-1), cy[:, :, None] * src.shape[1] + cx[:, None, :])
    else:
        win = src[cy[:, :, None], cx[:, None, :]]
    return image.grey(win) if isinstance(image, Overview) else win


class _Negated:
    """``-R`` read by fancy indexing only (no negated copy of a whole map)."""

    def __init__(self, R: np.ndarray):
        self.R = R
        self.shape = R.shape

    def __getitem__(self, key):
        return -self.R[key]


def _local_maxima(R: np.ndarray, kernel: np.ndarray, rad: int, threshold: float,
                  signs) -> dict:
    """Row-major indices ``(iy, ix)`` of the local maxima of ``sign * R`` above ``threshold``
    (a pixel equal to the maximum of its ``kernel`` neighbourhood), per sign.

    The map is processed in strips of rows that overlap by ``rad`` (the kernel's half-size),
    so the result is that of the whole map while the work buffers stay small. ``-R``'s
    maxima are ``R``'s minima (an erosion), so no negated copy is made.
    """
    H, W = R.shape
    step = max(64, _NCC_STRIP_BYTES // (4 * max(W, 1)))
    parts: dict = {sg: ([], []) for sg in signs}
    for a in range(0, H, step):
        b = min(a + step, H)
        lo, hi = max(a - rad, 0), min(b + rad, H)
        blk = R[lo:hi]
        for sg in signs:
            if sg > 0:
                m = (blk >= cv2.dilate(blk, kernel)) & (blk > threshold)
            else:
                m = (blk <= cv2.erode(blk, kernel)) & (blk < -threshold)
            # flat indices (row-major, as np.nonzero, which is far slower on 2-D masks)
            iy, ix = np.divmod(np.flatnonzero(m[a - lo : b - lo]), W)
            parts[sg][0].append(iy + a)
            parts[sg][1].append(ix)
    return {sg: (np.concatenate(parts[sg][0]), np.concatenate(parts[sg][1]))
            for sg in signs}
