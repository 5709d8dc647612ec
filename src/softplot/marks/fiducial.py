"""Fiducial marks of metric and aerial cameras (cross, dot, circle with dot).

The fiducial path runs the stages of the reseau path where they apply:

1. overview (:func:`softplot.marks.overview.make_overview`): factor chosen so the thinnest
   stroke is about one overview pixel;
2. candidates (:func:`softplot.marks.candidates.window_candidates`): each fiducial's position
   predicted from the certificate (film mm), the dpi and the stated quarter-turn, with the film
   centre at the scan centre; NCC with its template inside its window only (an unknown offset:
   the scan's margin plus 10 mm, and a rotation of +-12 degrees); the strongest peaks of each
   sign are candidates;
3. identification by the pattern (:func:`match_pattern`, this module): every pair of
   fiducials and pair of their candidates proposes a similarity transform (scale within
   tolerance of the dpi, rotation within the range); the proposal that explains most
   fiducials (then the highest summed score) wins; the polarity with the better match is the
   scan's;
4. measurement (:func:`softplot.marks.measurement.measure_marks`): LSM at full resolution for
   each fiducial with its analytic model, acceptance tests;
5. validation (:func:`softplot.marks.validation.validate_pattern`): an affine (up to 4 marks)
   or projective (5 or more) film -> pixel model; a mark whose residual exceeds 0.3 mm is
   rejected.
"""

from __future__ import annotations

import time

import numpy as np

from softplot.marks.candidates import WindowCandidates, window_candidates
from softplot.marks.common import MM_PER_INCH, DetectionError, polarity_signs, transform_json
from softplot.marks.measurement import measure_marks
from softplot.marks.overview import make_overview
from softplot.marks.result import Detection
from softplot.marks.template import fiducial_shape
from softplot.marks.validation import validate_pattern

__all__ = ["detect_fiducials", "layout_turns", "match_pattern"]

MAX_ROT_DEG = 12.0


def _rot(theta):
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def _film_to_pix_linear(k, theta):
    """Linear part film mm -> pixel for scale k (px/mm) and pixel-system angle theta."""
    return k * _rot(theta) @ np.diag([1.0, -1.0])


def match_pattern(film, cands: WindowCandidates, k_nom, theta0, scale_tol, sign):
    """Best similarity film -> pixel explaining most fiducials with candidates of ``sign``.

    ``film`` (N, 2) mm; ``k_nom`` px/mm and ``theta0`` (radians, pixel system) the expected
    scale and rotation. Returns ``((count, summed score), pick, Lm, t, k, theta)`` (``pick``
    (N,) each mark's candidate among those of ``sign``, -1 for none; ``Lm`` (2, 2), ``t`` (2,)
    film mm -> pixel) or None.
    """
    n = len(film)
    best = None
    c_xy, c_sc = zip(*(cands.of_sign(i, sign) for i in range(n)), strict=True)
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


def _fiducial_factor(fids, ppm: float, npix: int) -> int:
    """Overview factor: the finest feature (a stroke, a centre dot, a fifth of a dot) about
    1.2 overview px, and an overview of at most ~12 Mpx."""
    def feature(f):
        if f.shape == "dot":
            return f.size_mm / 5.0
        if f.shape == "circle-dot":
            return min(f.line_width_mm, f.dot_mm)
        return f.line_width_mm

    F = max(1, int(min(feature(f) for f in fids) * ppm / 1.2))
    while npix / (F * F) > 12e6:
        F += 1
    return F


def _check_size(sc, cam, film, dpi, name) -> None:
    """A scan smaller than half the fiducial pattern is refused."""
    ppm = dpi / MM_PER_INCH
    span = film.max(0) - film.min(0) if len(film) > 1 else np.array([1.0, 1.0])
    need = 0.5 * span * ppm
    if sc.width < need[0] or sc.height < need[1]:
        raise DetectionError(
            f"{name}: scan of {sc.width}x{sc.height} px is much smaller than the {cam.name} "
            f"fiducial pattern at {dpi:.0f} dpi (expected about {span[0] * ppm:.0f}x"
            f"{span[1] * ppm:.0f} px or more)")


def _candidates(sc, cam, ov, film, ppm, theta0, scale_tol, blur_px, signs):
    """Stage 2: each fiducial's window around its position predicted with the film centre at
    the scan centre, and the NCC peaks in it."""
    F = ov.factor
    centre = np.array([(sc.width - 1) / 2.0, (sc.height - 1) / 2.0])
    Lm0 = _film_to_pix_linear(ppm, theta0)
    pred = film @ Lm0.T + centre
    margin = max(abs(sc.width - cam.format_mm[0] * ppm), abs(sc.height - cam.format_mm[1] * ppm))
    radius = (0.5 * margin + 10.0 * ppm
              + np.hypot(*film.T).max() * ppm * (np.sin(np.radians(MAX_ROT_DEG)) + scale_tol))
    shapes = [fiducial_shape(fd, ppm / F) for fd in cam.fiducials]
    return window_candidates(ov, shapes, pred, radius, blur_px, signs)


def _pattern(cam, name, film, cands, ppm, theta0, scale_tol, signs, span):
    """Stage 3: the best pattern match over the signs; too few fiducials in it is an error."""
    n = len(film)
    best = None
    for sg in signs:
        b = match_pattern(film, cands, ppm, theta0, scale_tol, sg)
        if b is not None and (best is None or b[0] > best[0][0]):
            best = (b, sg)
    need_n = _need(n)
    if best is None or best[0][0][0] < need_n:
        found = 0 if best is None else best[0][0][0]
        raise DetectionError(
            f"{name}: fiducial marks not found: expected {n} {cam.name} fiducials "
            f"({', '.join(sorted({f.shape for f in cam.fiducials}))}) about {span[0]:.0f} mm "
            f"apart, found {found} in the expected pattern")
    return best


def _need(n: int) -> int:
    """The fiducials a result needs of ``n``."""
    return min(n, 2) if n <= 3 else 3


def detect_fiducials(sc, cam, *, name, dpi, polarity, rotate, blur_px, rules) -> Detection:
    """Fiducial-mark detection (see the module docstring); same result type as reseau."""
    t0 = time.perf_counter()
    timings: dict = {}
    fids = list(cam.fiducials)
    n = len(fids)
    film = cam.fiducial_film()
    dpi_source = "given" if dpi is not None else ("file" if sc.dpi else "estimated")
    dpi = dpi if dpi is not None else sc.dpi
    scale_tol = 0.06
    if dpi is None:
        dpi = 25.4 * min(sc.width / cam.format_mm[0], sc.height / cam.format_mm[1])
        scale_tol = 0.35
    ppm = dpi / MM_PER_INCH
    span = film.max(0) - film.min(0) if n > 1 else np.array([1.0, 1.0])
    _check_size(sc, cam, film, dpi, name)
    theta0 = np.radians(-float(rotate))
    F = _fiducial_factor(fids, ppm, sc.width * sc.height)
    ov = make_overview(sc, F, ppm, name, compact=False)
    timings["overview"] = time.perf_counter() - t0
    signs = polarity_signs(polarity)
    cands = _candidates(sc, cam, ov, film, ppm, theta0, scale_tol, blur_px, signs)
    (key, pick, Lm, t, k_fit, th), sign = _pattern(cam, name, film, cands, ppm, theta0,
                                                   scale_tol, signs, span)
    timings["pattern"] = time.perf_counter() - t0
    if dpi_source == "estimated":
        dpi = k_fit * MM_PER_INCH
        ppm = k_fit
    c0 = film @ Lm.T + t
    for m in range(n):
        if pick[m] >= 0:
            c0[m] = cands.of_sign(m, sign)[0][pick[m]]
    A0 = np.linalg.inv(Lm @ np.diag([1.0 / ppm, -1.0 / ppm]))
    meas = measure_marks(sc, [fiducial_shape(fd, ppm) for fd in fids], c0, A0,
                         float(blur_px), max(1.0, 0.5 * F + 0.5), sign, rules)
    n_ok = sum(s == "measured" for s in meas.status)
    if n_ok < _need(n):
        raise DetectionError(
            f"{name}: fiducial marks not found: expected {n} {cam.name} fiducials "
            f"({', '.join(sorted({f.shape for f in fids}))}), found {n_ok} that "
            "look like them where the pattern puts them")
    v = validate_pattern(film, meas, Lm, t, ppm)
    timings["total"] = time.perf_counter() - t0
    return _fiducial_detection(sc, cam, name, dpi, dpi_source, sign, film, meas, v, timings)


def _fiducial_detection(sc, cam, name, dpi, dpi_source, sign, film, m, v, timings):
    """The :class:`Detection` of a fiducial scan from the stages' hand-overs."""
    fids = list(cam.fiducials)
    n = len(fids)
    n_ok = sum(s == "measured" for s in m.status)
    warnings: list[str] = []
    if n_ok < n:
        warnings.append(f"{n - n_ok} of {n} fiducials not measured")
    turns = layout_turns(fids)
    if turns:
        warnings.append(
            f"the fiducial layout looks the same turned by {' or '.join(map(str, turns))} "
            "degrees: the marks' names rest on --rotate")
    tr = transform_json(v.H, v.rms, n_ok)
    tr["kind"] = v.kind
    cov = m.cov
    return Detection(
        image=name, camera=cam.name, width=sc.width, height=sc.height, dpi=float(dpi),
        polarity="negative" if sign > 0 else "positive",
        kind=["fiducial"] * n, name=[f.name for f in fids],
        row=np.full(n, -1), col=np.full(n, -1), film=film, xy=m.xy,
        sigma=np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1])),
        sigma_xy=np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], 1)),
        cov=cov,
        score=m.score, cnr=m.cnr, status=m.status, reason=m.reason, transform=tr,
        rms_px=v.rms, residual=v.residual, warnings=warnings, dpi_source=dpi_source,
        timings=timings,
    )
