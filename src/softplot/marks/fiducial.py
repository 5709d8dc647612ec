"""Fiducial marks of metric and aerial cameras (cross, dot, circle with dot).

1. Predict each fiducial's pixel position from the certificate (film mm), the dpi and the
   stated quarter-turn, with the film centre at the scan centre; its search window covers an
   unknown offset (the scan's margin plus 10 mm) and a rotation of +-12 degrees.
2. Overview of the scan (factor chosen so the thinnest stroke is about one overview pixel),
   NCC with each fiducial's template inside its window only; the strongest peaks of each sign
   are candidates.
3. Pattern match: every pair of fiducials and pair of their candidates proposes a similarity
   transform (scale within tolerance of the dpi, rotation within the range); the proposal that
   explains most fiducials (then the highest summed score) wins; the polarity with the better
   match is the scan's.
4. LSM at full resolution for each fiducial with its analytic model, acceptance tests, then an
   affine (up to 4 marks) or projective (5 or more) film -> pixel model; a mark whose residual
   exceeds 0.3 mm is rejected.
"""

from __future__ import annotations

import time

import numpy as np

from softplot.marks import coarse, grid
from softplot.marks.common import (
    MM_PER_INCH,
    DetectionError,
    blank_check,
    polarity_signs,
    transform_json,
)
from softplot.marks.measure import measure
from softplot.marks.result import Detection
from softplot.marks.template import fiducial_shape

__all__ = ["detect_fiducials", "layout_turns"]

MAX_ROT_DEG = 12.0


def _rot(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def _film_to_pix_linear(k, theta):
    """Linear part film mm -> pixel for scale k (px/mm) and pixel-system angle theta."""
    return k * _rot(theta) @ np.diag([1.0, -1.0])


def _candidates(ov, F, fids, pred_full, radius_full, ppm, blur_px, signs, per=6):
    """NCC peaks (full-res px) inside each fiducial's window: list of (xy, score, sign)."""
    out = []
    cache = {}
    for i, fd in enumerate(fids):
        shp = fiducial_shape(fd, ppm / F)
        key = (shp.kind, round(shp.length, 2), round(shp.width, 2), round(shp.radius, 2),
               round(shp.dot_radius, 2))
        c = coarse.full_to_ov(pred_full[i], F)
        r = radius_full / F
        x0 = int(max(np.floor(c[0] - r), 0))
        y0 = int(max(np.floor(c[1] - r), 0))
        x1 = int(min(np.ceil(c[0] + r) + 1, ov.shape[1]))
        y1 = int(min(np.ceil(c[1] + r) + 1, ov.shape[0]))
        cand = (np.zeros((0, 2)), np.zeros(0), np.zeros(0, int))
        if x1 - x0 > 4 and y1 - y0 > 4:
            win = ov[y0:y1, x0:x1]
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
        out.append(cand)
    return out


def _match(film, cands, k_nom, theta0, scale_tol, sign):
    """Best similarity film -> pixel explaining most fiducials with candidates of ``sign``."""
    n = len(film)
    best = None
    c_xy = [c[0][c[2] == sign] for c in cands]
    c_sc = [c[1][c[2] == sign] for c in cands]
    tol_px = None
    for i in range(n):
        for j in range(i + 1, n):
            if len(c_xy[i]) == 0 or len(c_xy[j]) == 0:
                continue
            df = film[j] - film[i]
            df_pix = np.array([df[0], -df[1]])  # film -> pixel axes (y flipped)
            a = c_xy[i][:, None, :]
            b = c_xy[j][None, :, :]
            d = (b - a).reshape(-1, 2)
            ai = np.repeat(np.arange(len(c_xy[i])), len(c_xy[j]))
            ln = np.hypot(d[:, 0], d[:, 1])
            k = ln / max(np.hypot(*df_pix), 1e-9)
            ang = np.arctan2(d[:, 1], d[:, 0]) - np.arctan2(df_pix[1], df_pix[0])
            ang = (ang - theta0 + np.pi) % (2 * np.pi) - np.pi
            ok = (np.abs(k / k_nom - 1.0) < scale_tol) & (np.abs(ang) < np.radians(MAX_ROT_DEG))
            for q in np.where(ok)[0]:
                th = theta0 + ang[q]
                Lm = _film_to_pix_linear(k[q], th)
                t = c_xy[i][ai[q]] - Lm @ film[i]
                pred = film @ Lm.T + t
                tol_px = max(8.0, 0.4 * k[q])  # 0.4 mm
                total = 0.0
                count = 0
                pick = np.full(n, -1)
                for m in range(n):
                    if len(c_xy[m]) == 0:
                        continue
                    dd = np.hypot(*(c_xy[m] - pred[m]).T)
                    near = np.where(dd < tol_px)[0]
                    if near.size:
                        best_m = near[np.argmax(c_sc[m][near])]
                        pick[m] = best_m
                        total += c_sc[m][best_m]
                        count += 1
                key = (count, total)
                if best is None or key > best[0]:
                    best = (key, pick, Lm, t, k[q], th)
    if n == 1 and len(c_xy[0]):
        # a single mark has no pattern: the best-scoring candidate where the certificate puts
        # it (the measuring stage's acceptance tests then judge its shape)
        j = int(np.argmax(c_sc[0]))
        Lm = _film_to_pix_linear(k_nom, theta0)
        best = ((1, float(c_sc[0][j])), np.array([j]), Lm, c_xy[0][j] - Lm @ film[0], k_nom,
                theta0)
    return best


#: film mm: fiducials this close after a quarter turn of the layout are in each other's place
SYMMETRY_TOL_MM = 0.2


def layout_turns(fids) -> list[int]:
    """The quarter turns (90, 180, 270 degrees) that map a fiducial layout onto itself: the
    positions (within :data:`SYMMETRY_TOL_MM`) and the shapes. Under such a turn the scan
    alone cannot tell the marks apart: their names rest on ``--rotate``."""
    film = np.array([[f.x, f.y] for f in fids], float)
    shapes = [(f.shape, round(f.size_mm, 3)) for f in fids]
    out = []
    for k in (1, 2, 3):
        c, s_ = np.cos(k * np.pi / 2), np.sin(k * np.pi / 2)
        turned = film @ np.array([[c, -s_], [s_, c]]).T
        d = np.hypot(*(turned[:, None, :] - film[None, :, :]).transpose(2, 0, 1))
        j = d.argmin(1)
        if (d[np.arange(len(film)), j] <= SYMMETRY_TOL_MM).all() and len(set(j)) == len(j) \
                and all(shapes[a] == shapes[b] for a, b in enumerate(j)):
            out.append(90 * k)
    return out


def detect_fiducials(sc, cam, *, name, dpi, polarity, rotate, blur_px, rules) -> Detection:
    """Fiducial-mark detection (see the module docstring); same result type as reseau."""
    t0 = time.perf_counter()
    timings: dict = {}
    fids = list(cam.fiducials)
    n = len(fids)
    film = cam.fiducial_film()
    warnings: list[str] = []
    dpi_source = "given" if dpi is not None else ("file" if sc.dpi else "estimated")
    dpi = dpi if dpi is not None else sc.dpi
    scale_tol = 0.06
    if dpi is None:
        dpi = 25.4 * min(sc.width / cam.format_mm[0], sc.height / cam.format_mm[1])
        scale_tol = 0.35
    ppm = dpi / MM_PER_INCH
    span = film.max(0) - film.min(0) if n > 1 else np.array([1.0, 1.0])
    need = 0.5 * span * ppm
    if sc.width < need[0] or sc.height < need[1]:
        raise DetectionError(
            f"{name}: scan of {sc.width}x{sc.height} px is much smaller than the {cam.name} "
            f"fiducial pattern at {dpi:.0f} dpi (expected about {span[0] * ppm:.0f}x"
            f"{span[1] * ppm:.0f} px or more)")
    theta0 = np.radians(-float(rotate))
    # overview factor: the finest feature (a stroke, a centre dot, a fifth of a dot) about
    # 1.2 overview px, and an overview of at most ~12 Mpx
    def feature(f):
        if f.shape == "dot":
            return f.size_mm / 5.0
        if f.shape == "circle-dot":
            return min(f.line_width_mm, f.dot_mm)
        return f.line_width_mm

    F = max(1, int(min(feature(f) for f in fids) * ppm / 1.2))
    while sc.width * sc.height / (F * F) > 12e6:
        F += 1
    ov = coarse.overview(sc, F)
    blank_check(ov, name)
    timings["overview"] = time.perf_counter() - t0
    centre = np.array([(sc.width - 1) / 2.0, (sc.height - 1) / 2.0])
    Lm0 = _film_to_pix_linear(ppm, theta0)
    pred = film @ Lm0.T + centre
    margin = max(abs(sc.width - cam.format_mm[0] * ppm), abs(sc.height - cam.format_mm[1] * ppm))
    radius = (0.5 * margin + 10.0 * ppm
              + np.hypot(*film.T).max() * ppm * (np.sin(np.radians(MAX_ROT_DEG)) + scale_tol))
    signs = polarity_signs(polarity)
    cands = _candidates(ov, F, fids, pred, radius, ppm, blur_px, signs)
    best = None
    for sg in signs:
        b = _match(film, cands, ppm, theta0, scale_tol, sg)
        if b is not None and (best is None or b[0] > best[0][0]):
            best = (b, sg)
    need_n = min(n, 2) if n <= 3 else 3
    if best is None or best[0][0][0] < need_n:
        found = 0 if best is None else best[0][0][0]
        raise DetectionError(
            f"{name}: fiducial marks not found: expected {n} {cam.name} fiducials "
            f"({', '.join(sorted({f.shape for f in fids}))}) about {span[0]:.0f} mm apart, "
            f"found {found} in the expected pattern")
    (key, pick, Lm, t, k_fit, th), sign = best
    timings["pattern"] = time.perf_counter() - t0
    if dpi_source == "estimated":
        dpi = k_fit * MM_PER_INCH
        ppm = k_fit
    pred = film @ Lm.T + t
    c0 = pred.copy()
    for m in range(n):
        if pick[m] >= 0:
            xy_c, _, sg_c = cands[m]
            c0[m] = xy_c[sg_c == sign][pick[m]]
    A0 = np.linalg.inv(Lm @ np.diag([1.0 / ppm, -1.0 / ppm]))
    xy = np.full((n, 2), np.nan)
    cov = np.full((n, 2, 2), np.nan)
    score = np.full(n, np.nan)
    cnr = np.full(n, np.nan)
    status = ["missing"] * n
    reason = ["not found"] * n
    s0 = float(blur_px)
    init_err = max(1.0, 0.5 * F + 0.5)
    for m, fd in enumerate(fids):
        shp = fiducial_shape(fd, ppm)
        ext = shp.extent + 2.0
        if not (ext <= c0[m, 0] <= sc.width - 1 - ext and ext <= c0[m, 1] <= sc.height - 1 - ext):
            reason[m] = "cut by the scan edge"
            continue
        fine = measure(sc, shp, c0[m : m + 1], A0[None], s0, init_err, sign, rules)
        score[m] = fine.score[0]
        cnr[m] = fine.cnr[0]
        if fine.ok[0]:
            xy[m] = fine.xy[0]
            cov[m] = fine.cov[0]
            status[m] = "measured"
            reason[m] = ""
        else:
            reason[m] = fine.reason[0] or "not found"
    ok = np.array([s == "measured" for s in status])
    if ok.sum() < need_n:
        raise DetectionError(
            f"{name}: fiducial marks not found: expected {n} {cam.name} fiducials "
            f"({', '.join(sorted({f.shape for f in fids}))}), found {int(ok.sum())} that "
            "look like them where the pattern puts them")
    Hm = _fit(film[ok], xy[ok], Lm, t)
    r = xy - grid.apply_h(Hm, film)
    bad = ok & (np.hypot(*r.T) > 0.3 * ppm)
    for m in np.where(bad)[0]:
        status[m] = "rejected"
        reason[m] = "outlier against the fiducial pattern"
    ok &= ~bad
    if bad.any():
        Hm = _fit(film[ok], xy[ok], Lm, t)
        r = xy - grid.apply_h(Hm, film)
    kind = "projective" if ok.sum() >= 5 else ("affine" if ok.sum() >= 3 else "similarity")
    rms = float(np.sqrt(np.mean(np.sum(r[ok] ** 2, 1)))) if ok.any() else float("nan")
    residual = np.where(ok[:, None], r, np.nan)
    if ok.sum() < n:
        warnings.append(f"{n - int(ok.sum())} of {n} fiducials not measured")
    turns = layout_turns(fids)
    if turns:
        warnings.append(
            f"the fiducial layout looks the same turned by {' or '.join(map(str, turns))} "
            "degrees: the marks' names rest on --rotate")
    tr = transform_json(Hm, rms, int(ok.sum()))
    tr["kind"] = kind
    return Detection(
        image=name, camera=cam.name, width=sc.width, height=sc.height, dpi=float(dpi),
        polarity="negative" if sign > 0 else "positive",
        kind=["fiducial"] * n, name=[f.name for f in fids],
        row=np.full(n, -1), col=np.full(n, -1), film=film, xy=xy,
        sigma=np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1])),
        sigma_xy=np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], 1)),
        cov=cov,
        score=score, cnr=cnr, status=status, reason=reason, transform=tr, rms_px=rms,
        residual=residual, warnings=warnings, dpi_source=dpi_source,
        timings={**timings, "total": time.perf_counter() - t0},
    )


def _fit(src, dst, Lm, t):
    """Projective (>= 5 points), affine (3-4), or the similarity from the pattern match."""
    if len(src) >= 5:
        return grid.projective_fit(src, dst)
    if len(src) >= 3:
        return grid.projective_fit(src, dst)  # affine for < 5 points
    H = np.eye(3)
    H[:2, :2] = Lm
    H[:2, 2] = t
    if len(src) >= 1:
        H[:2, 2] += np.mean(dst - src @ Lm.T - t, axis=0)
    return H
