"""Tie points between the two scans of a stereo pair, each with its precision.

Pipeline of :func:`match_pair`:

1. **film-corrected overviews**: each scan is resampled once onto its calibrated film grid
   (:func:`softplot.correction.resample`) at ``factor`` x the scan pixel (the longer side about
   ``overview_px`` pixels); the reseau crosses and fiducials are masked out;
2. **SIFT** (OpenCV) in both overviews, Lowe's ratio test and a mutual (left-right) check;
3. **five-point RANSAC** (``cv2.findEssentialMat``) on the photo coordinates of the
   candidates (through the film correction and interior orientation);
4. a **well distributed** subset: at most ``max_ties`` candidates, spread over a grid of cells;
5. **least-squares matching** (:func:`softplot.matching.lsm.match_patches`) in the scans
   themselves: the left point is an integer scan pixel, the right one is refined to a fraction
   of a pixel with its standard deviation; poor correlation or precision is dropped;
6. **relative orientation** (:func:`softplot.orientation.relative.relative_orientation`,
   coplanarity, Gauss-Helmert) of the refined photo coordinates weighted by their precision,
   with data snooping: flagged points are removed and the orientation repeated.

Coordinates: scan pixels (x right, y down, origin at the centre of the top-left pixel), film
and photo mm (x right, y up).
"""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from softplot.errors import SoftplotError
from softplot.matching.lsm import match_patches

__all__ = ["MatchOptions", "TieResult", "match_pair", "gruber_counts", "MIN_TIES"]

#: fewest ties a model can be set up with
MIN_TIES = 6


@dataclass
class MatchOptions:
    """Parameters of :func:`match_pair`.

    Attributes
    ----------
    max_ties : int
        Ties refined by least-squares matching (spread over ``grid`` x ``grid`` cells).
    grid : int
    ratio : float
        Lowe's ratio test threshold.
    overview_px : int
        Longer side of the film-corrected overviews SIFT runs on, px.
    ransac_px : float
        Five-point RANSAC threshold, overview pixels.
    half : int
        Least-squares matching template half size, scan px.
    min_corr : float
        Least correlation coefficient of a match.
    max_std_px : float
        Largest standard deviation of a match, px.
    sigma_floor_px : float
        Least standard deviation given to a match in the relative orientation, px.
    """

    max_ties: int = 600
    grid: int = 8
    ratio: float = 0.8
    overview_px: int = 1600
    ransac_px: float = 1.5
    half: int = 13
    min_corr: float = 0.8
    max_std_px: float = 0.5
    sigma_floor_px: float = 0.02


@dataclass
class TieResult:
    """Tie points of a pair.

    Attributes
    ----------
    names : list of str
    left_px, right_px : ndarray (n, 2)
        Scan pixels of each tie (left: integer pixel, the template centre).
    std_px : ndarray (n, 2)
        Standard deviation of the right position (the match), px.
    corr : ndarray (n,)
        Correlation coefficient of the match.
    left_photo, right_photo : ndarray (n, 2)
        Photo mm through each scan's film correction.
    py_px : ndarray (n,)
        Residual y-parallax after the relative orientation, in scan pixels.
    ro : RelativeOrientation
    pixel_mm : float
        Scan pixel size (mean of the two), mm.
    gruber : list of int
        Ties in each of the six Gruber areas (left photo).
    counts : dict
        Candidates after each stage.
    """

    names: list
    left_px: np.ndarray
    right_px: np.ndarray
    std_px: np.ndarray
    corr: np.ndarray
    left_photo: np.ndarray
    right_photo: np.ndarray
    py_px: np.ndarray
    ro: object
    pixel_mm: float
    gruber: list
    counts: dict = field(default_factory=dict)
    sigma_prior_mm: float = float("nan")
    #: (n, 2) index of each tie's SIFT keypoint in the left and right overview (the same
    #: keypoints in every pair a scan is part of: they link pairs into multi-ray points)
    keypoints: np.ndarray | None = None
    #: factor applied to the matches' own standard deviations: the a posteriori sigma0 of
    #: the relative orientation (over the a priori one) when it is above 1
    std_scale: float = 1.0

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def rms_px(self) -> float:
        """RMS residual y-parallax after the relative orientation, px."""
        return float(np.sqrt(np.mean(self.py_px**2)))

    def to_json(self) -> dict:
        ro = self.ro
        std = ro.std
        return {
            "n": self.n,
            "sigma0": float(ro.sigma0 / self.sigma_prior_mm),
            "sigma0_um": float(ro.sigma0 * 1000.0),
            "sigma0_note": "sigma0: a posteriori / a priori (the matches' own precision); "
                           "sigma0_um: photo micrometres",
            "rms_px": self.rms_px,
            "std_px_median": float(np.median(np.hypot(*self.std_px.T))),
            "std_scale": self.std_scale,
            "gruber": self.gruber,
            "counts": self.counts,
            "relative_orientation": {
                "mode": ro.mode,
                "bx": ro.value("bx"), "by": ro.value("by"), "bz": ro.value("bz"),
                "omega2": ro.value("omega2"), "phi2": ro.value("phi2"),
                "kappa2": ro.value("kappa2"),
                "std": {k: float(v) for k, v in std.items()},
                "angles_unit": "rad",
                "redundancy": int(ro.redundancy),
            },
        }

    def write(self, out: str | Path, overwrite: bool = False) -> dict:
        """Write ``left.csv``, ``right.csv`` (name,x,y pixels), ``ties.csv`` and
        ``match.json`` into ``out``; refuses to overwrite unless ``overwrite``."""
        out = Path(out)
        files = {k: out / f for k, f in (("left", "left.csv"), ("right", "right.csv"),
                                         ("ties", "ties.csv"), ("json", "match.json"))}
        check_outputs(files.values(), overwrite)
        out.mkdir(parents=True, exist_ok=True)
        for side, xy in (("left", self.left_px), ("right", self.right_px)):
            _write_csv(files[side], ["name", "x", "y"],
                       ([n, f"{x:.4f}", f"{y:.4f}"] for n, (x, y) in zip(self.names, xy,
                                                                          strict=True)))
        _write_csv(files["ties"], ["name", "x_left", "y_left", "x_right", "y_right", "sx_px",
                                   "sy_px", "corr", "py_px"],
                   ([n, f"{a[0]:.4f}", f"{a[1]:.4f}", f"{b[0]:.4f}", f"{b[1]:.4f}",
                     f"{s[0]:.4f}", f"{s[1]:.4f}", f"{c:.4f}", f"{p:.4f}"]
                    for n, a, b, s, c, p in zip(self.names, self.left_px, self.right_px,
                                                self.std_px, self.corr, self.py_px,
                                                strict=True)))
        tmp = files["json"].with_name(".match.json.part")
        tmp.write_text(json.dumps(self.to_json(), indent=1) + "\n", encoding="utf-8")
        tmp.replace(files["json"])
        return {k: str(v) for k, v in files.items()}


def check_outputs(paths, overwrite: bool) -> None:
    """Refuse (one line) when an output exists and ``overwrite`` is not set."""
    if overwrite:
        return
    for p in paths:
        if Path(p).exists():
            raise SoftplotError(f"{p}: exists; refusing to overwrite (use --overwrite)")


def _write_csv(path: Path, header, rows) -> None:
    tmp = path.with_name(f".{path.name}.part")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    tmp.replace(path)


# --------------------------------------------------------------------------- overviews


def _to_uint8(img: np.ndarray, valid: np.ndarray) -> np.ndarray:
    v = img[valid]
    if v.size == 0:
        return np.zeros(img.shape, np.uint8)
    lo, hi = np.percentile(v, [0.5, 99.5])
    out = (img - lo) * (255.0 / max(hi - lo, 1e-6))
    return np.clip(out, 0, 255).astype(np.uint8)


def film_overview(grey: np.ndarray, correction, factor: float, pixel_mm: float):
    """A film-corrected overview of a scan and the mask SIFT may use.

    Returns
    -------
    (image uint8 (h, w), mask uint8 (h, w), to_scan)
        ``to_scan((N, 2) overview px) -> (N, 2) scan px``.
    """
    from softplot.correction import resample

    ps = factor * pixel_mm
    res = resample(grey, correction, ps, "linear")
    img = res.image[..., 0] if res.image.ndim == 3 else res.image
    inside = resample(np.ones_like(grey, np.uint8), correction, ps, "nearest").image
    inside = (inside[..., 0] if inside.ndim == 3 else inside) > 0
    inside = cv2.erode(inside.astype(np.uint8), np.ones((9, 9), np.uint8)) > 0
    mask = inside.astype(np.uint8) * 255
    cam = correction.camera
    marks = []
    arm = 1.0
    if cam.reseau is not None:
        marks.append(cam.reseau.film().reshape(-1, 2))
        arm = float(cam.reseau.arm_length_mm)
    fid = cam.fiducial_film()
    if len(fid):
        marks.append(np.asarray(fid, float).reshape(-1, 2))
        arm = max(arm, 2.0)
    if marks:
        m = np.vstack(marks)
        cols = (m[:, 0] - res.x_min_mm) / ps - 0.5
        rows = (res.y_max_mm - m[:, 1]) / ps - 0.5
        r = int(np.ceil((0.5 * arm + 0.25) / ps)) + 2
        for x, y in zip(cols, rows, strict=True):
            cv2.circle(mask, (int(round(x)), int(round(y))), r, 0, -1)
    img8 = _to_uint8(img, inside)

    def to_scan(xy):
        xy = np.asarray(xy, float).reshape(-1, 2)
        film = np.c_[res.x_min_mm + (xy[:, 0] + 0.5) * ps, res.y_max_mm - (xy[:, 1] + 0.5) * ps]
        return correction.to_pixel(film, frm="film")[0]

    return img8, mask, to_scan


def mark_pixels(correction) -> tuple[np.ndarray, float]:
    """Scan pixels (M, 2) of every reseau cross and fiducial, and their radius in mm."""
    cam = correction.camera
    marks, arm = [], 1.0
    if cam.reseau is not None:
        marks.append(cam.reseau.film().reshape(-1, 2))
        arm = float(cam.reseau.arm_length_mm)
    if len(cam.fiducial_film()):
        marks.append(np.asarray(cam.fiducial_film(), float).reshape(-1, 2))
        arm = max(arm, 2.0)
    if not marks:
        return np.zeros((0, 2)), 0.0
    return correction.to_pixel(np.vstack(marks), frm="film")[0], 0.5 * arm + 0.1


# --------------------------------------------------------------------------- matching


def _clear_of_marks(xy, correction, pixel_mm, half):
    """True where a patch of half size ``half`` about scan pixel ``xy`` misses every mark."""
    mp, rad_mm = mark_pixels(correction)
    if not len(mp) or not len(xy):
        return np.ones(len(xy), bool)
    from scipy.spatial import cKDTree

    d, _ = cKDTree(mp).query(np.asarray(xy, float).reshape(-1, 2))
    return d > rad_mm / pixel_mm + np.sqrt(2) * (half + 2)


def _parallax_consistent(sl, sr, tol_px: float, k: int = 12) -> np.ndarray:
    """True where a tie's offset ``sr - sl`` agrees, within ``tol_px``, with the plane fitted
    to the offsets of its ``k`` nearest neighbours (in the left image).

    Catches false matches that slide along the epipolar line (the coplanarity cannot see
    them): the terrain's parallax is locally smooth.
    """
    from scipy.spatial import cKDTree

    n = len(sl)
    if n < 6:
        return np.ones(n, bool)
    k = min(k, n - 1)
    _, nb = cKDTree(sl).query(sl, k + 1)
    nb = nb[:, 1:]
    off = sr - sl
    d = sl[nb] - sl[:, None, :]  # (n, k, 2)
    X = np.concatenate([np.ones((n, k, 1)), d / max(1.0, float(np.ptp(sl)))], axis=2)
    Y = off[nb]  # (n, k, 2)
    # robust: two passes, the second without the neighbours far from the first plane
    w = np.ones((n, k))
    for _ in range(2):
        Xw = X * w[..., None]
        N = np.einsum("nki,nkj->nij", Xw, X) + 1e-9 * np.eye(3)
        coef = np.linalg.solve(N, np.einsum("nki,nkj->nij", Xw, Y))  # (n, 3, 2)
        r = np.linalg.norm(Y - np.einsum("nki,nij->nkj", X, coef), axis=2)
        w = (r <= max(tol_px, 3.0 * float(np.median(r)))).astype(float)
    return np.linalg.norm(off - coef[:, 0, :], axis=1) <= tol_px


def _sift(img, mask, nfeatures=6000):
    sift = cv2.SIFT_create(nfeatures=nfeatures, contrastThreshold=0.01)
    kp, des = sift.detectAndCompute(img, mask)
    if des is None or len(kp) == 0:
        return np.zeros((0, 2)), np.zeros((0, 128), np.float32), np.zeros(0)
    return (np.array([k.pt for k in kp], float), des,
            np.array([k.response for k in kp], float))


def _mutual_ratio(d1, d2, ratio):
    """Indices (i1, i2) passing the ratio test both ways and mutually nearest."""
    if len(d1) < 2 or len(d2) < 2:
        return np.zeros(0, int), np.zeros(0, int)
    # exact (brute force) nearest neighbours: the same matches on every machine and thread
    # count (FLANN's randomised trees are not)
    fl = cv2.BFMatcher(cv2.NORM_L2)
    f = fl.knnMatch(d1, d2, k=2)
    # the way back only for the descriptors the way there reached (the same result)
    tgt = np.unique([m[0].trainIdx for m in f
                     if len(m) == 2 and m[0].distance < ratio * m[1].distance])
    best_b = np.full(len(d2), -1)
    if len(tgt):
        b = fl.knnMatch(np.ascontiguousarray(d2[tgt]), d1, k=2)
        for m in b:
            if len(m) == 2 and m[0].distance < ratio * m[1].distance:
                best_b[tgt[m[0].queryIdx]] = m[0].trainIdx
    i1, i2 = [], []
    for m in f:
        if len(m) == 2 and m[0].distance < ratio * m[1].distance:
            if best_b[m[0].trainIdx] == m[0].queryIdx:
                i1.append(m[0].queryIdx)
                i2.append(m[0].trainIdx)
    return np.array(i1, int), np.array(i2, int)


def _separated(xy, score, dist: float) -> np.ndarray:
    """Indices (sorted) of points at least ``dist`` apart (Chebyshev distance, px), best
    ``score`` first (greedy)."""
    from scipy.spatial import cKDTree

    xy = np.asarray(xy, float).reshape(-1, 2)
    if len(xy) < 2:
        return np.arange(len(xy))
    tree = cKDTree(xy)
    taken = np.zeros(len(xy), bool)
    blocked = np.zeros(len(xy), bool)
    for i in np.argsort(-np.asarray(score, float), kind="stable"):
        if blocked[i]:
            continue
        taken[i] = True
        blocked[tree.query_ball_point(xy[i], dist - 1e-9, p=np.inf)] = True
    return np.flatnonzero(taken)


def _spread(xy, score, shape, grid, k_max):
    """Indices of at most ``k_max`` points, spread over a ``grid`` x ``grid`` partition."""
    h, w = shape
    cell = (np.minimum((xy[:, 1] / h * grid).astype(int), grid - 1) * grid
            + np.minimum((xy[:, 0] / w * grid).astype(int), grid - 1))
    order = np.lexsort((-score, cell))
    cell_s = cell[order]
    rank = np.arange(len(order)) - np.searchsorted(cell_s, cell_s)
    per = max(1, int(np.ceil(k_max / max(1, len(np.unique(cell))))))
    keep = order[rank < per]
    if len(keep) > k_max:
        keep = keep[np.argsort(-score[keep])[:k_max]]
    return np.sort(keep)


def gruber_counts(xy_left_mm, px_mm, format_mm, *, radius_frac: float = 0.15) -> list:
    """Ties in each of the six Gruber areas of the left photo.

    Areas (photo mm, left photo): about the left principal point ``(0, 0)`` and the right
    one's image ``(bp, 0)`` (``bp`` the median x-parallax of the ties), and above and below
    each at ``+-0.35`` of the format height; squares of half side ``radius_frac`` x format.
    Order: 1 (0, 0), 2 (bp, 0), 3 (0, +d), 4 (bp, +d), 5 (0, -d), 6 (bp, -d).
    """
    xy = np.asarray(xy_left_mm, float).reshape(-1, 2)
    bp = float(np.median(px_mm)) if len(px_mm) else 0.0
    d = 0.35 * format_mm[1]
    r = radius_frac * max(format_mm)
    centres = [(0, 0), (bp, 0), (0, d), (bp, d), (0, -d), (bp, -d)]
    return [int(np.sum((np.abs(xy[:, 0] - cx) <= r) & (np.abs(xy[:, 1] - cy) <= r)))
            for cx, cy in centres]


def _essential_inliers(p1, p2, c, thr_mm):
    """Five-point RANSAC (OpenCV) on photo mm; boolean inliers."""
    if len(p1) < 5:
        return np.zeros(len(p1), bool)
    n1 = np.c_[p1[:, 0] / c, -p1[:, 1] / c]
    n2 = np.c_[p2[:, 0] / c, -p2[:, 1] / c]
    try:
        E, inl = cv2.findEssentialMat(n1, n2, np.eye(3), method=cv2.RANSAC, prob=0.9999,
                                      threshold=thr_mm / c, maxIters=5000)
    except cv2.error:
        return np.zeros(len(p1), bool)
    if E is None or inl is None:
        return np.zeros(len(p1), bool)
    return inl.ravel().astype(bool)


def match_pair(left, right, left_map, right_map, options: MatchOptions | None = None,
               progress=None) -> TieResult:
    """Tie points of a stereo pair (see the module docstring).

    Parameters
    ----------
    left, right : softplot.io.Scan or ndarray (H, W)
        The scans (grey float32 in [0, 1] when arrays).
    left_map, right_map : softplot.correction.ScanPhotoMap
        Each scan's frame and film correction (scan pixel <-> photo mm).
    options : MatchOptions, optional
    progress : callable(str), optional
        Called with the name of each stage.

    Raises
    ------
    SoftplotError
        The scans do not overlap (too few consistent candidates) or fewer than
        :data:`MIN_TIES` ties survive the filtering.
    """
    from softplot.adjust import UndeterminedError
    from softplot.orientation.relative import relative_orientation

    opt = options or MatchOptions()
    say = progress or (lambda s: None)
    greys = [s if isinstance(s, np.ndarray) else s.pixels for s in (left, right)]
    greys = [np.ascontiguousarray(g, np.float32) for g in greys]
    maps = (left_map, right_map)
    cam = left_map.correction.camera
    c = float(cam.c)
    pixel_mm = [float(m.frame.pixel_mm) for m in maps]
    pmm = float(np.mean(pixel_mm))
    counts = {}

    # 1-2: overviews, SIFT, ratio + mutual
    say("overviews")
    ovs, kps = [], []
    for g, m, p in zip(greys, maps, pixel_mm, strict=True):
        factor = max(1.0, max(g.shape) / opt.overview_px)
        img, mask, to_scan = film_overview(g, m.correction, factor, p)
        ovs.append((img, to_scan, factor * p))
        kps.append(_sift(img, mask))
    counts["keypoints"] = [len(k[0]) for k in kps]
    say("sift")
    i1, i2 = _mutual_ratio(kps[0][1], kps[1][1], opt.ratio)
    counts["candidates"] = int(len(i1))
    if len(i1) < MIN_TIES:
        raise SoftplotError(
            f"the scans do not overlap (or show nothing to match): {len(i1)} candidate "
            f"matches, at least {MIN_TIES} needed")
    sl = ovs[0][1](kps[0][0][i1])
    sr = ovs[1][1](kps[1][0][i2])
    ph1 = left_map.pixel_to_photo(sl)
    ph2 = right_map.pixel_to_photo(sr)
    inl = _essential_inliers(ph1, ph2, c, opt.ransac_px * max(ovs[0][2], ovs[1][2]))
    counts["ransac"] = int(inl.sum())
    if inl.sum() < MIN_TIES:
        raise SoftplotError(
            f"the scans do not overlap: {int(inl.sum())} of {len(i1)} candidate matches agree "
            f"with one relative orientation, at least {MIN_TIES} needed")
    sl, sr = sl[inl], sr[inl]
    score = kps[0][2][i1][inl]
    kid = np.c_[i1, i2][inl]
    good = _parallax_consistent(sl, sr, 4.0 * max(ovs[0][2], ovs[1][2]) / min(pixel_mm))
    sl, sr, score, kid = sl[good], sr[good], score[good], kid[good]
    counts["smooth"] = int(len(sl))
    # avoid the marks: template and right patch must keep clear of every cross / fiducial
    say("lsm")
    keep = _clear_of_marks(sl, maps[0].correction, pixel_mm[0], opt.half)
    keep &= _clear_of_marks(sr, maps[1].correction, pixel_mm[1], opt.half)
    sl, sr, score, kid = sl[keep], sr[keep], score[keep], kid[keep]
    # independent ties: no two templates overlap (overlapping patches share their noise and
    # texture, so their errors are correlated and the orientation's precision optimistic)
    sep = _separated(sl, score, 2 * opt.half + 2)
    sl, sr, score, kid = sl[sep], sr[sep], score[sep], kid[sep]
    sel = _spread(sl, score, greys[0].shape, opt.grid, opt.max_ties)
    sl, sr, kid = sl[sel], sr[sel], kid[sel]
    counts["selected"] = int(len(sl))
    if len(sl) < MIN_TIES:
        raise SoftplotError(f"too few ties: {len(sl)} consistent candidates clear of the marks, "
                            f"at least {MIN_TIES} needed (do the scans overlap?)")
    A = None
    if len(sl) >= 3:
        A2, _ = cv2.estimateAffine2D(sl.astype(np.float32), sr.astype(np.float32),
                                     method=cv2.LMEDS)
        A = None if A2 is None else A2[:, :2]
    pm = match_patches(greys[0], greys[1], sl, sr, A, half=opt.half,
                       max_shift=3.0 * max(1.0, ovs[1][2] / pixel_mm[1]))
    ok = pm.ok & (pm.corr >= opt.min_corr) & np.all(pm.std <= opt.max_std_px, axis=1)
    # the right patch must keep clear of the marks too (after refinement)
    ok &= _clear_of_marks(pm.xy, right_map.correction, pixel_mm[1], opt.half)
    ok[ok] &= _parallax_consistent(np.rint(sl[ok]), pm.xy[ok], 1.5)
    counts["lsm"] = int(ok.sum())
    L = np.rint(sl[ok])
    R = pm.xy[ok]
    S = pm.std[ok]
    corr = pm.corr[ok]
    kid = kid[ok]
    if len(L) < MIN_TIES:
        raise SoftplotError(f"too few ties: {len(L)} after least-squares matching, at least "
                            f"{MIN_TIES} needed")

    # 6: relative orientation with data snooping
    say("relative orientation")
    p1 = left_map.pixel_to_photo(L)
    p2 = right_map.pixel_to_photo(R)
    sig = np.maximum(S, opt.sigma_floor_px) * pmm / np.sqrt(2.0)
    keep = np.ones(len(L), bool)
    ro = None
    for _ in range(8):
        idx = np.flatnonzero(keep)
        if len(idx) < MIN_TIES:
            break
        s4 = np.c_[sig[idx], sig[idx]]
        try:
            ro = relative_orientation(p1[idx], p2[idx], c, bx=1.0, sigma=s4)
        except (UndeterminedError, SoftplotError) as exc:
            raise SoftplotError(f"relative orientation of the ties failed: {exc}") from None
        if not ro.flagged.any():
            break
        keep[idx[ro.flagged]] = False
    idx = np.flatnonzero(keep)
    counts["kept"] = int(len(idx))
    if len(idx) < MIN_TIES or ro is None:
        raise SoftplotError(f"too few ties: {len(idx)} after filtering, at least {MIN_TIES} "
                            "needed")
    if len(ro.flagged) != len(idx):  # last round removed points: adjust the rest once more
        ro = relative_orientation(p1[idx], p2[idx], c, bx=1.0,
                                  sigma=np.c_[sig[idx], sig[idx]])
    names = [f"A{i + 1:04d}" for i in range(len(idx))]
    py_px = ro.py / pmm
    px_mm = p1[idx, 0] - p2[idx, 0]
    gr = gruber_counts(p1[idx], px_mm, cam.format_mm)
    # the stated precision is the matches' own, scaled by the orientation's variance factor
    # when the residual y-parallaxes say it is optimistic
    s_prior = float(np.median(sig[idx]))
    scale = max(1.0, float(ro.sigma0) / s_prior)
    return TieResult(names, L[idx], R[idx], S[idx] * scale, corr[idx], p1[idx], p2[idx], py_px,
                     ro, pmm, gr, counts, s_prior, kid[idx], scale)

