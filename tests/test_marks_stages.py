"""The stages of softplot.marks: each alone on a small render, and the package's structure.

Each stage is run by itself on a synthetic render and checked against the render's exact
truth: the overview, the candidates, the lattice (rows/cols and homography), the prediction,
the mark geometry, the measurement (from a prediction built from the truth, not from the
earlier stages) and the validation; the fiducial path's candidates, pattern match,
measurement and validation likewise.

Structure: no function of src/softplot/marks longer than MAX_LINES (except the ones listed with
a reason), no import circle between its modules, and no stage module importing the
orchestrator (detect.py).
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

import numpy as np
import pytest

import softplot.marks
from softplot.camera import load_camera
from softplot.io import Scan
from softplot.marks import coarse, grid
from softplot.marks import fiducial as fid_mod
from softplot.marks.candidates import reseau_candidates
from softplot.marks.common import DetectionError
from softplot.marks.detect import detect
from softplot.marks.lattice import HALF_STEPS, between_nodes, fit_lattice, turn_template
from softplot.marks.marksize import choose_width, mark_geometry
from softplot.marks.measurement import Measurement, measure_crosses, measure_marks
from softplot.marks.overview import make_overview, reseau_factor, reseau_overview
from softplot.marks.prediction import Prediction, predict
from softplot.marks.template import cross_shape, fiducial_shape
from softplot.marks.validation import validate, validate_pattern
from softplot.synthetic import ScanSpec, render_scan

MARKS = Path(softplot.marks.__file__).parent
MAX_LINES = 120
#: (module, function) -> why it is still longer than MAX_LINES
LONG_ALLOWED = {
    ("lsm.py", "lsm"): "the Gauss-Newton loop with its robust weights and tests: to be split "
                       "by its owner",
    ("measure.py", "measure"): "the fits, the scene refits and the acceptance: to be split "
                               "by its owner",
}


def _modules():
    return {p.stem: ast.parse(p.read_text(encoding="utf-8")) for p in sorted(MARKS.glob("*.py"))}


def test_no_function_longer_than_the_limit():
    long = {}
    for name, tree in _modules().items():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_LINES:
                    long[(f"{name}.py", node.name)] = n
    unexpected = {k: v for k, v in long.items() if k not in LONG_ALLOWED}
    assert not unexpected, f"functions over {MAX_LINES} lines: {unexpected}"


def _imports(tree, names) -> set[str]:
    """The modules of softplot.marks a module imports (anywhere in it, functions included)."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.module == "softplot.marks":
                out |= {a.name for a in node.names if a.name in names}
            elif node.module.startswith("softplot.marks."):
                out.add(node.module.split(".")[2])
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("softplot.marks."):
                    out.add(a.name.split(".")[2])
    return out


def _graph():
    mods = _modules()
    names = set(mods) - {"__init__"}
    return {m: _imports(t, names) - {m} for m, t in mods.items() if m != "__init__"}


def test_import_graph_has_no_circle():
    graph = _graph()
    assert {"common", "overview", "candidates", "lattice", "detect", "fiducial"} <= set(graph)
    state: dict = {}

    def visit(m, path):
        state[m] = 1
        for n in sorted(graph.get(m, ())):
            assert state.get(n) != 1, f"import circle: {' -> '.join(path + [m, n])}"
            if n not in state:
                visit(n, path + [m])
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m, [])


def test_no_stage_imports_the_orchestrator():
    graph = _graph()
    users = sorted(m for m, deps in graph.items() if "detect" in deps)
    assert users == [], f"modules importing softplot.marks.detect: {users}"
    # the fiducial path reaches the shared helpers through common, not through detect
    assert "common" in graph["fiducial"] and "detect" not in graph["fiducial"]


# --- the stages alone on renders -----------------------------------------------------------

CAM = "rollei-6006"
DPI = 600.0
PPM = DPI / 25.4


@functools.lru_cache(maxsize=4)
def _render(camera, seed, **kw):
    img, truth = render_scan(camera, ScanSpec(**kw), seed)
    sc = Scan.from_array(img, dpi=truth["dpi"], bit_depth=truth["bit_depth"])
    return sc, truth


def _truth(camera, truth):
    """True pixel positions (N, 2) of the certificate's marks and which are visible (N,)."""
    cam = load_camera(camera)
    names = cam.reseau.names() if cam.reseau is not None else [f.name for f in cam.fiducials]
    by = {m["name"]: m for m in truth["marks"]}
    xy = np.array([(by[n]["x"], by[n]["y"]) for n in names])
    vis = np.array([by[n]["state"] == "visible" for n in names])
    return xy, vis


@pytest.fixture(scope="module")
def turned():
    """A positive (dark crosses) Rollei scan turned by 4 degrees; (scan, truth, camera)."""
    sc, truth = _render(CAM, 3, dpi=DPI, noise_sigma=0.01, blur_sigma_px=1.0, rotation_deg=4.0)
    return sc, truth, load_camera(CAM)


@pytest.fixture(scope="module")
def coarse_stages(turned):
    sc, truth, cam = turned
    shape = cross_shape(cam, PPM)
    ov = reseau_overview(sc, shape.width, PPM, "scan")
    cands = reseau_candidates(sc, ov, cam, "auto", 1.0)
    return ov, cands


def test_overview_stage_reduces_to_a_line_about_one_pixel_wide(turned):
    sc, truth, cam = turned
    for line_px, npix in ((0.94, 1e6), (3.1, 1e6), (12.0, 1e6), (3.1, 4e8)):
        f = reseau_factor(line_px, int(npix))
        assert npix / f**2 <= 6e6
        if f > 1 and npix / (f - 1) ** 2 <= 6e6:  # not raised for the size: line width
            assert 0.62 <= line_px / f < 1.24, (line_px, f)
    ov = reseau_overview(sc, 3.1, PPM, "scan")
    assert ov.factor == reseau_factor(3.1, sc.width * sc.height) == 5
    assert ov.image.shape == (sc.height // 5, sc.width // 5)
    # overview pixel (i, j) averages the full-resolution pixels it covers
    full = np.asarray(sc.grey((slice(0, 10), slice(0, 10))), np.float64)
    assert abs(float(ov.image[1:2, 1:2][0, 0]) - full[5:10, 5:10].mean()) < 2.0 / 255
    blank = Scan.from_array(np.full((600, 600), 128, np.uint8), dpi=DPI)
    with pytest.raises(DetectionError, match="blank image"):
        reseau_overview(blank, 1.0, PPM, "blank.tif")


def test_candidate_stage_finds_every_visible_cross(turned, coarse_stages):
    sc, truth, cam = turned
    ov, cands = coarse_stages
    txy, vis = _truth(CAM, truth)
    # both signs found; the bright one, which cannot outscore the dark, not scored by its
    # arms yet (tests/test_marks_serial_speed.py)
    assert set(cands.peaks) | set(cands.deferred) == {1, -1} and cands.template.length > 0
    dark = coarse.ov_to_full(cands.peaks[-1].xy, ov.factor)  # the render's crosses are dark
    d = np.hypot(*(txy[:, None, :] - dark[None]).transpose(2, 0, 1)).min(1)
    assert vis.sum() == 121 and d[vis].max() < 1.0, d.max()


def test_lattice_stage_names_rows_and_cols_and_maps_within_a_pixel(turned, coarse_stages):
    sc, truth, cam = turned
    ov, cands = coarse_stages
    txy, vis = _truth(CAM, truth)
    film = cam.reseau.film()
    lat = fit_lattice(sc, ov, cands, cam, "auto", 0.0)
    assert lat.sign == -1
    assert abs(lat.grid.rotation_deg + 4.0) < 0.2  # pixel system: film +x turned by -4 deg
    lat = turn_template(lat, sc, ov, cam, 0.0, 1.0)
    # every cross on the lattice, each named as the truth names the cross at its position
    assert sorted(lat.grid.node) == list(range(121))
    near = np.hypot(*(lat.assigned_xy()[:, None, :] - txy[None]).transpose(2, 0, 1)).argmin(1)
    assert (near == lat.grid.node).all()
    err = np.hypot(*(grid.apply_h(lat.grid.H, film) - txy).T)
    assert err[vis].max() < 1.0, err.max()


def test_lattice_of_a_sparser_certificate_sees_the_crosses_between_its_nodes(turned,
                                                                              coarse_stages):
    """A 10 mm certificate (hasselblad-mk70, 5 x 5) on the Rollei's 5 mm reseau fits every
    other cross perfectly; the crosses halfway between its nodes tell the wrong camera. The
    right certificate sees none."""
    sc, truth, cam = turned
    ov, cands = coarse_stages
    right = turn_template(fit_lattice(sc, ov, cands, cam, "auto", 0.0), sc, ov, cam, 0.0, 1.0)
    assert between_nodes(right, cam.reseau) == []
    sparse = load_camera("hasselblad-mk70")
    wrong = fit_lattice(sc, ov, reseau_candidates(sc, ov, sparse, "auto", 1.0), sparse,
                        "auto", 0.0)
    assert wrong is not None and len(wrong.grid.node) >= 16  # the lattice itself fits
    assert sorted(between_nodes(wrong, sparse.reseau)) == sorted(HALF_STEPS)
    with pytest.raises(DetectionError, match="denser than hasselblad-mk70"):
        detect(sc, sparse)


def test_prediction_stage_within_a_pixel_of_truth(turned, coarse_stages):
    sc, truth, cam = turned
    ov, cands = coarse_stages
    txy, vis = _truth(CAM, truth)
    film = cam.reseau.film()
    lat = turn_template(fit_lattice(sc, ov, cands, cam, "auto", 0.0), sc, ov, cam, 0.0, 1.0)
    pr = predict(lat, film, PPM, 1.0)
    assert np.hypot(*(pr.xy - txy).T)[vis].max() < 1.0
    assert np.hypot(*(pr.start - txy).T)[vis].max() < 1.0 and pr.found[vis].all()
    # the affine maps the film's directions to the mark frame (u along film x, v along -y)
    ux = np.einsum("nij,nj->ni", pr.A, pr.J[:, :, 0]) / PPM
    assert np.abs(ux - [1.0, 0.0]).max() < 0.01
    inside, on_img = pr.inside(cross_shape(cam, PPM), sc.width, sc.height)
    assert inside.all() and on_img.all()
    # a scan ending at the bottom row's highest cross: that row cut, the others inside
    inside, _ = pr.inside(cross_shape(cam, PPM), sc.width, int(txy[-11:, 1].min()))
    assert not inside[-11:].any() and inside[:-11].all()


def _truth_prediction(cam, txy, sign, s0=1.0, jitter=0.4, seed=0):
    """A Prediction built from the truth alone (positions jittered by ``jitter`` px)."""
    film = cam.reseau.film()
    H = grid.projective_fit(film, txy)
    J = grid.h_jacobian(H, film)
    A = np.linalg.inv(J @ np.diag([1.0 / PPM, -1.0 / PPM]))
    start = txy + np.random.default_rng(seed).normal(0.0, jitter, txy.shape)
    return Prediction(film=film, xy=start, start=start, ncc=np.ones(len(film)),
                      found=np.ones(len(film), bool), A=A, J=J, H=H, sign=sign, px_per_mm=PPM,
                      max_shift=3.0, init_err=1.0, s0=float(np.hypot(s0, np.sqrt(1 / 12))))


def test_geometry_stage_measures_the_real_size():
    """Crosses 1.3 x longer and 3 x wider than the certificate's: the stage finds them
    (profiled at the crosses the prediction confirms)."""
    sc, truth = _render(CAM, 4, dpi=DPI, noise_sigma=0.01, blur_sigma_px=1.0,
                        mark_arm_scale=1.3, mark_width_scale=3.0)
    cam = load_camera(CAM)
    guess = cross_shape(cam, PPM)
    ov = reseau_overview(sc, guess.width, PPM, "scan")
    lat = fit_lattice(sc, ov, reseau_candidates(sc, ov, cam, "auto", 1.0), cam, "auto", 0.0)
    pr = predict(lat, cam.reseau.film(), PPM, 1.0)
    geom = mark_geometry(sc, pr, guess, 5.0 * PPM)
    assert geom.source == "scan" and geom.n >= 8
    assert abs(geom.arm_px / (1.3 * guess.length) - 1.0) < 0.03, geom
    geom = choose_width(sc, pr, geom, guess.width, None)
    # the width is settled among the profiles' value and steps from the guess towards it
    # (the least-squares fits decide): within a fifth of the truth, far from the guess
    assert abs(geom.width_px / (3.0 * guess.width) - 1.0) < 0.2, geom


@pytest.fixture(scope="module")
def measured(turned):
    """The measurement stage alone: from a prediction built from the truth."""
    sc, truth, cam = turned
    txy, vis = _truth(CAM, truth)
    pr = _truth_prediction(cam, txy, -1)
    inside, on_img = pr.inside(cross_shape(cam, PPM), sc.width, sc.height)
    m = measure_crosses(sc, cross_shape(cam, PPM), pr, inside, on_img, None, "opening")
    return pr, m


def test_measurement_stage_alone_within_its_bound(turned, measured):
    sc, truth, cam = turned
    txy, vis = _truth(CAM, truth)
    pr, m = measured
    ok = np.array([s == "measured" for s in m.status])
    assert ok[vis].all(), [r for r, v in zip(m.reason, vis, strict=True) if v and r]
    err = m.xy - txy
    sd = np.sqrt(np.stack([m.cov[:, 0, 0], m.cov[:, 1, 1]], 1))
    z = err[ok] / sd[ok]
    # the errors are what the reported covariance says (noise 0.01: a few hundredths of a px)
    assert 0.6 < np.sqrt(np.mean(z**2)) < 1.6, np.sqrt(np.mean(z**2))
    assert np.abs(z).max() < 5.0
    assert np.sqrt(np.mean(np.sum(err[ok] ** 2, 1))) < 0.05


def test_validation_stage_rejects_and_remeasures_displaced_crosses(turned, measured):
    sc, truth, cam = turned
    txy, vis = _truth(CAM, truth)
    pr, m0 = measured
    m = Measurement(**{k: (v.copy() if isinstance(v, (np.ndarray, list)) else v)
                       for k, v in vars(m0).items()})
    moved = [27, 60, 93]  # inside the grid: 0.6 px off, as if pulled by a scratch
    m.xy[moved] += [0.6, -0.3]
    v = validate(sc, pr, m, None)
    ok = np.array([s == "measured" for s in m.status])
    assert ok[vis].all()
    err = np.hypot(*(m.xy - txy).T)
    assert err[moved].max() < 0.1, err[moved]  # rejected, then measured again from the scan
    assert err[ok].max() < 0.15
    assert (v.arms[vis] == 2).all() and v.rms < 1.0
    assert np.nanmax(np.abs(v.residual - (m.xy - grid.apply_h(v.H, pr.film)))) < 1e-9


# --- the fiducial path's stages ------------------------------------------------------------

FID = "zeiss-rmk-a-15-23"


@pytest.fixture(scope="module")
def fiducial_scan():
    sc, truth = _render(FID, 21, dpi=300, polarity="negative", rotation_deg=6.0,
                        offset_px=(40.0, -25.0))
    return sc, truth, load_camera(FID)


def test_fiducial_candidates_and_pattern_match(fiducial_scan):
    sc, truth, cam = fiducial_scan
    txy, _ = _truth(FID, truth)
    fids, film, ppm = list(cam.fiducials), cam.fiducial_film(), 300 / 25.4
    ov = make_overview(sc, fid_mod._fiducial_factor(fids, ppm, sc.width * sc.height), ppm,
                       "scan", compact=False)
    cands = fid_mod._candidates(sc, cam, ov, film, ppm, 0.0, 0.06, 1.0, (1, -1))
    (count, _), pick, Lm, t, k, th = fid_mod.match_pattern(film, cands, ppm, 0.0, 0.06, 1)
    assert count == len(fids) and (pick >= 0).all()
    assert abs(np.degrees(th) + 6.0) < 0.2 and abs(k / ppm - 1.0) < 0.01
    assert np.hypot(*(film @ Lm.T + t - txy).T).max() < 1.0


def test_fiducial_measurement_and_validation_alone(fiducial_scan):
    sc, truth, cam = fiducial_scan
    txy, _ = _truth(FID, truth)
    fids, film, ppm = list(cam.fiducials), cam.fiducial_film(), 300 / 25.4
    th = np.radians(-6.0)
    Lm = ppm * np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]) @ np.diag([1, -1])
    t = np.mean(txy - film @ Lm.T, 0)
    A = np.linalg.inv(Lm @ np.diag([1.0 / ppm, -1.0 / ppm]))
    start = txy + np.random.default_rng(1).normal(0.0, 0.5, txy.shape)
    m = measure_marks(sc, [fiducial_shape(f, ppm) for f in fids], start, A, 1.0, 1.0, 1, None)
    assert all(s == "measured" for s in m.status), m.reason
    assert np.hypot(*(m.xy - txy).T).max() < 0.1
    # validation alone: one mark 1.5 mm off the pattern is rejected (a single non-robust
    # fit: it pulls the model, and one or two good marks near it may be rejected with it),
    # the model refitted to the rest maps every mark within half a pixel of the truth
    m.xy[3] += [1.5 * ppm, 0.0]
    v = validate_pattern(film, m, Lm, t, ppm)
    ok = np.array([s == "measured" for s in m.status])
    assert m.status[3] == "rejected" and ok.sum() >= 5
    assert v.kind == "projective" and v.rms < 0.1
    assert np.isnan(v.residual[~ok]).all()
    assert np.hypot(*(grid.apply_h(v.H, film) - txy).T).max() < 0.5
