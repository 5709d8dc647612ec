"""``detect``: find and measure every reseau cross and fiducial mark of a scan.

The orchestrator of :mod:`softplot.marks`: it runs the stages in order, each a module with one
hand-over object (pixel system throughout, film mm for the certificate):

1. overview (:mod:`softplot.marks.overview`, :class:`~softplot.marks.overview.ReseauOverview`):
   the scan reduced by an integer factor chosen so that a cross line is about one overview
   pixel wide (built blockwise and kept in the scan's own dtype, no float copy);
2. candidates (:mod:`softplot.marks.candidates`, :class:`~softplot.marks.candidates.Candidates`):
   NCC with a cross template rendered from the certificate at the overview's scale, computed in
   strips of rows (small work buffers); peaks of both signs. Where the whole detection
   finds no reseau, it is tried once more with each sign correlated with the scene taken
   away (:func:`~softplot.marks.candidates.scene_removed`: a busy scene's edges and regions
   hide the crosses from the plain correlation);
3. lattice and identification (:mod:`softplot.marks.lattice`,
   :class:`~softplot.marks.lattice.Lattice`; :mod:`softplot.marks.grid`): lattice
   scale/rotation/phase, row/col assignment, projective film -> pixel model by RANSAC, for
   each polarity; the better one is the scan's polarity (unless given). With a rotation above
   2 degrees the NCC is repeated with a rotated template;
4. prediction (:mod:`softplot.marks.prediction`, :class:`~softplot.marks.prediction.Prediction`):
   every cross from the model and the interpolated residuals of its neighbours, a local search
   in the NCC map, the affine each fit starts from;
5. mark geometry (:mod:`softplot.marks.marksize`,
   :class:`~softplot.marks.geometry.MarkGeometry`): the crosses' real arm length and line
   width, profiled at the confirmed predictions; crosses whose extent leaves the scan are
   "missing" (cut), never fitted;
6. measurement (:mod:`softplot.marks.measurement`,
   :class:`~softplot.marks.measurement.Measurement`): least-squares template matching at full
   resolution with robust weights and acceptance tests, the scene under each cross from the
   grey opening or jointly estimated (:mod:`softplot.marks.scene`), refits with the
   neighbours' affine; where too few crosses hold one by one, all of them fitted alike and
   accepted together where they lie on a projective grid (:mod:`softplot.marks.faint_grid`);
7. validation (:mod:`softplot.marks.validation`, :class:`~softplot.marks.validation.Validation`):
   the global projective model, the outlier test against the neighbours, the rescue of
   rejected and refused crosses from three half-arms or one bar; measured crosses that lie
   farther than :data:`~softplot.marks.validation.MAX_GRID_RMS_MM` (rms) off any projective
   grid are not a reseau (an error).

Fiducial cameras go through :mod:`softplot.marks.fiducial`.
"""

from __future__ import annotations

import time

import numpy as np

from softplot.camera import Camera, load_camera
from softplot.errors import SoftplotError
from softplot.marks import jpegq
from softplot.marks.candidates import reseau_candidates, scene_removed
from softplot.marks.common import (
    MM_PER_INCH,
    DetectionError,
    as_scan,
    format_grid_part,
    parse_grid_part,
    polarity_name,
    transform_json,
)
from softplot.marks.faint_grid import faint_grid
from softplot.marks.fiducial import detect_fiducials
from softplot.marks.lattice import (
    MIN_PART,
    MIN_SPANNING,
    Lattice,
    between_nodes,
    estimate_dpi,
    fit_lattice,
    frame_evidence,
    renamed,
    reseau_sized,
    turn_template,
)
from softplot.marks.marksize import centred_geometry, choose_width
from softplot.marks.measure import AcceptRules, opening_only, plane_watch
from softplot.marks.measurement import Measurement, measure_crosses
from softplot.marks.overview import reseau_overview
from softplot.marks.prediction import predict
from softplot.marks.result import Detection
from softplot.marks.scene import SCENE_MODELS
from softplot.marks.template import cross_shape
from softplot.marks.validation import (
    MAX_GRID_RMS_MM,
    SIMILAR_TOL_MM,
    Validation,
    similar_four,
    validate,
)

__all__ = ["detect", "as_scan", "DetectionError", "parse_grid_part", "format_grid_part"]

#: crosses measured on a lattice of at least MIN_PART candidates that make a reseau: fewer than
#: 4 are tested against the lattice's model (not a model of their own), and one cross agrees
#: with it by chance (a busy plain photograph's cross-like corner near one of its nodes)
MIN_MEASURED = 2
#: crosses measured on a lattice grown from one too small to be a reseau (its other crosses
#: looked for at its nodes) that make a reseau: a projective model fits 4 crosses exactly
#: (a scene feature measured as one of them goes unseen), a fifth tests them
MIN_DENSE = 5
#: fewer than 4 crosses measured lie within this (film mm, rms) of the lattice's model (the
#: lattice's crosses place it to a few hundredths of a millimetre; a plain photograph's
#: cross-like corners near its nodes lie 0.1-0.3 mm off)
FEW_GRID_RMS_MM = 0.075


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
        the joint estimate where the scene has sharp edges near the crosses, or where the
        crosses depart from their neighbours far beyond their own precision and the joint
        estimate measures them better.
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
    jpegq.prefetch(sc)  # the fits' JPEG quantisation, estimated beside the first stages
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
        return _reseau_or_opening(sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0,
                                  scene, part)
    except DetectionError as first:
        second = _scene_removed_try(sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0,
                                    scene, part)
        if second is not None:
            return second
        if polarity == "auto":
            raise first from None
        _contradicted(first, sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0, scene,
                      part)


def _reseau_or_opening(sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0, scene,
                       part) -> Detection:
    """:func:`_detect_reseau`; where it took the plane as the scene of flat patches
    (:func:`softplot.marks.measure.flat_scan`) and finds no reseau, or measures fewer than
    :data:`PLANE_TRUST` of the crosses, again with the opening's scene estimate under every
    cross (:func:`softplot.marks.measure.opening_only`), and that kept where it finds one
    fitting its model better (``rms_px``): a web copy whose 4 crosses of 25 held with the
    opening came out with 3 (no reseau) or 5, 2 of them 3 px off, over the plane."""
    def opening():
        with opening_only():
            return _detect_reseau(sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0,
                                  scene, part)

    try:
        with plane_watch() as used:
            det = _detect_reseau(sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0,
                                 scene, part)
    except DetectionError:
        return opening()
    if not used or _measured_share(det) >= PLANE_TRUST:
        return det
    try:  # few crosses held: the opening's detection kept where it fits its model better
        other = opening()
    except DetectionError:
        return det
    return other if other.rms_px < det.rms_px else det


#: a second try with the scene taken away (:func:`_scene_removed_try`) is a reseau only
#: where it measures at least this share of the crosses on the scan (a busy scene's
#: crosses hidden from the plain correlation: 15 of 19 measured; a busy plain photograph:
#: 4 of 109)
SECOND_TRY_SHARE = 0.5


def _scene_removed_try(sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0, scene,
                       part) -> Detection | None:
    """:func:`_reseau_or_opening` again with the candidates correlated with the scene taken
    away (:func:`~softplot.marks.candidates.scene_removed`), after the plain correlation
    found no reseau; None where it finds none either. Having looked twice, it is held to
    more: at least :data:`SECOND_TRY_SHARE` of the crosses on the scan measured, within
    :data:`FEW_GRID_RMS_MM` (rms) of their projective grid (a busy plain photograph's
    cross-like corners: 4 crosses at 0.18 mm)."""
    try:
        with scene_removed():
            det = _reseau_or_opening(sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0,
                                     scene, part)
    except DetectionError:
        return None
    ppm = det.dpi / MM_PER_INCH
    if _measured_share(det) < SECOND_TRY_SHARE or not det.rms_px <= FEW_GRID_RMS_MM * ppm:
        return None
    return det


#: a detection that took the plane and measured less than this share of the crosses on the
#: scan is checked against the opening's (:func:`_reseau_or_opening`)
PLANE_TRUST = 0.5


def _measured_share(det: Detection) -> float:
    """The share of a detection's crosses that it measured, of those on the scan (not
    outside it, not cut by its edge)."""
    on = [st for st, why in zip(det.status, det.reason, strict=True)
          if not why.startswith(("outside the scan", "cut by the scan edge"))]
    return sum(st == "measured" for st in on) / max(len(on), 1)


def _contradicted(first, sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0, scene,
                  part):
    """A polarity given by the user that the scan contradicts: say so, in one line (else
    ``first``, the error with the polarity given)."""
    other = "negative" if polarity == "positive" else "positive"
    try:
        det = _detect_reseau(sc, cam, name, dpi, other, rotate, blur_px, rules, t0, scene, part)
    except DetectionError:
        raise first from None
    n = int(det.measured.sum())
    raise DetectionError(
        f"{name}: no reseau found with --polarity {polarity}: the scan's crosses are "
        f"{other} ({n} found, {'bright' if other == 'negative' else 'dark'} marks); "
        f"give --polarity {other} or auto") from None


def _detect_reseau(sc, cam, name, dpi, polarity, rotate, blur_px, rules, t0,
                   scene="auto", part=None) -> Detection:
    """The reseau path: the stages in order (see the module docstring)."""
    res = cam.reseau
    timings: dict = {}
    rotate_pix = -float(rotate)  # pixel-system angle of film +x (clockwise on screen)
    dpi_source = "given" if dpi is not None else ("file" if sc.dpi else "estimated")
    dpi = dpi if dpi is not None else sc.dpi
    if dpi is None:
        # the scan holds the reseau: a first guess from its size, refined from the spacing
        dpi = estimate_dpi(sc, cam, polarity, rotate_pix, name)
    ppm = dpi / MM_PER_INCH
    _check_size(sc, cam, dpi, name)
    shape = cross_shape(cam, ppm)
    ov = reseau_overview(sc, shape.width, ppm, name)
    timings["overview"] = time.perf_counter() - t0
    lat = _lattice(sc, ov, cam, polarity, rotate_pix, blur_px, part, name, dpi)
    timings["grid"] = time.perf_counter() - t0
    # a lattice of fewer than MIN_PART candidates is a reseau once MIN_SPANNING crosses hold,
    # one grown from such a lattice by looking at its nodes once MIN_DENSE crosses hold
    min_measured = (MIN_DENSE if lat.densified
                    else MIN_SPANNING if len(lat.grid.node) < min(MIN_PART, res.count)
                    else MIN_MEASURED)
    pr = predict(lat, res.film(), ppm, blur_px)
    ambiguous = lat.grid.ambiguous
    # an ambiguous naming may move (:func:`renamed`) off an outer line, the format's edge
    # deciding
    keep = lat if ambiguous else None
    edge = (frame_evidence(ov.image, ov.factor, ov.px_per_mm, min(res.pitch_x, res.pitch_y))
            if ambiguous else None)
    del ov, lat  # the overview and the NCC map are not needed any more: free them
    geom, m, v, pr, need = _measure(sc, pr, res, shape, ppm, rules, scene, timings, t0,
                                    min_measured)
    moved = None
    if keep is not None:
        ok = np.asarray(m.status) == "measured"
        moved = renamed(keep, res, ok, pr.inside(geom.shape(), sc.width, sc.height)[0],
                        (sc.width, sc.height), v.H, edge, cam.format_mm)
    del keep, edge
    if moved is not None:
        # an outer line of the naming held no cross: the naming moved off it, measured again
        pr = predict(moved, res.film(), ppm, blur_px)
        del moved
        geom, m, v, pr, need = _measure(sc, pr, res, shape, ppm, rules, scene, timings, t0,
                                        min_measured)
    min_measured, few_mm, faint = need
    warnings = _judge(cam, name, pr.sign, ppm, m, v, ambiguous, min_measured, few_mm)
    if faint:
        warnings.append(f"the {sum(st == 'measured' for st in m.status)} crosses measured are "
                        "too faint to hold one by one: accepted together as a projective grid, "
                        "their covariances raised to its departure")
    timings["total"] = time.perf_counter() - t0
    return _reseau_detection(sc, cam, name, dpi, dpi_source, pr.sign, m, v, geom.to_json(ppm),
                             warnings, timings, ambiguous)


def _measure(sc, pr, res, shape0, ppm, rules, scene, timings, t0, min_measured):
    """The stages after the prediction ``pr`` (of the grid ``res``): the crosses' geometry,
    their measurement and validation: ``(geom, m, v, pr, (min_measured, few_mm))``, ``pr``
    with the geometry's centres (pixel system), the fewest crosses measured and the grid's
    tolerance (mm) that make a reseau, and whether the crosses were accepted together as a
    faint grid."""
    geom, pr = centred_geometry(sc, pr, shape0, min(res.pitch_x, res.pitch_y) * ppm)
    timings["profiles"] = time.perf_counter() - t0
    geom = choose_width(sc, pr, geom, shape0.width, rules, guess_arm=shape0.length)
    shape = geom.shape()
    timings["geometry"] = time.perf_counter() - t0
    # crosses whose extent leaves the scan are cut: never fitted
    inside, on_img = pr.inside(shape, sc.width, sc.height)
    timings["predict"] = time.perf_counter() - t0
    m = measure_crosses(sc, shape, pr, inside, on_img, rules, scene)
    few_mm = FEW_GRID_RMS_MM
    if min_measured == MIN_DENSE:
        # four crosses of a grown lattice are tested against the certificate's grid instead
        # (its similarity: the lattice, shaped by a scene feature among them, is not a test)
        min_measured = similar_four(pr.film, m.xy, m.status, m.reason, pr.H, ppm) or MIN_DENSE
        few_mm = SIMILAR_TOL_MM if min_measured < MIN_DENSE else few_mm
    timings["lsm"] = time.perf_counter() - t0
    v = validate(sc, pr, m, rules)
    faint = False
    if sum(st == "measured" for st in m.status) < min(min_measured, res.count):
        # too few crosses hold one by one: all of them, fitted alike, as a faint grid
        fg = faint_grid(sc, shape, pr, inside, rules, m)
        if fg is not None:
            m, v, faint = fg, validate(sc, pr, fg, rules), True
    return geom, m, v, pr, (min_measured, few_mm, faint)


def _check_size(sc, cam, dpi, name) -> None:
    """A scan too small for a part of 3 x 3 crosses (or the whole grid, when smaller), in
    either orientation (a quarter turn), is refused."""
    res = cam.reseau
    ppm = dpi / MM_PER_INCH
    span_mm = ((res.cols - 1) * res.pitch_x + res.arm_length_mm,
               (res.rows - 1) * res.pitch_y + res.arm_length_mm)
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


def _lattice(sc, ov, cam, polarity, rotate_pix, blur_px, part, name, dpi) -> Lattice:
    """Candidates and lattice (stages 2 and 3); no lattice, or one of fewer than
    :data:`MIN_PART` crosses that does not span the grid (:func:`reseau_sized`), is a
    :class:`DetectionError`."""
    res = cam.reseau
    ppm = dpi / MM_PER_INCH
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
    dense = between_nodes(lat, res)
    if dense:
        px = res.pitch_x / 2 if any(o[0] for o in dense) else res.pitch_x
        py = res.pitch_y / 2 if any(o[1] for o in dense) else res.pitch_y
        raise DetectionError(
            f"{name}: the scan's reseau is denser than {cam.name}'s: crosses halfway between "
            f"its {res.pitch_x}x{res.pitch_y} mm nodes (a pitch of about {px:g}x{py:g} mm); "
            f"is {cam.name} the scan's camera?")
    n_assigned = len(lat.grid.node)
    if not reseau_sized(lat.grid.node, res):
        raise DetectionError(
            f"{name}: no reseau found: expected {res.rows}x{res.cols} crosses at "
            f"{res.pitch_x}x{res.pitch_y} mm, found only {n_assigned} on a lattice")
    return lat


def _judge(cam, name, sign, ppm, m: Measurement, v: Validation, ambiguous,
           min_measured=MIN_MEASURED, few_mm=FEW_GRID_RMS_MM) -> list[str]:
    """Refuse what is not a reseau (fewer than ``min_measured`` crosses measured, or not on
    a grid: fewer than 4 within ``few_mm`` of the lattice's model); the warnings of one that
    is."""
    res = cam.reseau
    N, n_in = res.count, len(m.fitted)
    n_meas = sum(s == "measured" for s in m.status)
    if n_meas < min(min_measured, res.count):
        # a lattice of candidates was found, but the crosses do not hold up at full resolution
        # (scene texture, the wrong polarity or the wrong camera); crosses that do are never
        # thrown away for being few: two on the lattice of at least MIN_PART candidates (or
        # MIN_SPANNING on one spanning the grid) make a reseau, returned with a warning
        raise DetectionError(
            f"{name}: no reseau found: expected a {res.rows}x{res.cols} grid of "
            f"{polarity_name(sign)} crosses at {res.pitch_x}x{res.pitch_y} mm, measured only "
            f"{n_meas} of the {n_in} inside the scan")
    lim_mm = MAX_GRID_RMS_MM if n_meas >= 4 else few_mm
    if v.rms > lim_mm * ppm:
        # measured, but not on a grid: fits to scene content (e.g. the wrong polarity over a
        # busy scene), not a reseau deformed by at most a tenth of a millimetre; fewer than
        # 4 crosses are held to the lattice's model, closer
        raise DetectionError(
            f"{name}: no reseau found: expected a {res.rows}x{res.cols} grid of "
            f"{polarity_name(sign)} crosses at {res.pitch_x}x{res.pitch_y} mm, the {n_meas} "
            f"measured lie {v.rms:.1f} px (rms) off "
            f"{'any projective grid' if n_meas >= 4 else 'the lattice of candidates'} (at "
            f"most {lim_mm * ppm:.1f} px, {lim_mm} mm, for a reseau)")
    warnings: list[str] = []
    if n_meas < N:
        warnings.append(f"{N - n_meas} of {N} crosses not measured")
    if ambiguous:
        warnings.append("rows and columns are ambiguous: the scan shows a part of the grid "
                        "that could be several (no edge of the format decides, or a dark "
                        "region hides it); named as the crosses fit best, nearest the "
                        "format's centre: give --grid-part")
    if n_meas < 0.2 * n_in:
        # never thrown away for being few: returned, with the warning
        warnings.append(f"only {n_meas} of the {n_in} crosses inside the scan measured: "
                        "check the camera, --polarity and --dpi")
    return warnings


def _reseau_detection(sc, cam, name, dpi, dpi_source, sign, m: Measurement, v: Validation,
                      mark_geometry, warnings, timings, ambiguous=False) -> Detection:
    """The :class:`Detection` of a reseau scan from the stages' hand-overs."""
    res = cam.reseau
    cov = m.cov
    rows_cols = res.row_col()
    n_meas = sum(s == "measured" for s in m.status)
    n_nb = 0 if v.from_neighbours is None else int(np.sum(
        v.from_neighbours & (np.asarray(m.status) == "measured")))
    if n_nb:
        warnings = [*warnings, f"{n_nb} of the {n_meas} crosses measured lean on their "
                    "neighbours' prediction (their own fit is flat along a direction): their "
                    "errors correlate with their neighbours' (JSON from_neighbours)"]
    return Detection(
        image=name,
        camera=cam.name,
        width=sc.width,
        height=sc.height,
        dpi=float(dpi),
        polarity=polarity_name(sign),
        kind=["reseau"] * res.count,
        name=res.names(),
        row=rows_cols[:, 0].astype(int),
        col=rows_cols[:, 1].astype(int),
        film=res.film(),
        xy=m.xy,
        sigma=np.sqrt(0.5 * (cov[:, 0, 0] + cov[:, 1, 1])),
        sigma_xy=np.sqrt(np.stack([cov[:, 0, 0], cov[:, 1, 1]], 1)),
        cov=cov,
        score=m.score,
        cnr=m.cnr,
        status=m.status,
        reason=m.reason,
        transform=transform_json(v.H, v.rms, n_meas),
        rms_px=v.rms,
        residual=v.residual,
        warnings=warnings,
        ids_ambiguous=bool(ambiguous),
        dpi_source=dpi_source,
        timings=timings,
        scene="joint" if m.scene_tv else "opening",
        mark_geometry=mark_geometry,
        arms=v.arms,
        bar=v.bar,
        from_neighbours=v.from_neighbours,
        variance_factor=v.variance_factor,
    )
