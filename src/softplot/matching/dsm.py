"""Dense surface (DSM) of an oriented pair and automatic contours.

:func:`dense_surface`:

1. the normalised pair (:mod:`softplot.matching.epipolar`) at a pixel chosen from the grid
   spacing (about 5 samples per cell, never finer than the scans; the scans are low-pass
   filtered first when the normalised pixel is coarser);
2. the disparity range from sparse SIFT matches of the normalised pair;
3. OpenCV semi-global matching (``StereoSGBM``, 3-way) left -> right and right -> left
   (flipped images); sub-pixel disparity (1/16 px); a pixel is kept when both agree within
   ``lr_px`` (left-right consistency) and its confidence is high enough;
4. sub-pixel disparity by dense least-squares matching (:func:`refine_disparity`: the
   window warped by the local plane of the disparities, so it follows slopes); texture test:
   ``sigma_n = sqrt(2) s_n / sqrt(sum g_x^2)`` over the matching window (``s_n`` the image
   noise, estimated robustly; ``g_x`` the horizontal gradient) - blank (textureless) areas
   have a large ``sigma_n`` and are dropped; the disparity's stated standard deviation
   ``sigma_d = sqrt(s0^2 kappa / sum g_x^2)`` from the window's own residuals ``s0`` (both
   images' noise and what the model misses) and their correlation between neighbouring
   pixels ``kappa`` (blur, resampling);
5. intersection in the normalised frame into object space, with the height precision
   propagated from ``sigma_d``;
6. gridding at ``gsd`` m: a plane fitted to the points of each cell (so the slope within a
   cell does not bias it) evaluated at the cell centre; cells with fewer than
   ``min_points`` points are no-data. The cell's precision: the points' height variance
   times the mean correlation of their errors (neighbouring matching windows share pixels:
   :func:`_mean_correlation`);
7. holes of 1-2 cells surrounded by valid cells that lie on a plane are interpolated
   (:func:`fill_small_holes`); larger holes (occlusions, blank areas) stay no-data.

Grid: object X east, Y north (m); row 0 is the northernmost row; ``x0``, ``y0`` are the
object X, Y of the centre of the top-left cell; rows run towards -Y.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from softplot.errors import SoftplotError

__all__ = ["DSM", "DsmOptions", "dense_surface", "write_geotiff", "contours"]

NODATA = -9999.0


@dataclass
class DsmOptions:
    """Parameters of :func:`dense_surface` (see the module docstring)."""

    samples_per_cell: float = 5.0
    block: int = 5
    lr_px: float = 1.0
    #: largest move of the refinement from the semi-global disparity, semi-global pixels
    max_move_px: float = 2.0
    #: no-data cells surrounded by valid ones within this many cells are interpolated
    #: (0: never)
    fill_radius: int = 2
    max_sigma_d: float = 0.35
    min_points: int = 3
    uniqueness: int = 5
    window: int = 9
    max_side: int = 2500
    min_corr: float = 0.6
    #: least share of a matching window off the marks
    min_window_share: float = 0.6
    #: semi-global matching runs at half the pixel when the images are wider than this
    sgbm_full_side: int = 1600


@dataclass
class DSM:
    """A gridded surface.

    Attributes
    ----------
    Z : ndarray (rows, cols) float32
        Height, object m; NaN where no data.
    sigma : ndarray (rows, cols) float32
        Height precision (standard deviation), m; NaN where no data.
    x0, y0 : float
        Object X, Y of the centre of the top-left cell.
    gsd : float
        Cell size, m.
    info : dict
        Figures of the run (pixels matched, valid share, ...).
    """

    Z: np.ndarray
    sigma: np.ndarray
    x0: float
    y0: float
    gsd: float
    info: dict

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Object X, Y (rows, cols) of every cell centre."""
        r, c = np.mgrid[0:self.Z.shape[0], 0:self.Z.shape[1]]
        return self.x0 + c * self.gsd, self.y0 - r * self.gsd

    def sidecar(self) -> dict:
        return {"x0": self.x0, "y0": self.y0, "gsd": self.gsd, "nodata": NODATA,
                "rows": int(self.Z.shape[0]), "cols": int(self.Z.shape[1]),
                "bands": ["height_m", "sigma_m"],
                "convention": "x0, y0: object X, Y of the centre of the top-left cell; "
                              "rows run towards -Y, columns towards +X",
                **self.info}


def _disparity_range(L8, R8, geo):
    """(min, max) disparity col_left - col_right from sparse SIFT matches, px."""
    from softplot.matching.ties import _mutual_ratio, _sift

    f = max(1.0, max(L8.shape) / 500.0)  # SIFT doubles its first octave: keep it small
    small = [cv2.resize(im, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
             if f > 1 else im for im in (L8, R8)]
    kl = _sift(small[0], (small[0] > 0).astype(np.uint8) * 255, 1500)
    kr = _sift(small[1], (small[1] > 0).astype(np.uint8) * 255, 1500)
    i1, i2 = _mutual_ratio(kl[1], kr[1], 0.8)
    if len(i1) < 10:
        raise SoftplotError("dense matching: the normalised images have too little in common "
                            f"({len(i1)} sparse matches)")
    pl, pr = kl[0][i1] * f, kr[0][i2] * f
    ok = np.abs(pl[:, 1] - pr[:, 1]) < 2.0 * f
    if ok.sum() < 10:
        raise SoftplotError("dense matching: the sparse matches do not lie on epipolar rows "
                            "(is the orientation right?)")
    d = pl[ok, 0] - pr[ok, 0]
    lo, hi = np.percentile(d, [1, 99])
    pad = max(16.0, 0.15 * (hi - lo))
    return float(lo - pad), float(hi + pad)


def _sgbm(L8, R8, dmin, dmax, block, uniqueness):
    num = int(np.ceil((dmax - dmin) / 16.0)) * 16
    m = cv2.StereoSGBM_create(minDisparity=int(np.floor(dmin)), numDisparities=max(16, num),
                              blockSize=block, P1=8 * block * block, P2=32 * block * block,
                              uniquenessRatio=uniqueness, speckleWindowSize=0,
                              disp12MaxDiff=-1, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    return m


def _noise_sigma(img: np.ndarray, valid: np.ndarray) -> float:
    """Robust image noise (Immerkaer's Laplacian estimator on valid pixels)."""
    k = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    lap = cv2.filter2D(img, cv2.CV_32F, k)
    v = np.abs(lap[valid])
    return float(np.sqrt(np.pi / 2) * np.median(v) / 6.0) if v.size else 1.0


class _Reduced:
    """A scan's ScanPhotoMap for the scan reduced ``f`` times (pixel centres:
    ``reduced = (scan + 0.5) / f - 0.5``)."""

    def __init__(self, m, f: float):
        from types import SimpleNamespace

        self.m, self.f = m, float(f)
        self.correction = m.correction
        self.frame = SimpleNamespace(pixel_mm=m.frame.pixel_mm * self.f)

    def pixel_to_photo(self, xy):
        return self.m.pixel_to_photo((np.asarray(xy, float) + 0.5) * self.f - 0.5)

    def photo_to_pixel(self, xy):
        return (self.m.photo_to_pixel(xy) + 0.5) / self.f - 0.5


def _grey(img: np.ndarray) -> np.ndarray:
    """One grey channel (uint8, uint16 or float32), the scan itself when it is one."""
    a = np.asarray(img)
    if a.ndim == 3:
        a = a[..., :3].mean(axis=2).astype(np.float32) if a.dtype.kind == "f" else \
            cv2.cvtColor(np.ascontiguousarray(a[..., :3]), cv2.COLOR_RGB2GRAY)
    if a.dtype not in (np.uint8, np.uint16, np.float32):
        a = a.astype(np.float32)
    return a


def _reduce(img: np.ndarray, f: float) -> np.ndarray:
    """The scan reduced ``f`` times (pixel area averaging); itself when ``f`` <= 1.05."""
    if f <= 1.05:
        return img
    h, w = img.shape[:2]
    return cv2.resize(img, (max(1, int(round(w / f))), max(1, int(round(h / f)))),
                      interpolation=cv2.INTER_AREA)


def _unit(img: np.ndarray) -> np.ndarray:
    """float32 grey in [0, 1] of a uint8, uint16 or float image."""
    if img.dtype.kind == "f":
        return img.astype(np.float32, copy=False)
    return img.astype(np.float32) * np.float32(1.0 / np.iinfo(img.dtype).max)


def _fill(img: np.ndarray, hole: np.ndarray, r: int = 7) -> np.ndarray:
    """``img`` with the pixels of ``hole`` replaced by the local mean of the others."""
    if not hole.any():
        return img
    keep = (~hole).astype(np.float32)
    k = (2 * r + 1, 2 * r + 1)
    num = cv2.blur(img.astype(np.float32) * keep, k)
    den = cv2.blur(keep, k)
    for _ in range(4):  # wide holes: widen the mean until it reaches them
        if (den[hole] > 1e-3).all():
            break
        k = (2 * k[0] + 1, 2 * k[1] + 1)
        num, den = cv2.blur(img.astype(np.float32) * keep, k), cv2.blur(keep, k)
    fill = num / np.maximum(den, 1e-6)
    out = img.copy()
    out[hole] = fill[hole].astype(img.dtype) if img.dtype.kind == "f" else \
        np.clip(np.rint(fill[hole]), 0, np.iinfo(img.dtype).max).astype(img.dtype)
    return out


def _stretch(imgs, valid) -> list:
    """uint8 images for the semi-global matching: one linear stretch (0.5 - 99.5 %)."""
    v = np.concatenate([im[ok][::7] for im, ok in zip(imgs, valid, strict=True)])
    lo, hi = (np.percentile(v, [0.5, 99.5]) if v.size else (0.0, 1.0))
    sc = 255.0 / max(float(hi - lo), 1e-6)
    return [np.clip((im - lo) * sc, 0, 255).astype(np.uint8) for im in imgs]


#: causes of an invalid pixel in ``dense_surface(..., diag=)``: the first test it fails
CAUSES = {0: "valid", 1: "outside the left image", 2: "format border (window reach)",
          3: "reseau cross / fiducial", 4: "near the image edge (SGM block)",
          5: "semi-global: left-right / uniqueness", 6: "sigma_d too large (texture)",
          7: "correlation too low", 8: "window share off marks", 9: "refinement moved > lr_px",
          10: "right pixel outside / on a mark", 11: "other"}


#: rows of the normalised images refined, checked and intersected at a time
STRIP_ROWS = 64


def dense_surface(model, maps, images, gsd: float, options: DsmOptions | None = None,
                  progress=None, diag: dict | None = None) -> DSM:
    """DSM of an oriented pair (see the module docstring).

    Parameters
    ----------
    model : StereoModel
        Oriented pair (object frame).
    maps : (ScanPhotoMap, ScanPhotoMap)
    images : (ndarray, ndarray)
        Scans (H, W) grey or (H, W, C), pixel system; never copied at full size as floats.
    gsd : float
        Grid spacing, object m.
    diag : dict, optional
        Filled with per-pixel figures of the left normalised image for diagnosis (costs
        memory): ``cause`` (uint8, the first test a pixel fails, :data:`CAUSES`), ``geo``.
    """
    from softplot.matching.epipolar import epipolar_geometry, resample_pair

    opt = options or DsmOptions()

    def say(stage):
        _trim()  # each stage starts without the freed heap of the one before
        if progress:
            progress(stage)

    if not (gsd > 0 and np.isfinite(gsd)):
        raise SoftplotError(f"--gsd must be a positive number of metres, got {gsd}")
    sizes = [(im.shape[1], im.shape[0]) for im in images]
    geo0 = epipolar_geometry(model, maps, sizes)
    H = float(np.mean([p.X0[2] for p in (model.left, model.right)]))
    scan_px = geo0.pixel_mm
    say("normalised pair")
    greys = [_grey(im) for im in images]
    # 1. the disparity range from a coarse normalised pair (about 800 px across)
    extent_mm = max(geo0.cols[0], geo0.rows) * scan_px
    fc = max(1.0, extent_mm / 800.0 / scan_px)
    red = [_reduce(g, fc) for g in greys]
    rmaps = [_Reduced(m, fc) for m in maps]
    geo_c, imgs_c, _ = resample_pair(model, rmaps, red, scan_px * fc, keep_maps=False)
    del red
    L8c, R8c = _stretch([_unit(im) for im in imgs_c], [im > 0 for im in imgs_c])
    dlo, dhi = _disparity_range(L8c, R8c, geo_c)
    # distance from the parallax: lam = B / (xl - xr), xl - xr in mm
    dx_mm = np.array([dlo, dhi]) * geo_c.pixel_mm - (geo_c.col0[0] - geo_c.col0[1]) * \
        geo_c.pixel_mm
    dist = geo_c.base * geo_c.cn / np.maximum(np.abs(dx_mm), 1e-9)
    ground_per_mm = float(np.min(dist)) / geo_c.cn  # object m per normalised mm (nearest)
    pix = max(scan_px, gsd / opt.samples_per_cell / ground_per_mm)
    # the refinement's pixel: at most max_side pixels across the normalised images
    pix = max(pix, extent_mm / opt.max_side)
    f = pix / scan_px
    # 2. the normalised pair at that pixel, from scans reduced to about it (pixel area
    # averaging: no aliasing, no full-size float copy of a scan); kept in the scans' type
    fr = max(1.0, f / 1.25) if f > 1.2 else 1.0
    red = [_reduce(g, fr) for g in greys]
    rmaps = [_Reduced(m, fr) for m in maps]
    geo, (L, R), _ = resample_pair(model, rmaps, red, pix, keep_maps=False, tile_rows=256)
    # the reseau crosses and fiducials are on the film, not on the ground; the unexposed
    # border outside the format neither: masked (filled for the matching, never valid)
    marks = [_mark_mask(r.shape, m, fr) for r, m in zip(red, maps, strict=True)]
    del red
    _, mk, _ = resample_pair(model, rmaps, marks, pix, keep_maps=False, tile_rows=256)
    del marks
    mk = [_Bits(m > 0) for m in mk]  # kept 8 pixels a byte
    # 3. semi-global matching at half the refinement's pixel (a quarter of the pixels, half
    # the disparities) when the images are large, both ways, left-right consistency
    say("semi-global matching")
    scale = geo_c.pixel_mm / geo.pixel_mm
    off_c = geo_c.col0[0] - geo_c.col0[1]
    off = geo.col0[0] - geo.col0[1]
    dmin = (dlo - off_c) * scale + off
    dmax = (dhi - off_c) * scale + off
    hs = 2 if max(L.shape) > opt.sgbm_full_side else 1
    small = [_fill_strips(im, m, hs) for im, m in zip((L, R), mk, strict=True)]
    Ls8, Rs8 = _stretch(small, [a > 0 for a in small])
    del small
    D_s, cons_s = _sgbm_lr(Ls8, Rs8, dmin / hs, dmax / hs, opt)
    del Ls8, Rs8
    if hs > 1:  # back to the refinement's pixels (pixel centres: full = hs (half + 0.5) - 0.5)
        cols_f = (np.arange(L.shape[1], dtype=np.float32) + 0.5) / hs - 0.5
        rows_f = (np.arange(L.shape[0], dtype=np.float32) + 0.5) / hs - 0.5
        cons = cv2.resize(cons_s.astype(np.uint8), (L.shape[1], L.shape[0]),
                          interpolation=cv2.INTER_NEAREST)
        # a pixel is consistent when its whole neighbourhood of coarse pixels is
        cons = _Bits(cv2.erode(cons, np.ones((3, 3), np.uint8)) > 0)
    else:
        cons = _Bits(cons_s)
    del cons_s
    # 4. sub-pixel refinement and confidence, strip by strip
    say("refinement")
    fmt = [_format_mask(geo, k, ph, m) > 0 for k, (ph, m) in
           enumerate(zip((model.left, model.right), maps, strict=True))]
    valid_l = (L > 0) & fmt[0]
    # the matched pixel itself must miss the marks (windows may reach over them: their
    # pixels do not count) and its window must stay inside the format
    win = np.ones((opt.window + 2, opt.window + 2), np.uint8)
    near = np.ones((5, 5), np.uint8)
    bad_l = cv2.dilate((~fmt[0]).astype(np.uint8), win) > 0
    if diag is not None:
        diag_fmt = bad_l.copy()
        diag_mk = cv2.dilate(mk[0].rows(0, L.shape[0]).view(np.uint8), near) > 0
        diag_ero = cv2.erode(valid_l.astype(np.uint8), np.ones((2 * opt.block + 1,) * 2)) == 0
    bad_l |= cv2.dilate(mk[0].rows(0, L.shape[0]).view(np.uint8), near) > 0
    bad_l |= cv2.erode(valid_l.astype(np.uint8), np.ones((2 * opt.block + 1,) * 2)) == 0
    bad_r = cv2.dilate((~fmt[1] | (R <= 0)).astype(np.uint8), win) > 0
    bad_r |= cv2.dilate(mk[1].rows(0, R.shape[0]).view(np.uint8), near) > 0
    del fmt
    # the full-size masks kept through the strips: 8 pixels a byte
    bad_l, bad_r = _Bits(bad_l), _Bits(bad_r)
    # image noise from a band of at most 1024 rows across the middle
    b0 = max(0, L.shape[0] // 2 - 512)
    band = slice(b0, b0 + 1024)
    s_n = _noise_sigma(_unit(L[band]) * np.float32(255.0),
                       cv2.erode(valid_l[band].astype(np.uint8), np.ones((5, 5))) > 0)
    del valid_l
    _trim()
    h = opt.window // 2 + 2
    hf = FILL_HALO
    Pz, Sz, n_ok, n_cons = [], [], 0, 0
    sig_med = []
    kap = []
    for r0 in range(0, L.shape[0], STRIP_ROWS):
        r1 = min(L.shape[0], r0 + STRIP_ROWS)
        a0, a1 = max(0, r0 - h), min(L.shape[0], r1 + h)
        f0, f1 = max(0, a0 - hf), min(L.shape[0], a1 + hf)
        mkl, mkr = mk[0].rows(f0, f1), mk[1].rows(f0, f1)
        Lf = _unit(_fill(L[f0:f1], mkl))[a0 - f0:a1 - f0] * np.float32(255.0)
        Rf = _unit(_fill(R[f0:f1], mkr))[a0 - f0:a1 - f0] * np.float32(255.0)
        mkl, mkr = mkl[a0 - f0:a1 - f0], mkr[a0 - f0:a1 - f0]
        if hs > 1:
            mxs, mys = np.meshgrid(cols_f, rows_f[a0:a1])
            D0 = cv2.remap(D_s, mxs, mys, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_REPLICATE) * np.float32(hs)
            del mxs, mys
        else:
            D0 = D_s[a0:a1]
        c_s = cons.rows(a0, a1)
        d0 = np.where(c_s, D0, 0.0).astype(np.float32)
        d, corr, energy, share, s02, kappa = refine_disparity(
            Lf, Rf, d0, c_s, opt.window, wl=(~mkl).astype(np.float32), wr=(~mkr).astype(np.float32),
            smooth=opt.window)
        del Lf, Rf, D0, mkl, mkr
        k0, k1 = r0 - a0, r1 - a0
        n_cons += int(np.count_nonzero(c_s[k0:k1]))
        d, corr, energy, d0 = d[k0:k1], corr[k0:k1], energy[k0:k1], d0[k0:k1]
        d_all = d
        # the texture test: the disparity's precision from the image noise alone (blank
        # areas have no gradients); the stated precision: from the window's own residuals
        sigma_n = np.sqrt(2.0) * s_n / np.sqrt(np.maximum(energy, 1e-12))
        sigma_d = np.sqrt(s02[k0:k1] * kappa / np.maximum(energy, 1e-12))
        kap.append(kappa)
        ok = (c_s[k0:k1] & (sigma_n <= opt.max_sigma_d) & (corr >= opt.min_corr)
              & (share[k0:k1] >= opt.min_window_share)
              & (np.abs(d - d0) <= opt.max_move_px * hs) & ~bad_l.rows(r0, r1))
        rr, cc = np.nonzero(ok)
        d = d[rr, cc]
        cr = np.rint(cc - d).astype(np.int64)
        inside = (cr >= 0) & (cr < R.shape[1])
        inside[inside] &= ~bad_r.rows(r0, r1)[rr[inside], cr[inside]]
        if diag is not None:
            cz = np.zeros((r1 - r0, L.shape[1]), np.uint8)
            tests = [(1, ~(L[r0:r1] > 0)), (2, diag_fmt[r0:r1]), (3, diag_mk[r0:r1]),
                     (4, diag_ero[r0:r1]), (5, ~c_s[k0:k1]),
                     (6, sigma_n > opt.max_sigma_d), (7, corr < opt.min_corr),
                     (8, share[k0:k1] < opt.min_window_share),
                     (9, np.abs(d_all - d0) > opt.max_move_px * hs)]
            for code, t in tests[::-1]:
                cz[t] = code
            cz[rr[~inside], cc[~inside]] = 10
            cz[(cz == 0) & ~ok] = 11
            diag.setdefault("cause", []).append(cz)
            diag.setdefault("d0", []).append(d0.copy())
            diag.setdefault("d", []).append(d_all.copy())
            diag.setdefault("sigma_d", []).append(sigma_d.astype(np.float32))
        rr, cc, d = rr[inside] + r0, cc[inside], d[inside]
        n_ok += len(rr)
        # intersection in the normalised frame
        xl = (cc - geo.col0[0]) * geo.pixel_mm
        xr = (cc - d - geo.col0[1]) * geo.pixel_mm
        yn = (geo.row0 - rr) * geo.pixel_mm
        P = geo.intersect(xl, xr, yn)
        lam = geo.base / (xl - xr)
        sd = sigma_d[rr - r0, cc]
        # dZ / d(disparity px) = lam^2 / B * pixel_mm * cn (the height part of the ray)
        sZ = lam**2 / geo.base * geo.pixel_mm * geo.cn * sd
        good = np.isfinite(P).all(axis=1) & (lam > 0)
        Pz.append(P[good].astype(np.float32))
        Sz.append(sZ[good].astype(np.float16))  # a precision: 3 digits are plenty
        sig_med.append(sd[good][::17].copy())  # a copy: not a view keeping all of sd
        _trim()  # the strip's temporaries: no heap left to fragment under the kept points
    n_left = int(np.count_nonzero(L))
    del L, R, D_s, cons, bad_l, bad_r, mk
    say("gridding")
    if diag is not None:
        diag["geo"] = geo
        diag["hs"] = hs
        for k in ("cause", "d0", "d", "sigma_d"):
            diag[k] = np.vstack(diag[k])
        diag["points"] = (np.vstack(Pz), np.concatenate(Sz))
    dsm = _grid(Pz, Sz, gsd, opt.min_points, window=opt.window)
    del Pz, Sz
    dsm = fill_small_holes(dsm, opt.fill_radius)
    sm = np.concatenate(sig_med) if sig_med else np.zeros(0)
    dsm.info.update({
        "pixels_matched": n_cons, "pixels_valid": n_ok, "pixels_left": n_left,
        "normalised_pixel_mm": geo.pixel_mm, "sgbm_pixel_mm": geo.pixel_mm * hs,
        "disparity_range_px": [float(dmin), float(dmax)],
        "noise_grey": s_n, "flying_height_m": H,
        "sigma_d_px_median": float(np.median(sm)) if sm.size else None,
        "residual_correlation_factor": float(np.median(kap)) if kap else None,
    })
    return dsm


def _trim() -> None:
    """Return the freed heap to the system (glibc ``malloc_trim``; a no-op elsewhere)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


class _Bits:
    """A boolean image kept 8 pixels a byte; rows unpacked on demand."""

    def __init__(self, a: np.ndarray):
        self.shape = a.shape
        self.p = np.packbits(a, axis=1)

    def rows(self, r0: int, r1: int) -> np.ndarray:
        """Rows r0:r1 as a bool array."""
        return np.unpackbits(self.p[r0:r1], axis=1, count=self.shape[1]).view(bool)


#: rows above and below a strip the filling of the marks looks at
FILL_HALO = 64


def _fill_strips(img, hole, hs: int = 1, rows: int = 256) -> np.ndarray:
    """:func:`_fill` (``hole``: a :class:`_Bits`), as float32 in [0, 1], reduced ``hs`` times
    (pixel area), strip by strip."""
    H, W = img.shape[:2]
    out = np.empty((-(-H // hs), -(-W // hs)), np.float32)
    for r0 in range(0, H, rows):  # rows is a multiple of hs: the reduction is exact
        r1 = min(H, r0 + rows)
        f0, f1 = max(0, r0 - FILL_HALO), min(H, r1 + FILL_HALO)
        a = _unit(_fill(img[f0:f1], hole.rows(f0, f1))[r0 - f0:r1 - f0])
        if hs > 1:
            a = cv2.resize(a, (-(-W // hs), -(-(r1 - r0) // hs)), interpolation=cv2.INTER_AREA)
        out[r0 // hs:r0 // hs + a.shape[0]] = a
    return out


def _sgbm_lr(L8, R8, dmin, dmax, opt):
    """Disparity ``col_left - col_right`` (float32, px) of every left pixel by semi-global
    matching both ways, and where both ways agree within ``opt.lr_px``."""
    block = opt.block
    m = _sgbm(L8, R8, dmin, dmax, block, opt.uniqueness)
    pad = int(max(0, np.ceil(dmax)) + block)
    # SGBM needs the right image at least as wide as the left; pad both to a common width
    W = max(L8.shape[1], R8.shape[1]) + pad
    Lp = np.zeros((L8.shape[0], W), np.uint8)
    Rp = np.zeros((L8.shape[0], W), np.uint8)
    Lp[:, :L8.shape[1]] = L8
    Rp[:, :R8.shape[1]] = R8
    mindisp = m.getMinDisparity()
    if mindisp < 0:  # shift the right image so all disparities are >= 0
        sh = -mindisp
        Rp = np.zeros((L8.shape[0], W + sh), np.uint8)
        Rp[:, sh:sh + R8.shape[1]] = R8
        Lp = np.pad(Lp, ((0, 0), (0, sh)))
        m.setMinDisparity(0)
        m.setNumDisparities(int(np.ceil((dmax - dmin) / 16.0)) * 16)
    else:
        sh = 0
    dl = m.compute(Lp, Rp).astype(np.float32)
    dl *= np.float32(1 / 16)
    # right -> left on flipped images: the same disparities (col_left - col_right)
    dr = m.compute(np.ascontiguousarray(Rp[:, ::-1]),
                   np.ascontiguousarray(Lp[:, ::-1])).astype(np.float32)
    dr *= np.float32(1 / 16)
    dr = dr[:, ::-1]
    lo = m.getMinDisparity()
    del Lp, Rp
    w = L8.shape[1]
    ok = np.empty((dl.shape[0], w), bool)
    col = np.arange(w, dtype=np.float32)[None, :]
    for r0 in range(0, dl.shape[0], 256):  # in bands of rows: no full-size temporaries
        d = dl[r0:r0 + 256, :w]
        cr = np.rint(col - d).astype(np.int32)
        inside = (cr >= 0) & (cr < dr.shape[1])
        np.clip(cr, 0, dr.shape[1] - 1, out=cr)
        back = np.take_along_axis(dr[r0:r0 + 256], cr, axis=1)
        ok[r0:r0 + 256] = (inside & (d >= lo) & (back >= lo) & (np.abs(back - d) <= opt.lr_px)
                           & (L8[r0:r0 + 256] > 0))
    del dr
    out = dl[:, :w] - np.float32(sh)
    return out, ok


def refine_disparity(L, R, d, valid, window: int = 9, iterations: int = 3, wl=None,
                     wr=None, smooth: int = 0):
    """Sub-pixel refinement of a disparity map by dense 1-D least-squares matching.

    For every pixel, Gauss-Newton on the shift that minimises the weighted sum over a
    ``window`` square of ``((L(x) - m_L) - (R(x - D(x) - s) - m_R))^2`` (weighted local
    means removed), where ``D`` is the warp: the local mean of the current disparities of
    the valid pixels over ``smooth`` x ``smooth`` pixels (the centre value of a plane fitted
    to them), so the window follows a slope of the surface - its right half is compressed
    or stretched as the ground tilts - and not the noise of single disparities; the pixel's
    disparity is then ``D + s``. With ``smooth`` <= 1 the warp is each pixel's own disparity.
    The right image is resampled bicubic. Weights: ``wl`` of the left pixels times ``wr``
    of the right pixels they fall on (0 on the marks: a window may reach over a mark, which
    then does not count).

    Returns the refined disparity (px), the correlation coefficient of each window after
    refinement, the weighted sum of squared gradients of the window ``E``, the share of the
    window that counts, the a posteriori variance ``s0^2`` of a grey-value difference in the
    window after the shift (2 parameters estimated: shift and mean) and the residuals'
    correlation factor ``kappa`` (:func:`_correlation_factor`, pooled over the valid pixels):
    the disparity's standard deviation is ``sqrt(s0^2 kappa / E)``.
    """
    L = L.astype(np.float32)
    R = R.astype(np.float32)
    d = d.astype(np.float32).copy()
    rows, cols = np.mgrid[0:L.shape[0], 0:L.shape[1]].astype(np.float32)
    k = (window, window)
    box = lambda a: cv2.boxFilter(a, -1, k, normalize=True)  # noqa: E731
    gR = cv2.Sobel(R, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    one = np.ones_like(L)
    wl = one if wl is None else wl.astype(np.float32)
    wr = one if wr is None else wr.astype(np.float32)

    def terms(d):
        mx = cols - d
        Rw = cv2.remap(R, mx, rows, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        g = cv2.remap(gR, mx, rows, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        w = wl * cv2.remap(wr, mx, rows, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        sw = np.maximum(box(w), 1e-6)
        Lc = L - box(w * L) / sw
        Rc = Rw - box(w * Rw) / sw
        gc = g - box(w * g) / sw
        return w, sw, Lc, Rc, gc

    vm = valid.astype(np.float32)
    sk = (smooth, smooth)

    def field(d):
        """the warp: the masked local mean of the disparities (a plane through a symmetric
        window has its centre value there), so the warp follows the slope, not the noise"""
        if smooth <= 1:
            return d
        num = cv2.boxFilter(d * vm, -1, sk, normalize=True)
        den = cv2.boxFilter(vm, -1, sk, normalize=True)
        return np.where(den > 0.2, num / np.maximum(den, 1e-6), d).astype(np.float32)

    for it in range(iterations + 1):
        D = field(d)
        w, sw, Lc, Rc, gc = terms(D)
        r0 = Lc - Rc
        num = box(w * r0 * gc)
        den = box(w * gc * gc)
        step = np.where(valid, -num / np.maximum(den, 1e-12), 0.0).astype(np.float32)
        d = np.where(valid, D + np.clip(step, -1.0, 1.0), d).astype(np.float32)
        del D
        if it < iterations:  # the temporaries go before the next warp is made
            del w, sw, Lc, Rc, gc, r0, num, den, step
    corr = box(w * Lc * Rc) / np.sqrt(np.maximum(box(w * Lc * Lc) * box(w * Rc * Rc), 1e-12))
    del Lc, Rc
    energy = den * np.float32(window * window)
    # a posteriori variance of a grey value difference in the window after the shift
    # (both images' noise and what the model misses), 2 parameters (shift, mean) estimated
    nw = np.maximum(sw * np.float32(window * window), np.float32(3.0))
    s02 = np.maximum(box(w * r0 * r0) - num * num / np.maximum(den, 1e-12), 0.0) / sw \
        * (nw / (nw - np.float32(2.0)))
    del nw, num, w
    r0 += gc * step
    kappa = _correlation_factor(r0, gc, valid)
    return d, corr, energy, sw, s02, kappa


def _correlation_factor(res, g, use, max_lag: int = 3) -> float:
    """Variance factor of a least-squares shift whose grey-value residuals ``res`` are
    correlated between neighbouring pixels (the optics' blur, the resampling): the shift's
    variance is ``s0^2 sum_pq g_p rho(p - q) g_q / (sum g^2)^2``, i.e. ``s0^2 / sum g^2``
    times ``kappa = sum_lag rho(lag) rho_g(lag)`` with ``rho`` the residuals' and ``rho_g``
    the gradients' correlation at that pixel lag, pooled over the pixels ``use``. Lags up to
    ``max_lag`` in both directions; insignificant correlations count as 0."""
    m = use.astype(bool)
    if m.sum() < 100:
        return 1.0
    r = np.where(m, res - res[m].mean(), 0.0).astype(np.float32)
    gg = np.where(m, g, 0.0).astype(np.float32)
    vr, vg = float(np.mean(r[m] ** 2)), float(np.mean(gg[m] ** 2))
    if not (vr > 0 and vg > 0):
        return 1.0
    h, w = r.shape
    k = 1.0
    for dy in range(0, max_lag + 1):
        for dx in range(-max_lag, max_lag + 1):
            if dy == 0 and dx <= 0:
                continue
            xa, xb = (slice(0, w - dx), slice(dx, w)) if dx >= 0 else (slice(-dx, w),
                                                                     slice(0, w + dx))
            both = m[:h - dy, xa] & m[dy:, xb]
            nb = int(both.sum())
            if nb < 100:
                continue
            rho = float(np.sum(r[:h - dy, xa] * r[dy:, xb])) / nb / vr
            if not abs(rho) > 2.0 / np.sqrt(nb):
                continue
            rho_g = float(np.sum(gg[:h - dy, xa] * gg[dy:, xb])) / nb / vg
            k += 2.0 * rho * rho_g
    return max(k, 1.0)


def _mark_mask(shape, m, f: float = 1.0) -> np.ndarray:
    """uint8 mask (1) of the reseau crosses / fiducials of a scan reduced ``f`` times."""
    from softplot.matching.ties import mark_pixels

    mask = np.zeros(shape[:2], np.uint8)
    mp, rad_mm = mark_pixels(m.correction)
    r = int(np.ceil(rad_mm / (m.frame.pixel_mm * f))) + 2
    for x, y in (mp + 0.5) / f - 0.5:
        cv2.circle(mask, (int(round(x)), int(round(y))), r, 1, -1)
    return mask


def _format_mask(geo, k: int, photo, m, margin_mm: float = 0.2) -> np.ndarray:
    """uint8 (rows, cols[k]) of normalised image k: 1 inside the photo format (shrunk by
    ``margin_mm`` of film), 0 outside (the unexposed border, or beyond the scan)."""
    fw, fh = m.correction.camera.format_mm
    a, b = 0.5 * fw - margin_mm, 0.5 * fh - margin_mm
    t = np.linspace(-1.0, 1.0, 65)
    ring = np.vstack([np.c_[a * t, 0 * t + b], np.c_[0 * t + a, -b * t],
                      np.c_[-a * t, 0 * t - b], np.c_[0 * t - a, b * t]])
    ph = m.pixel_to_photo(m.correction.to_pixel(ring, frm="film")[0])
    xn = geo.from_photo(k, ph, photo.M, photo.c, photo.x0, photo.y0)
    px = geo.to_pixel(k, xn)
    mask = np.zeros((geo.rows, geo.cols[k]), np.uint8)
    cv2.fillPoly(mask, [np.rint(px * 16).astype(np.int32)], 1, cv2.LINE_8, shift=4)
    return mask


def _u8(img):
    return np.clip(np.asarray(img, np.float32) * 255.0, 0, 255).astype(np.uint8)


def _grid(P, sZ, gsd, min_points, chunk: int = 1 << 16, band_cells: int = 1 << 17,
          window: int | None = None) -> DSM:
    """Plane-fit gridding of points P (N, 3) with height precision sZ (N,), each given
    whole or as a list of pieces (float32).

    Per cell, a plane ``z = a + b dx + c dy`` (dx, dy: offsets from the cell centre in cells)
    fitted to its points, twice: the second time without the points farther from the first
    plane than ``max(4 sZ, 3 x the robust spread)``. Sums accumulate chunk by chunk (the
    points are read, never copied whole), for a band of about ``band_cells`` cells (whole
    rows of the grid) at a time."""
    pieces = [(p, z) for p, z in zip(P, sZ, strict=True) if len(p)] if isinstance(P, list) \
        else [(P, sZ)]
    if not pieces:
        raise SoftplotError("dense matching found no valid surface point")
    N = sum(len(p) for p, _ in pieces)
    z_ref = float(np.median(np.concatenate([p[::97, 2] for p, _ in pieces])))
    x0 = np.floor(min(float(p[:, 0].min()) for p, _ in pieces) / gsd) * gsd + 0.5 * gsd
    y0 = np.ceil(max(float(p[:, 1].max()) for p, _ in pieces) / gsd) * gsd - 0.5 * gsd
    cols = int(np.floor((max(float(p[:, 0].max()) for p, _ in pieces) - x0) / gsd + 0.5)) + 1
    rows = int(np.floor((y0 - min(float(p[:, 1].min()) for p, _ in pieces)) / gsd + 0.5)) + 1
    n = rows * cols
    # chunks: (piece, slice in it, slice of the whole)
    chunks, o = [], 0
    for p, z in pieces:
        for i in range(0, len(p), chunk):
            j = min(len(p), i + chunk)
            chunks.append((p, z, slice(i, j), slice(o + i, o + j)))
        o += len(p)

    def cells(ch):
        p, _, sl, _ = ch
        X = p[sl, 0].astype(np.float64)
        Y = p[sl, 1].astype(np.float64)
        c = np.clip(np.rint((X - x0) / gsd).astype(np.int64), 0, cols - 1)
        r = np.clip(np.rint((y0 - Y) / gsd).astype(np.int64), 0, rows - 1)
        dx = ((X - (x0 + c * gsd)) / gsd).astype(np.float32)
        dy = ((Y - (y0 - r * gsd)) / gsd).astype(np.float32)
        return r * cols + c, dx, dy, p[sl, 2] - np.float32(z_ref)

    band_rows = max(1, band_cells // cols)
    keep = np.ones(N, bool)
    sol = np.empty((n, 3), np.float32)
    use = np.zeros(n, bool)
    sig = np.full(n, np.nan, np.float32)
    for rnd in range(2):
        # a cell needs enough points around its centre (no extrapolation of a plane
        # from a few points at its edge): the median count of the cells with points
        cnt = np.zeros(n, np.int32)
        for ch in chunks:
            cnt += np.bincount(cells(ch)[0][keep[ch[3]]], minlength=n).astype(np.int32)
        full = float(np.median(cnt[cnt > 0])) if (cnt > 0).any() else 0.0
        del cnt
        sol.fill(np.nan)
        for b0 in range(0, rows, band_rows):
            i0, i1 = b0 * cols, min(rows, b0 + band_rows) * cols
            nb = i1 - i0
            S = np.zeros((10, nb), np.float32)
            for ch in chunks:
                idx, dx, dy, Z = cells(ch)
                k = keep[ch[3]] & (idx >= i0) & (idx < i1)
                if not k.any():
                    continue
                idx, dx, dy, Z = idx[k] - i0, dx[k], dy[k], Z[k]
                S[0] += np.bincount(idx, minlength=nb)
                for j, v in enumerate((dx, dy, dx * dx, dx * dy, dy * dy, Z, Z * dx, Z * dy),
                                      1):
                    S[j] += np.bincount(idx, weights=v, minlength=nb)
                S[9] += np.bincount(idx, weights=ch[1][ch[2]][k].astype(np.float64) ** 2,
                                    minlength=nb)
            cb = S[0]
            with np.errstate(invalid="ignore", divide="ignore"):
                ub = ((cb >= max(min_points, 0.4 * full)) & (np.abs(S[1] / cb) <= 0.25)
                      & (np.abs(S[2] / cb) <= 0.25))
            use[i0:i1] = ub
            ub_all = np.flatnonzero(ub)
            for i in range(0, len(ub_all), chunk):
                ub = ub_all[i:i + chunk]
                ui = ub + i0
                c1, sx, sy = (S[j, ub].astype(np.float64) for j in (0, 1, 2))
                M = np.empty((len(ub), 3, 3))
                M[:, 0] = np.stack([c1, sx, sy], -1)
                M[:, 1] = np.stack([sx, S[3, ub], S[4, ub]], -1)
                M[:, 2] = np.stack([sy, S[4, ub], S[5, ub]], -1)
                bz = np.stack([S[6, ub], S[7, ub], S[8, ub]], -1).astype(np.float64)
                det = np.linalg.det(M)
                good = np.abs(det) > 1e-6 * np.maximum(c1, 1) ** 3
                sol[ui[good]] = np.linalg.solve(M[good], bz[good][..., None])[..., 0]
                # cells with too little spread for a plane: their mean
                sol[ui[~good], 0] = bz[~good, 0] / c1[~good]
                sol[ui[~good], 1:] = 0.0
            if rnd == 1:
                with np.errstate(invalid="ignore", divide="ignore"):
                    sig[i0:i1] = np.sqrt(S[9] / np.maximum(S[0], 1)
                                         * _mean_correlation(S[0], window))
            del S
        if rnd == 1:
            break
        # the robust spread of the residuals (a sample), then the points to keep
        res_s = []
        for ch in chunks:
            idx, dx, dy, Z = cells(ch)
            res_s.append(np.abs(Z - (sol[idx, 0] + sol[idx, 1] * dx + sol[idx, 2] * dy))[::7]
                         .copy())
        spread = 3.0 * 1.4826 * float(np.nanmedian(np.concatenate(res_s)))
        del res_s
        for ch in chunks:
            idx, dx, dy, Z = cells(ch)
            res = np.abs(Z - (sol[idx, 0] + sol[idx, 1] * dx + sol[idx, 2] * dy))
            keep[ch[3]] = res <= np.maximum(4.0 * ch[1][ch[2]].astype(np.float32), spread)
    Zc = sol[:, 0]
    valid = np.isfinite(Zc) & use
    Zg = np.where(valid, Zc + np.float32(z_ref), np.nan).reshape(rows, cols).astype(np.float32)
    Sg = np.where(valid, sig, np.nan).reshape(rows, cols).astype(np.float32)
    return DSM(Zg, Sg, float(x0), float(y0), float(gsd),
               {"cells_valid": int(valid.sum()), "cells": int(n)})


def fill_small_holes(dsm: DSM, radius: int = 2, max_misfit: float = 3.0) -> DSM:
    """The DSM with its small holes interpolated (``radius`` 0: unchanged).

    A no-data cell is filled when valid cells lie on both sides of it along both grid axes
    within ``radius`` cells and more than half of the ``(2 radius + 1)^2 - 1`` cells around it
    are valid: a hole at most about ``radius`` cells across; never the edge of a larger
    hole, an occlusion or a blank area (at most half of the cells around it are valid
    there), never beyond the surface's edge. Its
    height: the plane fitted to those cells (weights ``1 / distance^2``) at its centre; it is
    left empty when the cells do not lie on a plane within ``max_misfit`` times their own
    precision (a step such as a wall). Its precision: the larger of ``sqrt(mean sigma^2)``
    of the cells around it and ``s_fit``, the plane's residual RMS (their noise and the
    surface's bending over the hole). The number of filled cells is ``info["cells_interpolated"]``.
    """
    if radius <= 0:
        dsm.info["cells_interpolated"] = 0
        return dsm
    Z, S = dsm.Z, dsm.sigma
    V = np.isfinite(Z)
    if not V.any():
        dsm.info["cells_interpolated"] = 0
        return dsm
    h, w = Z.shape
    offs = [(dy, dx) for dy in range(-radius, radius + 1) for dx in range(-radius, radius + 1)
            if (dy, dx) != (0, 0)]

    def shifted(a, dy, dx, fill):
        """a[r + dy, c + dx] for every cell (``fill`` beyond the grid)."""
        out = np.full_like(a, fill)
        out[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)] = \
            a[max(0, dy):h - max(0, -dy), max(0, dx):w - max(0, -dx)]
        return out

    # candidates: valid cells on both sides along both axes (rows: dy, columns: dx), more
    # than half of the cells around valid
    count = np.zeros(Z.shape, np.uint8)
    sides = np.zeros((4,) + Z.shape, bool)
    for dy, dx in offs:
        v = shifted(V, dy, dx, False)
        count += v
        for j, on in enumerate((dx < 0, dx > 0, dy < 0, dy > 0)):
            if on:
                sides[j] |= v
    cand = ~V & sides.all(axis=0) & (count > len(offs) // 2)
    del count, sides
    if not cand.any():
        dsm.info["cells_interpolated"] = 0
        return dsm
    rr, cc = np.nonzero(cand)
    z_ref = float(np.nanmedian(Z))
    # weighted sums (weights 1 / distance^2) over the cells around each candidate
    names = ("w", "x", "y", "xx", "xy", "yy", "z", "zx", "zy", "zz", "s2", "n")
    sums = {k: np.zeros(len(rr)) for k in names}
    for dy, dx in offs:
        r2, c2 = rr + dy, cc + dx
        inside = (r2 >= 0) & (r2 < h) & (c2 >= 0) & (c2 < w)
        r2, c2 = np.clip(r2, 0, h - 1), np.clip(c2, 0, w - 1)
        v = inside & V[r2, c2]
        z = np.where(v, Z[r2, c2].astype(np.float64) - z_ref, 0.0)
        wt = v / float(dx * dx + dy * dy)
        for k, t in (("w", 1.0), ("x", dx), ("y", dy), ("xx", dx * dx), ("xy", dx * dy),
                     ("yy", dy * dy)):
            sums[k] += wt * t
        sums["z"] += wt * z
        sums["zx"] += wt * z * dx
        sums["zy"] += wt * z * dy
        sums["zz"] += wt * z * z
        sums["s2"] += wt * np.where(v, S[r2, c2].astype(np.float64) ** 2, 0.0)
        sums["n"] += v
    M = np.stack([np.stack([sums["w"], sums["x"], sums["y"]], -1),
                  np.stack([sums["x"], sums["xx"], sums["xy"]], -1),
                  np.stack([sums["y"], sums["xy"], sums["yy"]], -1)], 1)
    b = np.stack([sums["z"], sums["zx"], sums["zy"]], -1)
    good = np.abs(np.linalg.det(M)) > 1e-9
    sol = np.full(b.shape, np.nan)
    sol[good] = np.linalg.solve(M[good], b[good][..., None])[..., 0]
    # weighted residual RMS of the plane (3 parameters)
    ssr = sums["zz"] - np.einsum("ni,ni->n", sol, b)
    n = sums["n"]
    s_fit = np.sqrt(np.maximum(ssr, 0.0) / sums["w"] * n / np.maximum(n - 3.0, 1.0))
    s_nb = np.sqrt(sums["s2"] / sums["w"])
    ok = good & np.isfinite(sol[:, 0]) & (s_fit <= max_misfit * s_nb)
    Zo, So = Z.copy(), S.copy()
    Zo[rr[ok], cc[ok]] = (sol[ok, 0] + z_ref).astype(np.float32)
    So[rr[ok], cc[ok]] = np.maximum(s_nb[ok], s_fit[ok]).astype(np.float32)
    info = dict(dsm.info)
    info["cells_interpolated"] = int(ok.sum())
    info["cells_valid"] = int(np.isfinite(Zo).sum())
    return DSM(Zo, So, dsm.x0, dsm.y0, dsm.gsd, info)


def _mean_correlation(n, window: int | None) -> np.ndarray:
    """Mean correlation of the height errors of ``n`` points of a cell (array), as a factor
    of their single-point variance: the variance of their mean.

    The points of a cell are neighbouring pixels, about ``s = sqrt(n)`` a side; the
    disparities of two pixels ``(i, j)`` apart come from matching windows of ``window``
    pixels that overlap by ``(1 - |i|/window)+ (1 - |j|/window)+`` of their pixels, and
    their errors are correlated by as much. The mean over all pairs of a square of ``s`` by
    ``s`` pixels is ``m(s)^2`` with ``m(s) = sum_k (s - |k|) (1 - |k|/window)+ / s^2``. With
    no ``window``: 1 (the single-point variance)."""
    n = np.asarray(n, np.float64)
    if window is None:
        return np.ones_like(n)
    s = np.maximum(np.rint(np.sqrt(np.maximum(n, 1.0))), 1.0)
    smax = int(s.max()) if s.size else 1
    table = np.ones(smax + 1)
    for si in range(1, smax + 1):
        k = np.arange(-(si - 1), si)
        table[si] = float(np.sum((si - np.abs(k)) * np.clip(1 - np.abs(k) / window, 0, None))
                          ) / si**2
    return table[s.astype(np.int64)] ** 2


def write_geotiff(path, dsm: DSM, overwrite: bool = False) -> tuple[Path, Path]:
    """Write the DSM as a 2-band float32 GeoTIFF (height, precision) and ``<stem>.json``.

    Tags: ModelPixelScale (gsd, gsd, 0), ModelTiepoint (raster corner (0, 0) -> object X, Y
    of the top-left corner of the top-left cell), GeoKeyDirectory (projected model, pixel is
    area, user-defined coordinate system), GDAL_NODATA.
    """
    import tifffile

    from softplot.matching.ties import check_outputs

    p = Path(path)
    side = p.with_suffix(".json")
    if p.suffix.lower() not in (".tif", ".tiff"):
        raise SoftplotError(f"{p}: the DSM is a GeoTIFF: use a .tif or .tiff name")
    check_outputs([p, side], overwrite)
    bands = np.stack([np.nan_to_num(dsm.Z, nan=NODATA), np.nan_to_num(dsm.sigma, nan=NODATA)]
                     ).astype(np.float32)
    g = dsm.gsd
    geokeys = (1, 1, 0, 4,
               1024, 0, 1, 1,  # GTModelType: projected
               1025, 0, 1, 1,  # GTRasterType: pixel is area
               3072, 0, 1, 32767,  # ProjectedCSType: user-defined
               3076, 0, 1, 9001)  # ProjLinearUnits: metre
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.part")
    tifffile.imwrite(
        tmp, bands, photometric="minisblack", planarconfig="separate", metadata=None,
        extratags=[
            (33550, "d", 3, (g, g, 0.0), True),
            (33922, "d", 6, (0.0, 0.0, 0.0, dsm.x0 - 0.5 * g, dsm.y0 + 0.5 * g, 0.0), True),
            (34735, "H", len(geokeys), geokeys, True),
            (42113, "s", 0, f"{NODATA:g}", True),
        ])
    tmp.replace(p)
    side.write_text(json.dumps(dsm.sidecar(), indent=1) + "\n", encoding="utf-8")
    return p, side


def read_geotiff(path) -> DSM:
    """Read a DSM written by :func:`write_geotiff` (and its ``.json`` sidecar)."""
    import tifffile

    p = Path(path)
    with tifffile.TiffFile(p) as tf:
        page = tf.pages[0]
        a = page.asarray()
        scale = page.tags[33550].value
        tie = page.tags[33922].value
        nod = float(page.tags[42113].value)
    a = np.where(a == nod, np.nan, a).astype(np.float32)
    g = float(scale[0])
    info = json.loads(p.with_suffix(".json").read_text()) if p.with_suffix(".json").exists() \
        else {}
    return DSM(a[0], a[1], float(tie[3]) + 0.5 * g, float(tie[4]) - 0.5 * g, g, info)


def contours(dsm: DSM, interval: float, code: str = "CONTOUR"):
    """Contour lines of the DSM at multiples of ``interval`` (object m): Features.

    Marching squares (scikit-image) on the grid; no-data cells break the lines (nothing is
    drawn across them). Vertices are object X, Y at the contour height Z.
    """
    from skimage.measure import find_contours

    from softplot.export.features import Feature

    if not (interval > 0 and np.isfinite(interval)):
        raise SoftplotError(f"--contours must be a positive interval in metres, got {interval}")
    Z = dsm.Z
    valid = np.isfinite(Z)
    if not valid.any():
        return []
    lo, hi = np.nanmin(Z), np.nanmax(Z)
    levels = np.arange(np.ceil(lo / interval) * interval, hi, interval)
    if len(levels) > 10000:
        raise SoftplotError(f"--contours {interval}: {len(levels)} levels; use a larger interval")
    filled = np.where(valid, Z, np.nanmin(Z) - 1.0)
    feats = []
    for h in levels:
        for line in find_contours(filled, float(h), mask=valid):
            if len(line) < 2:
                continue
            X = dsm.x0 + line[:, 1] * dsm.gsd
            Y = dsm.y0 - line[:, 0] * dsm.gsd
            feats.append(Feature(code, "contour", np.c_[X, Y, np.full(len(X), float(h))],
                                 {"height": float(h), "interval": float(interval),
                                  "source": "dsm"}))
    return feats
