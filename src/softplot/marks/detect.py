"""``detect``: find and measure every reseau cross and fiducial mark of a scan.

The orchestrator of :mod:`softplot.marks`: it runs the stages in order, each a module with one
hand-over object (pixel system throughout, film mm for the certificate):

1. overview (:mod:`softplot.marks.overview`, :class:`~softplot.marks.overview.ReseauOverview`):
   the scan reduced by an integer factor chosen so that a cross line is about one overview
   pixel wide (built blockwise and kept in the scan's own dtype, no float copy);
2. candidates (:mod:`softplot.marks.candidates`, :class:`~softplot.marks.candidates.Candidates`):
   NCC with a cross template rendered from the certificate at the overview's scale, computed in
   strips of rows (small work buffers); peaks of both signs;
3. lattice and identification (:mod:`softplot.marks.lattice`,
   :class:`~softplot.marks.lattice.Lattice`; :mod:`softplot.marks.grid`): lattice
   scale/rotation/phase, row/col assignment, projective film -> pixel model by RANSAC, for
   each polarity; the better one is the scan's polarity (unless given). With a rotation above
   2 degrees the NCC is repeated with a rotated template;
4. prediction of every cross (model + interpolated residuals of its neighbours), a local search
   in the NCC map, and least-squares template matching at full resolution
   (:mod:`softplot.marks.lsm`) with robust weights, against the scene under each cross as the
   grey opening estimates it (:func:`softplot.marks.measure.scene_background`); where the
   scene has sharp edges at the crosses (``scene="auto"``, :func:`_busy_scene`) the fits are
   refitted with the scene estimated jointly with each cross
   (:mod:`softplot.marks.scene_tv`: TV-regularised deconvolution with the fitted cross held,
   then LSM again: twice for every cross, twice more for those still moving);
5. acceptance tests (contrast, correlation, shape, support of each arm): a mark that fails is
   "missing"; crosses whose extent leaves the scan are "missing" (cut) without a fit; crosses
   whose fitted affine departs from their neighbours', or that failed, are refitted with the
   neighbours' affine and blur held (:func:`_shape_from_neighbours`);
6. the global projective model refitted to the measured crosses; a cross whose residual
   departs from its neighbours' (a smooth film deformation moves neighbours alike) by more than
   a robust threshold, or by more than :data:`OUTLIER_K` times what its own sigma and the
   prediction's error lead one to expect (:func:`_departure_model`), is "rejected";
   rejected and refused crosses are fitted again from the
   neighbours' prediction, once without each half-arm (:func:`_rescue`); measured crosses
   that lie farther than :data:`MAX_GRID_RMS_MM` (rms) off any projective grid are not a
   reseau (an error).

Fiducial cameras go through :mod:`softplot.marks.fiducial`.
"""

from __future__ import annotations

import time

import numpy as np
from scipy.optimize import nnls
from scipy.spatial import cKDTree

from softplot.camera import Camera, load_camera
from softplot.errors import SoftplotError
from softplot.marks import coarse, grid
from softplot.marks.candidates import reseau_candidates, search_map
from softplot.marks.common import (
    MM_PER_INCH,
    DetectionError,
    as_scan,
    format_grid_part,
    parse_grid_part,
    polarity_name,
    transform_json,
)
from softplot.marks.fiducial import detect_fiducials
from softplot.marks.geometry import estimate_geometry, width_candidates
from softplot.marks.lattice import estimate_dpi, fit_lattice, turn_template
from softplot.marks.measure import AcceptRules, measure, measure_one_arm, median_blur
from softplot.marks.overview import reseau_overview
from softplot.marks.precision import variance_factor
from softplot.marks.result import Detection
from softplot.marks.template import MarkShape, cross_shape

__all__ = ["detect", "as_scan", "DetectionError", "parse_grid_part", "format_grid_part"]

#: departures from the smooth deformation field below this (film mm) are never outliers on
#: the grid's outline, where the local quadratic extrapolates: it does not follow a 100 um
#: deformation better than a few micrometres there
OUTLIER_FLOOR_MM = 0.0025
#: inside the grid the local cubic follows a 100 um deformation to a few tenths of a
#: micrometre (no false rejection in the sweep down to 0.02 px): floor max(px, film mm)
OUTLIER_FLOOR_INNER = (0.05, 0.0005)
#: a reseau's measured crosses lie within this (film mm, rms) of a projective grid: three
#: times the largest film deformation tested (100 um); more is not a reseau
MAX_GRID_RMS_MM = 0.3
#: a departure from the neighbours' prediction beyond this many times its expected size
#: (:func:`_departure_model`: from the mark's own sigma and the scan's prediction error) is
#: an outlier (for a Gaussian departure a chance of exp(-2.75^2) = 5e-4 per mark)
OUTLIER_K = 2.75
#: the scene models of :func:`detect` (``scene=``)
SCENE_MODELS = ("auto", "opening", "joint")
#: refits with the joint scene estimate (:func:`softplot.marks.measure._refit_scene`; the
#: third and fourth only for the crosses still moving)
JOINT_PASSES = 4
#: ``scene="auto"`` takes the joint scene estimate when at least BUSY_COUNT crosses have a
#: scene edge steeper than BUSY_EDGE x their contrast per px in their footprint. The sweep's
#: smooth textures reach 0.09 at most, its busy scenes 0.18-0.5 (docs/accuracy.md)
BUSY_EDGE = 0.13
BUSY_COUNT = 2
#: a lattice of fewer candidates than this (or the whole grid, when smaller) is not a reseau:
#: a part of 3 x 3 crosses with a few missing still passes
MIN_PART = 6


def _idw(film_all, film_known, val_known, k=4):
    """Inverse-distance interpolation of residual vectors at film points (mm)."""
    if len(film_known) == 0:
        return np.zeros((len(film_all), 2))
    k = min(k, len(film_known))
    d, j = cKDTree(film_known).query(film_all, k=k)
    d = d.reshape(len(film_all), k)
    j = j.reshape(len(film_all), k)
    w = 1.0 / np.maximum(d, 1e-6) ** 2
    return (val_known[j] * w[..., None]).sum(1) / w.sum(1)[:, None]


def detect(
    scan,
    camera: Camera | str,
    *,
    dpi: float | None = None,
    polarity: str = "auto",
    rotate: float = 0.0,
    blur_px: float = 1.0,
    rules: AcceptRules | None = None,
    scene: str = "auto",
    grid_part=None,
) -> Detection:
    """Detect and measure the reseau crosses and fiducial marks of a scan.

    Parameters
    ----------
    scan : Scan, path or ndarray
        The scan (pixel system).
    camera : Camera or str
        Certificate (built-in name, TOML path or Camera).
    dpi : float, optional
        Scan resolution; default the file's, else estimated from the image.
    polarity : {"auto", "positive", "negative"}
        "positive": dark marks on a bright background (a print); "negative": bright marks
        (a film negative). "auto" decides from the image.
    rotate : float
        Coarse rotation of the photo in the scan (0, 90, 180, 270 degrees, counter-clockwise
        on screen, as the synthetic scanner's ``rotation_deg``). Residual rotations of
        +-20 degrees around it are found automatically.
    blur_px : float
        Expected scanner blur sigma (px), only the LSM starting value.
    rules : AcceptRules, optional
        Acceptance thresholds.
    scene : {"auto", "opening", "joint"}
        The scene under each cross: "opening" the grey opening's estimate
        (:func:`softplot.marks.measure.scene_background`); "joint" also refitted with the
        scene estimated jointly with the cross (:mod:`softplot.marks.scene_tv`); "auto"
        the joint estimate where the scene has sharp edges near the crosses.
    grid_part : str, mapping or tuple, optional
        The part of the reseau the scan shows, when the user knows it (e.g.
        ``"cols=0:12,rows=0:6"``, :func:`parse_grid_part`): rows and columns are named within
        it. By default any connected part of at least 3 x 3 crosses is found and named from
        the format's edges the scan shows.

    Returns
    -------
    Detection
    """
    t0 = time.perf_counter()
    cam = load_camera(camera)
    sc = as_scan(scan, dpi=dpi)
    if scene not in SCENE_MODELS:
        raise SoftplotError(f"scene must be {', '.join(SCENE_MODELS)}, got {scene!r}")
    if polarity not in ("auto", "positive", "negative"):
        raise SoftplotError(f"polarity must be auto, positive or negative, got {polarity!r}")
    name = sc.path.name if sc.path is not None else "<array>"
    if cam.reseau is None:
        if grid_part is not None:
            raise SoftplotError(f"--grid-part: camera {cam.name} has fiducial marks, no reseau")
        return detect_fiducials(sc, cam, name=name, dpi=dpi, polarity=polarity, rotate=rotate,
                                blur_px=blur_px, rules=rules)
    part = parse_grid_part(grid_part, cam.reseau.rows, cam.reseau.cols)
    try:
        return _detect_reseau(sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0, scene,
                              part)
    except DetectionError as first:
        if polarity == "auto":
            raise
        # a polarity given by the user that the scan contradicts: say so, in one line
        other = "negative" if polarity == "positive" else "positive"
        try:
            det = _detect_reseau(sc, cam, name, dpi, other, rotate, blur_px, rules, t0, scene,
                                 part)
        except DetectionError:
            raise first from None
        n = int(det.measured.sum())
        raise DetectionError(
            f"{name}: no reseau found with --polarity {polarity}: the scan's crosses are "
            f"{other} ({n} found, {'bright' if other == 'negative' else 'dark'} marks); "
            f"give --polarity {other} or auto") from None


def _detect_reseau(sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0,
                   scene="auto", part=None) -> Detection:
    res = cam.reseau
    warnings: list[str] = []
    timings: dict = {}
    rotate_pix = -float(rotate)  # pixel-system angle of film +x (clockwise on screen)
    dpi_source = "given" if dpi is not None else ("file" if sc.dpi else "estimated")
    dpi = dpi if dpi is not None else sc.dpi
    span_mm = ((res.cols - 1) * res.pitch_x + res.arm_length_mm,
               (res.rows - 1) * res.pitch_y + res.arm_length_mm)

    if dpi is None:
        # the scan holds the reseau: a first guess from its size, refined from the spacing
        dpi = estimate_dpi(sc, cam, polarity, rotate_pix, name)
    ppm = dpi / MM_PER_INCH
    # a part of the grid is enough: the scan must hold 3 x 3 crosses (or the whole grid, when
    # smaller), in either orientation (a quarter turn)
    part_mm = ((min(res.cols, 3) - 1) * res.pitch_x + res.arm_length_mm,
               (min(res.rows, 3) - 1) * res.pitch_y + res.arm_length_mm)
    need = sorted((part_mm[0] * ppm * 0.9, part_mm[1] * ppm * 0.9))
    have = sorted((sc.width, sc.height))
    if have[0] < need[0] or have[1] < need[1]:
        raise DetectionError(
            f"{name}: scan of {sc.width}x{sc.height} px is much smaller than the "
            f"{cam.name} reseau at {dpi:.0f} dpi (expected about "
            f"{span_mm[0] * ppm:.0f}x{span_mm[1] * ppm:.0f} px, and at least "
            f"{part_mm[0] * ppm:.0f}x{part_mm[1] * ppm:.0f} px for a part of 3x3 crosses)")
    shape = cross_shape(cam, ppm)
    ov = reseau_overview(sc, shape.width, ppm, name)
    f = ov.factor
    timings["overview"] = time.perf_counter() - t0
    cands = reseau_candidates(sc, ov, cam, polarity, blur_px)
    lat = fit_lattice(sc, ov, cands, cam, polarity, rotate_pix, part)
    del cands
    if lat is None:
        raise DetectionError(
            f"{name}: no reseau found: expected a {res.rows}x{res.cols} grid of crosses at "
            f"{res.pitch_x}x{res.pitch_y} mm ({res.pitch_x * ppm:.0f} px at {dpi:.0f} dpi), "
            "found no regular pattern of cross-like marks")
    # repeat the correlation with the template turned like the grid (when it is turned)
    lat = turn_template(lat, sc, ov, cam, rotate_pix, blur_px, part)
    g, sign = lat.grid, lat.sign
    timings["grid"] = time.perf_counter() - t0
    n_assigned = len(g.node)
    if n_assigned < min(MIN_PART, res.count):
        raise DetectionError(
            f"{name}: no reseau found: expected {res.rows}x{res.cols} crosses at "
            f"{res.pitch_x}x{res.pitch_y} mm, found only {n_assigned} on a lattice")

    # --- prediction of every cross ---------------------------------------------------------
    film = res.film()
    N = res.count
    pred = grid.apply_h(g.H, film)
    cand_xy = lat.assigned_xy()
    resid = cand_xy - grid.apply_h(g.H, film[g.node])
    pred = pred + _idw(film, film[g.node], resid)
    # local search in the NCC map around each prediction
    spread = float(np.sqrt(np.mean(np.sum(resid**2, 1)))) if len(resid) else 3.0
    radius_ov = max(2.0, (2.0 * spread + 2.0) / f)
    found_ov, val = search_map(lat.ncc, lat.half, sign, coarse.full_to_ov(pred, f), radius_ov)
    del ov, lat  # the overview and the NCC map are not needed any more: free them
    use = np.isfinite(found_ov).all(1) & (val >= 0.3)
    c0 = np.where(use[:, None], coarse.ov_to_full(found_ov, f), pred)
    # affine of every cross: pixel -> mark frame (u along film x, v along film -y, nominal px)
    Jh = grid.h_jacobian(g.H, film)  # d pixel / d film mm
    A0 = np.linalg.inv(Jh @ np.diag([1.0 / ppm, -1.0 / ppm]))
    # the crosses' real size, measured on the ones the lattice found (the certificate's is a
    # starting guess only)
    prof = np.where(use)[0]
    geom = estimate_geometry(sc.grey, c0[prof], A0[prof], shape, sign,
                             pitch_px=min(res.pitch_x, res.pitch_y) * ppm, score=val[prof])
    s0 = float(np.hypot(blur_px, np.sqrt(1.0 / 12.0)))
    init_err = max(0.75, 0.5 * f + 0.25)
    timings["profiles"] = time.perf_counter() - t0
    widths = width_candidates(geom, shape.width)
    if len(widths) > 1:
        # the profiles contradict the guess: the least-squares fit of the best crosses decides
        trial = prof[np.argsort(-val[prof])[:8]]
        scores = []
        for w in widths:
            ft = measure(sc, MarkShape("cross", length=geom.arm_px, width=w), c0[trial],
                         A0[trial], s0, init_err, sign, rules, anchor=pred[trial],
                         max_shift=radius_ov * f + 1.0)
            scores.append(float(np.mean(np.where(ft.ok, ft.score, 0.0))))
        geom = geom.with_width(widths[int(np.argmax(scores))])
    else:
        geom = geom.with_width(widths[0])
    shape = geom.shape()
    timings["geometry"] = time.perf_counter() - t0

    # crosses whose extent leaves the scan are cut: never fitted
    ext = 0.5 * shape.length + 0.5 * shape.width
    tips = np.stack([pred + ext * Jh[:, :, 0] / ppm * sgn for sgn in (1, -1)]
                    + [pred + ext * Jh[:, :, 1] / ppm * sgn for sgn in (1, -1)], 1)
    tips = np.concatenate([tips, pred[:, None, :] + 0.0], 1)
    inside = ((tips[..., 0] >= 0.5) & (tips[..., 0] <= sc.width - 1.5)
              & (tips[..., 1] >= 0.5) & (tips[..., 1] <= sc.height - 1.5)).all(1)
    on_img = ((pred[:, 0] >= 0) & (pred[:, 0] <= sc.width - 1)
              & (pred[:, 1] >= 0) & (pred[:, 1] <= sc.height - 1))
    timings["predict"] = time.perf_counter() - t0

    idx = np.where(inside)[0]
    # "auto": the joint scene where the first pass sees sharp scene edges at the crosses
    fine = measure(sc, shape, c0[idx], A0[idx], s0, init_err, sign, rules, anchor=pred[idx],
                   max_shift=radius_ov * f + 1.0,
                   scene_tv=JOINT_PASSES if scene == "joint" else 0,
                   auto_tv=JOINT_PASSES if scene == "auto" else 0, busy=_busy_scene)
    tv = fine.scene_tv
    _shape_from_neighbours(sc, shape, film[idx], c0[idx], pred[idx], fine, s0, init_err, sign,
                           rules, radius_ov * f + 1.0, ppm, scene_tv=tv)
    _other_sizes(sc, shape, c0[idx], A0[idx], pred[idx], fine, s0, init_err, sign, rules,
                 radius_ov * f + 1.0, scene_tv=tv)
    timings["lsm"] = time.perf_counter() - t0

    xy = np.full((N, 2), np.nan)
    cov = np.full((N, 2, 2), np.nan)
    cov_w = np.full((N, 2, 2), np.nan)  # independent pixels: the outlier tests' precision
    score = np.full(N, np.nan)
    cnr = np.full(N, np.nan)
    status = ["missing"] * N
    reason = ["outside the scan" if not on_img[i] else "cut by the scan edge" for i in range(N)]
    for k, i in enumerate(idx):
        score[i] = fine.score[k]
        cnr[i] = fine.cnr[k]
        if fine.ok[k]:
            xy[i] = fine.xy[k]
            cov[i], cov_w[i] = fine.cov[k], fine.cov_white[k]
            status[i] = "measured"
            reason[i] = ""
        else:
            reason[i] = fine.reason[k] or "not found"

    sigma = np.sqrt(0.5 * (cov_w[:, 0, 0] + cov_w[:, 1, 1]))
    floor_px = np.where(_outline(film, np.array(status) == "measured"),
                        max(0.1, OUTLIER_FLOOR_MM * ppm),
                        max(OUTLIER_FLOOR_INNER[0], OUTLIER_FLOOR_INNER[1] * ppm))
    Hm, residual, rms, dep = _reject_outliers(film, xy, status, reason, g.H, sigma,
                                              floor_px=floor_px)
    A_fit = A0.copy()
    A_fit[idx] = np.where(np.isfinite(fine.A), fine.A, A0[idx])
    fitted = np.zeros(N, bool)
    fitted[idx] = True
    if _rescue(sc, shape, film, xy, (cov, cov_w), status, reason, Hm, sigma, floor_px, A_fit,
               s0, init_err, sign, rules, radius_ov * f + 1.0, ppm, scene_tv=tv,
               blur=_held_blur(fine), fitted=fitted, departure=dep):
        sigma = np.sqrt(0.5 * (cov_w[:, 0, 0] + cov_w[:, 1, 1]))
        Hm, residual, rms, _ = _reject_outliers(film, xy, status, reason, Hm, sigma,
                                                floor_px=floor_px)
    arms = np.where(np.array(status) == "measured", 2, 0)
    _lone_arms(sc, shape, film, xy, (cov, cov_w), status, reason, arms, Hm, sigma, A_fit, s0,
               sign, rules, radius_ov * f + 1.0, fitted, _held_blur(fine), fine, ppm)
    if (arms == 1).any():
        residual[arms == 1] = xy[arms == 1] - grid.apply_h(Hm, film[arms == 1])
    # the errors the crosses' own fits cannot see, from their departures from each other
    two = arms == 2
    vfac = variance_factor(film[two], residual[two], cov[two], _local_prediction, ppm)
    cov = cov * vfac
    rows_cols = res.row_col()
    sig_xy = np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], 1))
    n_meas = sum(s == "measured" for s in status)
    if n_meas < min(4, res.count):
        # a lattice of candidates was found, but the crosses do not hold up at full
        # resolution (scene texture, the wrong polarity or the wrong camera)
        raise DetectionError(
            f"{name}: no reseau found: expected a {res.rows}x{res.cols} grid of "
            f"{polarity_name(sign)} crosses at {res.pitch_x}x{res.pitch_y} mm, measured only "
            f"{n_meas} of the {len(idx)} inside the scan")
    if rms > MAX_GRID_RMS_MM * ppm:
        # measured, but not on a grid: fits to scene content (e.g. the wrong polarity over a
        # busy scene), not a reseau deformed by at most a tenth of a millimetre
        raise DetectionError(
            f"{name}: no reseau found: expected a {res.rows}x{res.cols} grid of "
            f"{polarity_name(sign)} crosses at {res.pitch_x}x{res.pitch_y} mm, the {n_meas} "
            f"measured lie {rms:.1f} px (rms) off any projective grid (at most "
            f"{MAX_GRID_RMS_MM * ppm:.1f} px, {MAX_GRID_RMS_MM} mm, for a reseau)")
    if n_meas < N:
        warnings.append(f"{N - n_meas} of {N} crosses not measured")
    if g.ambiguous:
        warnings.append("the scan shows a part of the grid that could be several (no edge of "
                        "the format decides): rows and columns are named as if the scan were "
                        "centred on the format")
    if n_meas < 0.2 * len(idx):
        # never thrown away for being few: returned, with the warning
        warnings.append(f"only {n_meas} of the {len(idx)} crosses inside the scan measured: "
                        "check the camera, --polarity and --dpi")
    timings["total"] = time.perf_counter() - t0
    return Detection(
        image=name,
        camera=cam.name,
        width=sc.width,
        height=sc.height,
        dpi=float(dpi),
        polarity=polarity_name(sign),
        kind=["reseau"] * N,
        name=res.names(),
        row=rows_cols[:, 0].astype(int),
        col=rows_cols[:, 1].astype(int),
        film=film,
        xy=xy,
        sigma=np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1])),
        sigma_xy=sig_xy,
        cov=cov,
        score=score,
        cnr=cnr,
        status=status,
        reason=reason,
        transform=transform_json(Hm, rms, n_meas),
        rms_px=rms,
        residual=residual,
        warnings=warnings,
        dpi_source=dpi_source,
        timings=timings,
        scene="joint" if tv else "opening",
        mark_geometry=geom.to_json(ppm),
        arms=arms,
        variance_factor=vfac,
    )


def _lone_arms(sc, shape, film, xy, cov, status, reason, arms, Hm, sigma, A, s0, sign, rules,
               max_shift, fitted, blur, fine, ppm):
    """Crosses fitted but not measured (missing or rejected), measured again as a lone bar
    (:func:`softplot.marks.measure.measure_one_arm`): from the position and with the affine
    their neighbours predict; along the bar the position is that prediction, with the
    per-axis RMS of the measured crosses' departures from their neighbours' (leave-one-out)
    predictions as its standard deviation, at least :data:`LONE_ARM_ALONG_MIN_PX`. The
    bar's contrast to noise must be at least half the measured crosses' median. ``cov``:
    the reported and the independent-pixel covariances. Modifies the arrays in place
    (``arms`` 1 where a bar was measured)."""
    st = np.array(status)
    q = np.where(((st == "missing") | (st == "rejected")) & np.asarray(fitted, bool))[0]
    meas = np.where(st == "measured")[0]
    if q.size == 0 or meas.size < 8 or shape.kind != "cross":
        return
    r = xy - grid.apply_h(Hm, film)
    target = grid.apply_h(Hm, film[q]) + _local_fit(film[q], film[meas], r[meas], 16, 2,
                                                     n_sigma=sigma[meas])
    loo = r[meas] - _local_prediction(film[meas], r[meas], sigma=sigma[meas])
    along = max(float(np.sqrt(np.mean(loo**2))), LONE_ARM_ALONG_MIN_PX)
    held, _ = _position_affine(film, xy, st == "measured", ppm)
    Aq = np.where(np.isfinite(held[q]).all((1, 2))[:, None, None], held[q], A[q])
    cnr_ref = float(np.median(fine.cnr[fine.ok])) if fine.ok.any() else None
    f1 = measure_one_arm(sc, shape, target, Aq, s0, sign, rules, max_shift=max_shift,
                         along_sd=along, blur=blur, cnr_ref=cnr_ref)
    for j, i in enumerate(q):
        if f1.ok[j]:
            xy[i], cov[0][i], cov[1][i] = f1.xy[j], f1.cov[j], f1.cov_white[j]
            status[i], reason[i], arms[i] = "measured", "", 1


#: the least standard deviation (px) of a lone bar's position along it (the prediction's)
LONE_ARM_ALONG_MIN_PX = 0.5


def _busy_scene(edge: np.ndarray) -> bool:
    """Whether the scene has sharp edges at the crosses: at least :data:`BUSY_COUNT` (accepted)
    crosses whose footprint holds a scene edge steeper than :data:`BUSY_EDGE` times their contrast
    per px (:func:`softplot.marks.measure._footprint_gradient`)."""
    e = np.asarray(edge, float)
    return int(np.sum(np.isfinite(e) & (e > BUSY_EDGE))) >= BUSY_COUNT


def _position_affine(film, xy, ok, ppm, k=24):
    """Each mark's pixel -> mark-frame affine predicted from its neighbours' positions.

    The affine of a mark is the local Jacobian of the film mm -> pixel mapping (film
    deformation and scanner) in the mark frame (u along film x, v along film -y, nominal px,
    as ``A0``): here the derivative of a local cubic (:func:`_local_fit`) through the
    measured pixel positions ``xy`` (M, 2) of the ``k`` nearest accepted marks (``ok`` (M,)),
    the mark itself left out. The positions are the most precise thing the detector measures
    (a Rollei's neighbours are 5 mm apart, the arms 0.8 mm long): a cubic follows a 100 um
    deformation to about 5e-5, where a plane through even the exact affines of the
    neighbours misses it by about 4e-4
    (``tests/test_marks_units.py::test_affine_from_neighbour_positions_follows_a_strong_deformation``).

    Returns
    -------
    A : (M, 2, 2)
        Predicted affines (NaN where fewer than 4 marks are accepted).
    lev : (M,)
        Variance factor of each prediction's Jacobian for unit position noise (px^2 / mm^2):
        large where the neighbours lie to one side (corners, edges).
    """
    good = np.where(ok & np.isfinite(xy).all(1))[0]
    M = len(film)
    if good.size < 4:
        return np.full((M, 2, 2), np.nan), np.full(M, np.nan)
    _, grad, lev = _local_fit(film, film[good], xy[good], k, degree=3, gradient=True)
    J = grad @ np.diag([1.0 / ppm, -1.0 / ppm])
    # 2 x 2 inverses by hand: a degenerate neighbourhood (collinear marks: a Jacobian near
    # singular, |det| ~ 1 otherwise) gives NaN, not an exception
    det = J[:, 0, 0] * J[:, 1, 1] - J[:, 0, 1] * J[:, 1, 0]
    adj = np.stack([np.stack([J[:, 1, 1], -J[:, 0, 1]], -1),
                    np.stack([-J[:, 1, 0], J[:, 0, 0]], -1)], -2)
    with np.errstate(all="ignore"):
        A = adj / det[:, None, None]
    A[~np.isfinite(A).all((1, 2)) | (np.abs(det) < 1e-6)] = np.nan
    return A, lev


def _shape_from_neighbours(sc, shape, film, c0, pred, fine, s0, init_err, sign, rules,
                           max_shift, ppm, z_max=2.5, scene_tv=0):
    """Refit marks whose shape was pulled by the scene, with the shape of their neighbours.

    A cross's affine (scale, rotation, shear of the film and scanner at that place) varies
    smoothly over the film, so its neighbours' positions predict it
    (:func:`_position_affine`). A scene edge along one half-arm pulls that half, and a free
    affine absorbs the pull by turning that bar, which hides it from LSM's half-arm test.
    So each element of the fitted affine is compared with the prediction: where one departs
    from it by more than ``z_max`` times the robust spread of that element's departures over
    all accepted marks (scaled by the prediction's own variance factor, larger at the grid's
    outline), or where the mark was not accepted, the mark is fitted again with the predicted
    affine held (the half-arm test then sees a pulled half and drops it), and the blur held
    at the accepted marks' median (:func:`_held_blur`); the refit replaces the first when
    accepted. The spread adapts to the scan: where the prediction is the
    weaker of the two (a 100 um deformation at 2400 dpi, low noise) only the marks the scene
    really pulled stand out. Modifies ``fine`` in place.
    """
    cons, lev = _position_affine(film, fine.xy, fine.ok, ppm)
    have = np.isfinite(cons).all((1, 2))
    fin = have & np.isfinite(fine.A).all((1, 2))
    ref = fin & fine.ok
    z = np.full(len(film), np.inf)
    if ref.sum() >= 4:
        dth = np.full((len(film), 4), np.nan)
        dth[fin] = (fine.A[fin] - cons[fin]).reshape(-1, 4)
        med = np.median(dth[ref], axis=0)
        spread = 1.4826 * np.median(np.abs(dth[ref] - med), axis=0) + 1e-9
        scale = spread * np.sqrt(lev / np.median(lev[ref]))[:, None]
        z[fin] = np.max(np.abs(dth[fin] - med) / scale[fin], axis=1)
    redo = np.where(have & (~fine.ok | (z > z_max)))[0]
    if redo.size == 0:
        return
    start = np.where(fine.ok[redo, None], fine.xy[redo], c0[redo])
    blur = _held_blur(fine)
    f2 = measure(sc, shape, start, cons[redo], s0, init_err, sign, rules, anchor=pred[redo],
                 max_shift=max_shift, fit_shape=False, scene_tv=scene_tv, blur=blur)
    # of two accepted fits of one mark, keep the one that agrees better with its neighbours:
    # the outlier test's leave-one-out prediction of its residual against a projective model
    both = fine.ok[redo] & f2.ok
    if both.any() and fine.ok.sum() >= 8:
        m = np.where(fine.ok)[0]
        Hm = grid.projective_fit(film[m], fine.xy[m])
        near = _local_prediction(film[m], fine.xy[m] - grid.apply_h(Hm, film[m]))
        k = redo[both]
        at = grid.apply_h(Hm, film[k]) + near[np.searchsorted(m, k)]
        worse = np.hypot(*(f2.xy[both] - at).T) > np.hypot(*(fine.xy[k] - at).T)
        f2.ok[np.where(both)[0][worse]] = False
    for j, i in enumerate(redo):
        if f2.ok[j]:
            fine.xy[i], fine.cov[i], fine.A[i], fine.s[i] = f2.xy[j], f2.cov[j], cons[i], f2.s[j]
            fine.cov_white[i] = f2.cov_white[j]
            fine.score[i], fine.cnr[i], fine.ok[i], fine.reason[i] = (
                f2.score[j], f2.cnr[j], True, "")


def _other_sizes(sc, shape, c0, A0, pred, fine, s0, init_err, sign, rules, max_shift,
                 scene_tv=0, steps=(0.5, 2.5)):
    """Measure crosses of another size than the others (a larger centre cross) with their own.

    A cross refused as "wrong size" had its fitted affine scale the mark by ``k`` (the square
    root of the determinants' ratio, fitted over predicted ``A0``); when ``k`` lies within
    ``steps`` it is fitted again with the shape scaled by ``k`` (arms and lines) from its
    fitted centre (else ``c0``) and the predicted affine, and an accepted fit replaces the
    refusal. Modifies ``fine`` in place."""
    if fine.A is None:
        return
    bad = np.array([not o and r == "wrong size" for o, r in zip(fine.ok, fine.reason,
                                                                   strict=True)])
    bad &= np.isfinite(fine.A).all((1, 2))
    if not bad.any():
        return
    k = np.sqrt(np.abs(np.linalg.det(A0[bad])) / np.maximum(np.abs(np.linalg.det(fine.A[bad])),
                                                              1e-12))
    idx = np.where(bad)[0][(k >= steps[0]) & (k <= steps[1])]
    k = k[(k >= steps[0]) & (k <= steps[1])]
    # one fit per size class (scales rounded to a tenth)
    for kk in np.unique(np.round(k, 1)):
        grp = idx[np.round(k, 1) == kk]
        big = MarkShape("cross", length=shape.length * kk, width=shape.width * kk)
        start = np.where(np.isfinite(fine.xy[grp]).all(1, keepdims=True), fine.xy[grp], c0[grp])
        f2 = measure(sc, big, start, A0[grp], s0 * max(kk, 1.0), init_err, sign, rules,
                     anchor=pred[grp], max_shift=max_shift, scene_tv=scene_tv)
        for j, i in enumerate(grp):
            if f2.ok[j]:
                fine.xy[i], fine.cov[i], fine.A[i] = f2.xy[j], f2.cov[j], f2.A[j]
                fine.score[i], fine.cnr[i], fine.ok[i], fine.reason[i] = (
                    f2.score[j], f2.cnr[j], True, "")
                if fine.s is not None and f2.s is not None:
                    fine.s[i] = f2.s[j]
                for extra in ("cov_white", "arms"):
                    a, b = getattr(fine, extra, None), getattr(f2, extra, None)
                    if a is not None and b is not None:
                        a[i] = b[j]


def _held_blur(fine) -> float | None:
    """The blur (px) that refits and rescues hold (:func:`softplot.marks.measure.median_blur`
    of the accepted marks)."""
    return median_blur(fine.s, fine.ok) if fine.s is not None else None


def _local_fit(q_film, n_film, n_val, k_max=16, degree=2, n_sigma=None, n_dev=None,
               gradient=False):
    """Values at query points from a weighted local polynomial through their neighbours.

    For each query point (``q_film`` (Q, 2) mm) a polynomial in film mm (plane for
    ``degree=1``; quadratic for ``degree=2`` when at least 9 neighbours; cubic for
    ``degree=3`` when at least 16, else quadratic) is fitted to the values ``n_val`` (M, C)
    of its ``k`` nearest neighbours ``n_film`` (M, 2), the query point itself left out, with
    weights ``1/(1 + d^2)`` (``d`` in units of the median neighbour spacing), lowered for
    imprecise neighbours (``n_sigma`` (M,), against the typical one) and for neighbours far
    from their own prediction (``n_dev`` (M,), against 3x its robust spread).

    Returns (Q, C); with ``gradient`` also the polynomial's gradient at each query point
    (Q, C, 2) (value units per mm) and the variance factor of that gradient (Q,) (its two
    components' variances summed, for unit noise on the values; per mm^2).
    """
    n_val = np.asarray(n_val, float).reshape(len(n_film), -1)
    k = min(k_max, len(n_film) - 1)
    d, j = cKDTree(n_film).query(q_film, k=k + 1)
    # leave the query point out (a zero-distance match), else the farthest neighbour
    drop = np.where(d[:, 0] < 1e-9, 0, k)
    keep = np.arange(k + 1)[None, :] != drop[:, None]
    d = d[keep].reshape(-1, k)
    j = j[keep].reshape(-1, k)
    unit = float(np.median(d[:, 0])) or 1.0
    dx = (n_film[j] - np.asarray(q_film)[:, None, :]) / unit  # (Q, k, 2)
    X, Y = dx[..., 0], dx[..., 1]
    cols = [np.ones(d.shape), X, Y]
    if degree >= 2 and k >= 9:
        cols += [X**2, X * Y, Y**2]
    if degree >= 3 and k >= 16:
        cols += [X**3, X**2 * Y, X * Y**2, Y**3]
    D = np.stack(cols, -1)  # (Q, k, p)
    w = 1.0 / (1.0 + (d / unit) ** 2)
    if n_sigma is not None:
        sg = np.nan_to_num(np.asarray(n_sigma, float), nan=1.0)
        w = w / (1.0 + (sg[j] / (float(np.median(sg)) + 1e-6)) ** 2)
    if n_dev is not None:
        spread = 1.4826 * float(np.median(n_dev)) + 1e-12
        w = w / (1.0 + (n_dev[j] / (3.0 * spread)) ** 2)
    # per query the highest degree its neighbours determine (a partial grid of a few rows
    # cannot carry a cubic in y): the terms of a degree whose normal equations are
    # ill-conditioned are dropped for that query; a plane that is not determined (collinear
    # neighbours) gives no gradient (NaN)
    p = D.shape[-1]
    DwT0 = (D * w[..., None]).transpose(0, 2, 1)
    N0 = np.matmul(DwT0, D)
    dg = np.sqrt(np.maximum(np.einsum("qii->qi", N0), 1e-300))
    Nn = N0 / (dg[:, :, None] * dg[:, None, :])  # unit diagonal
    # the leading blocks of Nn are the normalised lower-degree matrices, and no eigenvalue of
    # a principal submatrix lies below the smallest of the whole (Cauchy interlacing): where
    # the full degree is well conditioned every lower one is, and only the rest are tested
    level = np.zeros(len(d), int)  # terms used: 3 plane, 6 quadratic, 10 cubic (0: none)
    full = np.linalg.eigvalsh(Nn)[:, 0] > 1e-6
    level[full] = p
    rest = np.where(~full)[0]
    lev_r = np.zeros(rest.size, int)
    below = 0
    for L in (3, 6, 10):
        if L >= p or rest.size == 0:
            break
        lam = np.linalg.eigvalsh(Nn[rest, :L, :L])[:, 0]
        lev_r = np.where((lam > 1e-6) & (lev_r == below), L, lev_r)
        below = L
    level[rest] = lev_r
    # the dropped terms' rows and columns of the normal equations are 0 (their coefficients
    # 0): masks of N0 and of the weighted design, no second product
    use = (np.arange(p)[None, :] < np.maximum(level, 3)[:, None]).astype(float)  # (Q, p)
    DwT = DwT0 * use[:, :, None]
    N = N0 * (use[:, :, None] * use[:, None, :]) + 1e-9 * np.eye(p)
    N[:, np.arange(p), np.arange(p)] += 1.0 - use
    coef = np.linalg.solve(N, np.matmul(DwT, n_val[j]))  # (Q, p, C)
    if not gradient:
        return coef[:, 0, :]
    Ni = np.linalg.inv(N)
    var = Ni @ np.matmul(DwT, DwT.transpose(0, 2, 1)) @ Ni  # coefficients, unit noise
    grad = np.stack([coef[:, 1, :], coef[:, 2, :]], -1) / unit
    grad[level < 3] = np.nan
    return coef[:, 0, :], grad, (var[:, 1, 1] + var[:, 2, 2]) / unit**2


def _local_prediction(film, r, k_max=16, sigma=None):
    """Leave-one-out prediction of each residual from a local polynomial fit to its neighbours.

    ``film`` (M, 2) mm, ``r`` (M, 2) px. A smooth film deformation is locally quadratic to a
    good approximation (:func:`_local_fit`); inside the grid, where the neighbours surround
    the mark, a local cubic through the 24 nearest follows a 100 um deformation several times
    better (true positions at 2400 dpi: largest departure 0.017 px instead of 0.036 px); on
    the grid's outline, where the fit extrapolates, the quadratic is kept. A second pass
    lowers the weight of neighbours that depart from their own prediction (one bad neighbour
    must not condemn a good mark, at a corner especially). Returns the predicted residuals
    (M, 2).
    """
    pred = _local_fit(film, film, r, k_max, 2, n_sigma=sigma)
    dev = np.hypot(*(r - pred).T)
    out = _local_fit(film, film, r, k_max, 2, n_sigma=sigma, n_dev=dev)
    inner = ~_outline(film)
    if inner.any():
        out[inner] = _local_fit(film[inner], film, r, 24, 3, n_sigma=sigma, n_dev=dev)
    return out


def _outlier_threshold(spread, floor, sigma, expected=None):
    """Largest departure (px) from the neighbours' prediction that is not an outlier:
    ``max(floor, 3 s, min(4.5 s, 4 sigma))`` (``s`` the departures' robust spread, ``sigma``
    the mark's own precision); with ``expected`` (px, the departure's expected size for that
    mark, :func:`_departure_model`) at most ``max(floor, OUTLIER_K x expected)``: a precise
    mark among imprecise ones is held to its own precision. The outlier test and the rescue
    share it. Arrays of one value per mark (or scalars)."""
    thr = np.maximum(np.maximum(3.0 * spread, floor), np.minimum(4.5 * spread, 4.0 * sigma))
    if expected is None:
        return thr
    return np.minimum(thr, np.maximum(floor, OUTLIER_K * expected))


def _departure_model(dev, sigma, edge, iterations=6):
    """Coefficients of the expected squared departure of a mark from its neighbours'
    prediction, ``a sigma^2 + b``: ``a`` scales the mark's own variance (``sigma`` px from LSM,
    which a busy scene makes optimistic), ``b`` (px^2) is what every mark shares (the
    prediction's error: its neighbours' noise and the deformation the local polynomial does
    not follow).

    ``dev`` (M,) px departures, ``sigma`` (M,) px, ``edge`` (M,) bool (the grid's outline,
    extrapolated: its own ``a, b`` when both it and the inside have 8 marks or more). Fitted
    by non-negative least squares on ``dev^2``, weighted by the model's inverse square (the
    variance of a squared Gaussian departure grows with its mean); departures beyond 3 times
    the model's size are left out and the fit repeated. On a clean scan ``b`` dominates and
    the test is the spread's; over a busy scene it holds a precise cross to its own sigma.
    Returns (2, 2): rows outline, inside; columns ``a``, ``b``
    (:func:`_expected_departure` evaluates it).
    """
    d2 = np.asarray(dev, float) ** 2
    s2 = np.nan_to_num(np.asarray(sigma, float), nan=1.0) ** 2
    edge = np.asarray(edge, bool)
    def fit(d2, s2):
        a, b = 1.0, float(np.median(d2)) + 1e-12
        for _ in range(iterations):
            mod = a * s2 + b
            keep = d2 <= 9.0 * mod
            if keep.sum() < 2:
                break
            wt = 1.0 / np.maximum(mod[keep], 1e-24)
            M = np.stack([s2[keep], np.ones(int(keep.sum()))], 1) * wt[:, None]
            (a, b), _ = nnls(M, d2[keep] * wt)
            b = max(float(b), 1e-12)
        return a, b

    if min(edge.sum(), (~edge).sum()) >= 8:
        return np.array([fit(d2[edge], s2[edge]), fit(d2[~edge], s2[~edge])])
    return np.tile(fit(d2, s2), (2, 1))  # too few in a group: one model for both


def _expected_departure(coef, sigma, edge):
    """Expected departure (px) of marks with precision ``sigma`` (px) on the outline
    (``edge`` True) or inside the grid, from :func:`_departure_model`'s ``coef``."""
    c = coef[np.where(np.asarray(edge, bool), 0, 1)]
    sg = np.nan_to_num(np.asarray(sigma, float), nan=1.0)
    return np.sqrt(c[..., 0] * sg**2 + c[..., 1])


def _spread(dev, edge):
    """Robust spread (1.4826 x median) of departures, separately for the grid's outline."""
    spread = np.full(len(dev), 1.4826 * np.median(dev))
    for grp in (edge, ~edge):
        if grp.sum() >= 8:
            spread[grp] = 1.4826 * np.median(dev[grp])
    return spread


def _outline(film, present=None):
    """Marks on the outline of the certificate's grid (M,) bool; with ``present`` (M,) bool
    (e.g. the measured marks) also those of which a lattice neighbour (one pitch along film x
    or y) is not present: at the edge of a cropped or partial frame, or beside a gap, a
    mark's neighbours' prediction extrapolates, as on the grid's outline."""
    film = np.asarray(film, float)
    lo, hi = film.min(0), film.max(0)
    tol = 1e-6 * float(np.max(hi - lo) + 1.0)
    out = ((np.abs(film - lo) < tol) | (np.abs(film - hi) < tol)).any(1)
    present = None if present is None else np.asarray(present, bool)
    if present is None or not present.any() or len(film) < 2:
        return out
    have = cKDTree(film[present])
    for k in (0, 1):
        u = np.unique(np.round(film[:, k], 6))
        d = np.diff(u)
        if d.size == 0:
            continue
        step = np.zeros(2)
        step[k] = float(d.min())
        for sgn in (1.0, -1.0):
            q = film + sgn * step
            # only where the certificate has that neighbour (the grid's own outline is above)
            inside = ((q >= lo - tol) & (q <= hi + tol)).all(1)
            dist, _ = have.query(q)
            out |= inside & (dist > 0.25 * step[k])
    return out


def _rescue(sc, shape, film, xy, cov, status, reason, Hm, sigma, floor_px, A, s0, init_err,
            sign, rules, max_shift, ppm, *, fitted, scene_tv=0, blur=None, departure=None):
    """Measure rejected and refused crosses again from three of their four half-arms.

    A cross rejected by the outlier test was usually pulled by scene content along one
    half-arm; one that the acceptance tests refused (``status`` "missing" among ``fitted``,
    (M,) bool: the crosses that were fitted, i.e. not cut by the scan edge) often has one
    half-arm on conflicting scene content. Each such
    cross is fitted four times, each time without one half-arm, from
    the position its neighbours predict and with the affine their positions predict held
    (:func:`_position_affine`; from ``A`` (M, 2, 2), free, where the neighbours do not
    surround the cross): a free affine would let the remaining half of that bar set its
    direction alone, and the cross's precision would drop several times. A fit that passes
    the acceptance tests and lies within the outlier test's own threshold of that prediction
    is a measurement of the cross by its clean parts (of several such, the best-correlated).
    The blur is held at ``blur`` (px) when given; ``departure``, the outlier test's
    :func:`_departure_model`, tightens that threshold as it does the test's. A cross that
    was not measured at all is predicted from the measured ones alone.
    ``cov``: the reported and the independent-pixel covariances (N, 2, 2) each.
    Modifies the arrays in place; returns whether any cross was recovered.
    """
    st = np.array(status)
    rej = np.where((st == "rejected") | ((st == "missing") & np.asarray(fitted, bool)))[0]
    meas = np.where(st == "measured")[0]
    if rej.size == 0 or meas.size < 8:
        return False
    r = xy - grid.apply_h(Hm, film)
    miss = ~np.isfinite(r[rej]).all(1)
    ids = np.concatenate([meas, rej[~miss]])
    p_ids = _local_prediction(film[ids], r[ids], sigma=sigma[ids])
    pred = np.zeros((meas.size + rej.size, 2))
    pred[: meas.size] = p_ids[: meas.size]
    pred[meas.size + np.where(~miss)[0]] = p_ids[meas.size :]
    if miss.any():  # not measured at all: predicted from the measured crosses alone
        q = rej[miss]
        pm = _local_fit(film[q], film[meas], r[meas], 16, 2, n_sigma=sigma[meas])
        inner_q = ~_outline(film)[q]
        if inner_q.any():
            pm[inner_q] = _local_fit(film[q[inner_q]], film[meas], r[meas], 24, 3,
                                     n_sigma=sigma[meas])
        pred[meas.size + np.where(miss)[0]] = pm
    edge = _outline(film, st == "measured")
    dev_m = np.hypot(*(r[meas] - pred[: meas.size]).T)
    spread = _spread(dev_m, edge[meas])  # constant within each group
    s_in = float(spread[~edge[meas]][0]) if (~edge[meas]).any() else float(spread[0])
    s_out = float(spread[edge[meas]][0]) if edge[meas].any() else s_in
    sp_rej = np.where(edge[rej], s_out, s_in)
    target = grid.apply_h(Hm, film[rej]) + pred[meas.size :]
    held, lev = _position_affine(film, xy, st == "measured", ppm)
    # held where the neighbours surround the cross; at the grid's corners the prediction is
    # an extrapolation (variance factor tens of times the typical one): free there
    hold = np.isfinite(held[rej]).all((1, 2)) & (lev[rej] <= 4.0 * np.nanmedian(lev[meas]))
    best = np.full(rej.size, -np.inf)
    for grp, fit_shape in ((np.where(hold)[0], False), (np.where(~hold)[0], True)):
        if grp.size == 0:
            continue
        Ag = A[rej[grp]] if fit_shape else held[rej[grp]]

        # the four fits are independent: one call measures them as four calls would, in
        # common fits where the blur is held (measure's per-mark drop_part); merged in order
        m = grp.size
        f4 = measure(sc, shape, np.tile(target[grp], (4, 1)), np.tile(Ag, (4, 1, 1)), s0,
                     init_err, sign, rules, anchor=np.tile(target[grp], (4, 1)),
                     max_shift=max_shift, drop_part=np.repeat(np.arange(4), m),
                     fit_shape=fit_shape, scene_tv=scene_tv, blur=blur)
        for k in range(4):
            f2 = f4.rows(slice(k * m, (k + 1) * m))
            sg = f2.sigma
            sp = sp_rej[grp]
            fl = floor_px[rej[grp]]
            exp = (None if departure is None
                   else _expected_departure(departure, sg, edge[rej[grp]]))
            thr = _outlier_threshold(sp, fl, sg, exp)
            d = np.hypot(*(f2.xy - target[grp]).T)
            good = f2.ok & (d <= thr) & (np.nan_to_num(f2.score, nan=-1.0) > best[grp])
            for j in np.where(good)[0]:
                i = rej[grp[j]]
                best[grp[j]] = f2.score[j]
                xy[i], cov[0][i], cov[1][i] = f2.xy[j], f2.cov[j], f2.cov_white[j]
                status[i], reason[i] = "measured", ""
    return bool(np.isfinite(best).any())


def _reject_outliers(film, xy, status, reason, H0, sigma, floor_px=0.1):
    """Refit the global model to the measured marks; flag marks that disagree with it.

    A smooth film deformation moves neighbouring crosses alike, so each residual against the
    projective model is compared with a leave-one-out local quadratic fit to its neighbours'
    residuals (a local cubic inside the grid, a quadratic on its outline); a departure beyond
    ``max(floor, 3 s, min(4.5 s, 4 sigma))`` (``s``: the robust spread of the departures,
    separately for the marks on the grid's outline, which are extrapolated, and those inside
    it (the outline of the marks measured when the test starts: the edge of a cropped or
    partial frame counts, :func:`_outline`); ``sigma``: the mark's own precision; ``floor``
    (px, scalar or one per mark): on the outline 0.1 px or :data:`OUTLIER_FLOOR_MM` on the
    film, inside :data:`OUTLIER_FLOOR_INNER`, whichever is larger) is an outlier (a mark
    locked onto something else, or pulled by a scratch along an arm); and
    beyond ``OUTLIER_K`` times the departure expected from the mark's own sigma and the
    prediction's error (:func:`_departure_model`, fitted to the departures before any
    rejection), whichever is smaller, but never below the floor. The worst one is rejected
    and the test repeated. Modifies ``status`` and ``reason`` in place. Returns the global
    model (3, 3), the residuals (M, 2) px (NaN where not measured), their rms (px) and the
    departure model (None with fewer than 8 measured marks).
    """
    Hm = H0
    n_max = max(1, len(film) // 10)
    edge = _outline(film, np.array([s == "measured" for s in status]))
    coef = None
    for _ in range(n_max):
        m = np.array([s == "measured" for s in status])
        if m.sum() < 8:
            break
        Hm = grid.projective_fit(film[m], xy[m])
        r = xy - grid.apply_h(Hm, film)
        idx = np.where(m)[0]
        pred = _local_prediction(film[idx], r[idx], sigma=sigma[idx])
        dev = np.hypot(*(r[idx] - pred).T)
        # marks on the outline of the grid are predicted by extrapolation, which a strong
        # deformation makes worse than the interpolation inside: each group its own spread
        spread = _spread(dev, edge[idx])
        sg = np.nan_to_num(sigma[idx], nan=1.0)
        if coef is None:  # from all measured marks, before any is rejected
            coef = _departure_model(dev, sg, edge[idx])
        fl = np.broadcast_to(floor_px, (len(film),))[idx]
        thr = _outlier_threshold(spread, fl, sg, _expected_departure(coef, sg, edge[idx]))
        bad = dev > thr
        if not bad.any():
            break
        worst = idx[int(np.argmax(np.where(bad, dev / thr, -1.0)))]
        status[worst] = "rejected"
        reason[worst] = "outlier against the global model and its neighbours"
    m = np.array([s == "measured" for s in status])
    if m.sum() >= 4:
        Hm = grid.projective_fit(film[m], xy[m])
    r = xy - grid.apply_h(Hm, film)
    residual = np.where(m[:, None], r, np.nan)
    rms = float(np.sqrt(np.mean(np.sum(r[m] ** 2, 1)))) if m.any() else float("nan")
    return Hm, residual, rms, coef
