"""Dense surface (DSM) of an oriented pair and automatic contours.

:func:`dense_surface`:

1. the normalised pair (:mod:`softplot.matching.epipolar`) at a pixel chosen from the grid
   spacing (about 5 samples per cell, never finer than the scans; the scans are low-pass
   filtered first when the normalised pixel is coarser);
2. the disparity range from sparse SIFT matches of the normalised pair;
3. OpenCV semi-global matching (``StereoSGBM``, 3-way) left -> right and right -> left
   (flipped images); sub-pixel disparity (1/16 px); a pixel is kept when both agree within
   ``lr_px`` (left-right consistency) and its confidence is high enough;
4. confidence: the disparity's standard deviation ``sigma_d = sqrt(2) s_n / sqrt(sum g_x^2)``
   over the matching window (``s_n`` the image noise, estimated robustly; ``g_x`` the
   horizontal gradient) - blank (textureless) areas have a large ``sigma_d`` and are dropped;
5. intersection in the normalised frame into object space, with the height precision
   propagated from ``sigma_d``;
6. gridding at ``gsd`` m: a plane fitted to the points of each cell (so the slope within a
   cell does not bias it) evaluated at the cell centre; cells with fewer than
   ``min_points`` points are no-data. Nothing is interpolated into empty cells.

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
    max_sigma_d: float = 0.35
    min_points: int = 3
    uniqueness: int = 5
    window: int = 9
    max_side: int = 2500
    min_corr: float = 0.7


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

    f = max(1.0, max(L8.shape) / 1200.0)
    small = [cv2.resize(im, None, fx=1 / f, fy=1 / f, interpolation=cv2.INTER_AREA)
             if f > 1 else im for im in (L8, R8)]
    kl = _sift(small[0], (small[0] > 0).astype(np.uint8) * 255, 4000)
    kr = _sift(small[1], (small[1] > 0).astype(np.uint8) * 255, 4000)
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


def dense_surface(model, maps, images, gsd: float, options: DsmOptions | None = None,
                  progress=None) -> DSM:
    """DSM of an oriented pair (see the module docstring).

    Parameters
    ----------
    model : StereoModel
        Oriented pair (object frame).
    maps : (ScanPhotoMap, ScanPhotoMap)
    images : (ndarray, ndarray)
        Scans (H, W) grey, pixel system.
    gsd : float
        Grid spacing, object m.
    """
    from softplot.matching.epipolar import epipolar_geometry, resample_pair

    opt = options or DsmOptions()
    say = progress or (lambda s: None)
    if not (gsd > 0 and np.isfinite(gsd)):
        raise SoftplotError(f"--gsd must be a positive number of metres, got {gsd}")
    sizes = [(im.shape[1], im.shape[0]) for im in images]
    geo0 = epipolar_geometry(model, maps, sizes)
    H = float(np.mean([p.X0[2] for p in (model.left, model.right)]))
    # ground size of a scan pixel at the scene (approximate, from the photo scale)
    scan_px = geo0.pixel_mm
    # mean object distance: from the base and the sparse parallax after resampling; first
    # guess from the height of the centres above the lowest object plane is not known, so the
    # normalised pixel follows from one coarse pass
    say("normalised pair")
    greys = [np.asarray(im, np.float32) if im.dtype.kind == "f" else
             im.astype(np.float32) / float(np.iinfo(im.dtype).max) for im in images]
    greys = [g[..., :3].mean(axis=2) if g.ndim == 3 else g for g in greys]
    geo_c, imgs_c, _ = resample_pair(model, maps, greys, scan_px * 4, keep_maps=False)
    L8c, R8c = (_u8(im) for im in imgs_c)
    dlo, dhi = _disparity_range(L8c, R8c, geo_c)
    # distance from the parallax: lam = B / (xl - xr), xl - xr in mm
    dx_mm = np.array([dlo, dhi]) * geo_c.pixel_mm - (geo_c.col0[0] - geo_c.col0[1]) * \
        geo_c.pixel_mm
    dist = geo_c.base * geo_c.cn / np.maximum(np.abs(dx_mm), 1e-9)
    ground_per_mm = float(np.min(dist)) / geo_c.cn  # object m per normalised mm (nearest)
    pix = max(scan_px, gsd / opt.samples_per_cell / ground_per_mm)
    # semi-global matching cost grows with pixels x disparities: at most max_side pixels
    # across the normalised images (fewer samples per cell on huge scans)
    extent_mm = max(geo_c.cols[0], geo_c.rows) * geo_c.pixel_mm
    pix = max(pix, extent_mm / opt.max_side)
    f = pix / scan_px
    if f > 1.2:
        greys = [cv2.GaussianBlur(g, (0, 0), 0.5 * f) for g in greys]
    geo, imgs, _ = resample_pair(model, maps, greys, pix, keep_maps=False)
    # the reseau crosses and fiducials are on the film, not on the ground: mask them out
    # (painted over for the matching, never valid)
    marks = [_mark_mask(g.shape, m) for g, m in zip(greys, maps, strict=True)]
    _, mimgs, _ = resample_pair(model, maps, marks, pix, keep_maps=False)
    L, R = imgs
    L8, R8 = _u8(L), _u8(R)
    mL, mR = ((mi > 0).astype(np.uint8) for mi in mimgs)
    if mL.any():
        L8 = cv2.inpaint(L8, mL, 3, cv2.INPAINT_TELEA)
        L = L8.astype(np.float32) / 255.0 * (mL > 0) + L * (mL == 0)
    if mR.any():
        R8 = cv2.inpaint(R8, mR, 3, cv2.INPAINT_TELEA)
        R = R8.astype(np.float32) / 255.0 * (mR > 0) + R * (mR == 0)
    # disparity range in this resolution (col_left - col_right)
    scale = geo_c.pixel_mm / geo.pixel_mm
    off_c = geo_c.col0[0] - geo_c.col0[1]
    off = geo.col0[0] - geo.col0[1]
    dmin = (dlo - off_c) * scale + off
    dmax = (dhi - off_c) * scale + off
    say("semi-global matching")
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
    dl = m.compute(Lp, Rp).astype(np.float32) / 16.0
    # right -> left on flipped images: the same disparities (col_left - col_right)
    dr = m.compute(np.ascontiguousarray(Rp[:, ::-1]),
                   np.ascontiguousarray(Lp[:, ::-1])).astype(np.float32)[:, ::-1] / 16.0
    invalid_l = dl < m.getMinDisparity()
    invalid_r = dr < m.getMinDisparity()
    rows, cols = np.mgrid[0:dl.shape[0], 0:dl.shape[1]]
    cr = np.rint(cols - dl).astype(np.int64)
    inside = (cr >= 0) & (cr < dr.shape[1])
    back = np.where(inside, dr[rows, np.clip(cr, 0, dr.shape[1] - 1)], np.nan)
    consistent = inside & ~invalid_l & (np.abs(back - dl) <= opt.lr_px)
    consistent &= ~invalid_r[rows, np.clip(cr, 0, dr.shape[1] - 1)]
    # sub-pixel refinement (dense least-squares matching along the rows) and confidence:
    # the disparity's standard deviation from the noise and the texture of the window
    say("refinement")
    valid_img = Lp > 0
    Lf = np.zeros(Lp.shape, np.float32)
    Rf = np.zeros(Rp.shape, np.float32)
    Lf[:, :L.shape[1]] = L * 255.0
    Rf[:, sh:sh + R.shape[1]] = R * 255.0
    s_n = _noise_sigma(Lf, cv2.erode(valid_img.astype(np.uint8), np.ones((5, 5))) > 0)
    d0 = np.where(consistent, dl, 0.0).astype(np.float32)
    dl, corr, energy = refine_disparity(Lf, Rf, d0, consistent, opt.window)
    sigma_d = np.sqrt(2.0) * s_n / np.sqrt(np.maximum(energy, 1e-12))
    ok = (consistent & (sigma_d <= opt.max_sigma_d) & valid_img & (corr >= opt.min_corr)
          & (np.abs(dl - d0) <= opt.lr_px))
    ok &= cv2.erode(valid_img.astype(np.uint8), np.ones((2 * block + 1, 2 * block + 1))) > 0
    # no window may touch a mark, in the left image or at the matched place in the right
    win = np.ones((opt.window + 2, opt.window + 2), np.uint8)
    near_l = np.zeros(Lp.shape, bool)
    near_l[:, :mL.shape[1]] = cv2.dilate(mL, win) > 0
    near_r = np.zeros(Rp.shape, bool)
    near_r[:, sh:sh + mR.shape[1]] = cv2.dilate(mR, win) > 0
    # nor may it reach outside the format (the unexposed film border is not ground)
    fmt = [_format_mask(geo, k, ph, m) for k, (ph, m) in
           enumerate(zip((model.left, model.right), maps, strict=True))]
    near_l[:, :fmt[0].shape[1]] |= cv2.dilate(1 - fmt[0], win) > 0
    near_l[:, fmt[0].shape[1]:] = True
    near_r[:, :sh] = True
    near_r[:, sh:sh + fmt[1].shape[1]] |= cv2.dilate(1 - fmt[1], win) > 0
    near_r[:, sh + fmt[1].shape[1]:] = True
    rr0, cc0 = np.mgrid[0:ok.shape[0], 0:ok.shape[1]]
    cr0 = np.clip(np.rint(cc0 - dl).astype(np.int64), 0, near_r.shape[1] - 1)
    ok &= ~near_l & ~near_r[rr0, cr0]
    ok[:, L8.shape[1]:] = False
    # intersection: disparity in the padded frame -> normalised x of both images
    say("intersection")
    rr, cc = np.nonzero(ok)
    d = dl[rr, cc]
    col_r = cc - d - sh
    xl = (cc - geo.col0[0]) * geo.pixel_mm
    xr = (col_r - geo.col0[1]) * geo.pixel_mm
    yn = (geo.row0 - rr) * geo.pixel_mm
    P = geo.intersect(xl, xr, yn)
    lam = geo.base / (xl - xr)
    ray = np.sqrt(xl**2 + yn**2 + geo.cn**2)
    # dP/d(disparity px) = lam^2 / B * pixel_mm * |ray| ; height part ~ the ray's Z share
    sZ = lam**2 / geo.base * geo.pixel_mm * ray * sigma_d[rr, cc] * (geo.cn / ray)
    good = np.isfinite(P).all(axis=1) & (lam > 0)
    P, sZ = P[good], sZ[good]
    say("gridding")
    dsm = _grid(P, sZ, gsd, opt.min_points)
    dsm.info.update({
        "pixels_matched": int(consistent.sum()), "pixels_valid": int(ok.sum()),
        "pixels_left": int((Lp[:, :L8.shape[1]] > 0).sum()),
        "normalised_pixel_mm": geo.pixel_mm, "disparity_range_px": [float(dmin), float(dmax)],
        "noise_grey": s_n, "flying_height_m": H,
        "sigma_d_px_median": float(np.median(sigma_d[ok])) if ok.any() else None,
    })
    return dsm


def refine_disparity(L, R, d, valid, window: int = 9, iterations: int = 3):
    """Sub-pixel refinement of a disparity map by dense 1-D least-squares matching.

    For every pixel, Gauss-Newton on the shift that minimises the sum over a ``window``
    square of ``(L(x) - m_L) - (R(x - d) - m_R)`` (local means removed); the right image is
    warped by each pixel's own disparity (bicubic). Returns the refined disparity, the
    correlation coefficient of each window after refinement and the sum of squared
    gradients of the window (for the precision).
    """
    L = L.astype(np.float32)
    R = R.astype(np.float32)
    d = d.astype(np.float32).copy()
    rows, cols = np.mgrid[0:L.shape[0], 0:L.shape[1]].astype(np.float32)
    k = (window, window)
    box = lambda a: cv2.boxFilter(a, -1, k, normalize=True)  # noqa: E731
    Lc = L - box(L)
    gR = cv2.Sobel(R, cv2.CV_32F, 1, 0, ksize=3) / 8.0
    for _ in range(iterations):
        mx = cols - d
        Rw = cv2.remap(R, mx, rows, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        g = cv2.remap(gR, mx, rows, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        Rc = Rw - box(Rw)
        gc = g - box(g)
        r = Lc - Rc
        num = box(r * gc)
        den = box(gc * gc)
        step = np.where(valid, -num / np.maximum(den, 1e-12), 0.0).astype(np.float32)
        d += np.clip(step, -1.0, 1.0)
    mx = cols - d
    Rw = cv2.remap(R, mx, rows, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    Rc = Rw - box(Rw)
    corr = box(Lc * Rc) / np.sqrt(np.maximum(box(Lc * Lc) * box(Rc * Rc), 1e-12))
    g = cv2.remap(gR, mx, rows, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    energy = box((g - box(g)) ** 2) * (window * window)
    return d, corr, energy


def _mark_mask(shape, m) -> np.ndarray:
    """uint8 mask (255) of the reseau crosses / fiducials of a scan (pixel system)."""
    from softplot.matching.ties import mark_pixels

    mask = np.zeros(shape[:2], np.float32)
    mp, rad_mm = mark_pixels(m.correction)
    r = int(np.ceil(rad_mm / m.frame.pixel_mm)) + 2
    for x, y in mp:
        cv2.circle(mask, (int(round(x)), int(round(y))), r, 1.0, -1)
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


def _grid(P, sZ, gsd, min_points) -> DSM:
    """Plane-fit gridding of points P (N, 3) with height precision sZ (N,)."""
    if len(P) == 0:
        raise SoftplotError("dense matching found no valid surface point")
    X, Y, Z = P.T
    x0 = np.floor(X.min() / gsd) * gsd + 0.5 * gsd
    y0 = np.ceil(Y.max() / gsd) * gsd - 0.5 * gsd
    cols = int(np.floor((X.max() - x0) / gsd + 0.5)) + 1
    rows = int(np.floor((y0 - Y.min()) / gsd + 0.5)) + 1
    c = np.clip(np.rint((X - x0) / gsd).astype(np.int64), 0, cols - 1)
    r = np.clip(np.rint((y0 - Y) / gsd).astype(np.int64), 0, rows - 1)
    idx = r * cols + c
    n = rows * cols
    dx = (X - (x0 + c * gsd)) / gsd
    dy = (Y - (y0 - r * gsd)) / gsd
    # robust centre first: median-free two passes (drop points far from the first plane)
    w = np.ones(len(P))
    Zc = None
    for _ in range(2):
        s = {k: np.bincount(idx, weights=w * v, minlength=n) for k, v in
             (("1", np.ones_like(dx)), ("x", dx), ("y", dy), ("xx", dx * dx),
              ("xy", dx * dy), ("yy", dy * dy), ("z", Z), ("zx", Z * dx), ("zy", Z * dy))}
        N = np.stack([np.stack([s["1"], s["x"], s["y"]], -1), np.stack([s["x"], s["xx"], s["xy"]],
                      -1), np.stack([s["y"], s["xy"], s["yy"]], -1)], -2)
        b = np.stack([s["z"], s["zx"], s["zy"]], -1)
        cnt = s["1"]
        # a cell needs enough points around its centre (no extrapolation of a plane
        # from a few points at its edge)
        full = float(np.median(cnt[cnt > 0])) if (cnt > 0).any() else 0.0
        with np.errstate(invalid="ignore", divide="ignore"):
            cx, cy = s["x"] / cnt, s["y"] / cnt
        use = ((cnt >= max(min_points, 0.4 * full)) & (np.abs(cx) <= 0.25)
               & (np.abs(cy) <= 0.25))
        sol = np.full((n, 3), np.nan)
        det = np.linalg.det(N[use])
        good = np.abs(det) > 1e-6 * np.maximum(cnt[use], 1) ** 3
        ui = np.flatnonzero(use)[good]
        sol[ui] = np.linalg.solve(N[ui], b[ui][..., None])[..., 0]
        # cells with too little spread for a plane: their weighted mean
        flat = np.flatnonzero(use)[~good]
        sol[flat, 0] = b[flat, 0] / cnt[flat]
        sol[flat, 1:] = 0.0
        Zc = sol[:, 0]
        pred = sol[idx, 0] + sol[idx, 1] * dx + sol[idx, 2] * dy
        res = Z - pred
        tol = np.maximum(4.0 * sZ, 3.0 * np.nanmedian(np.abs(res)) * 1.4826)
        w = (np.abs(res) <= tol).astype(float)
    var = np.bincount(idx, weights=w * sZ**2, minlength=n) / np.maximum(cnt, 1)
    valid = np.isfinite(Zc) & use
    Zg = np.where(valid, Zc, np.nan).reshape(rows, cols).astype(np.float32)
    Sg = np.where(valid, np.sqrt(var), np.nan).reshape(rows, cols).astype(np.float32)
    return DSM(Zg, Sg, float(x0), float(y0), float(gsd),
               {"cells_valid": int(valid.sum()), "cells": int(n)})


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
