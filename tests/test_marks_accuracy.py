"""Accuracy of reseau-cross detection against exact synthetic truth (issue 3, point 6).

Every case renders a scan with ``softplot.synthetic.render_scan``, runs ``softplot.marks.detect``
and checks, per scan:

* 0 crosses given a wrong row/col (a measured cross more than 1 px from its own truth);
* 0 crosses claimed where the truth says covered, cut or outside;
* over all cases of the run together, busy renders included, at least 99.5 % of the visible
  crosses measured (issue 3 point 6 states the rate for the sweep: the pooled rate, checked
  by ``conftest.py`` at the end of the session, a failure fails the run); per scan, a guard
  of our own against a scan that collapses: at most ``max(1, 0.5 %)`` not measured, at
  most 10 % on a busy scene (where crosses the scene makes ambiguous are rejected, not
  reported wrong);
* RMS error of the measured crosses <= 1.5 x the Cramér-Rao bound of that render
  (:func:`softplot.marks.crb.render_crb`: the render's blur, noise + quantisation, line width,
  arm length, and pixel by pixel the scene each cross hides, saturated pixels censored);
* RMS <= 0.03 px when the contrast-to-noise ratio is >= 20 and the line width >= 2 px.

``SOFTPLOT_FULL=1`` runs the whole sweep; the default run samples it. Set
``SOFTPLOT_SWEEP_LOG=file.jsonl`` to append one line of figures per case.
"""

from __future__ import annotations

import functools
import json
import os

import numpy as np
import pytest
from scipy.special import ndtr

from conftest import POOLED_RATE_KEY, sweep
from softplot.camera import load_camera
from softplot.io import Scan
from softplot.marks import detect
from softplot.marks.crb import _censored_information, centre_crb, effective_noise, render_crb
from softplot.marks.template import cross_shape
from softplot.synthetic import ScanSpec, TruthMapping, render_scan


@functools.lru_cache(maxsize=8)
def _render(camera: str, items: tuple, seed: int):
    spec = ScanSpec(**dict(items))
    return render_scan(camera, spec, seed)


def render(camera: str, seed: int = 0, **kw):
    """Cached synthetic render: (image, truth)."""
    return _render(camera, tuple(sorted(kw.items())), seed)


@functools.lru_cache(maxsize=4)
def _scene(camera: str, items: tuple, seed: int) -> np.ndarray:
    kw = dict(items)
    kw.update(noise_sigma=0.0, bits=32, file_format="tif")
    img, truth = render_scan(camera, ScanSpec(**kw), seed, marks=False, clip=False)
    return Scan.from_array(img, dpi=truth["dpi"]).grey()


def scene_of(camera: str, seed: int = 0, **kw) -> np.ndarray:
    """The same render without marks and noise (grey, float): the scene each cross hides."""
    return _scene(camera, tuple(sorted(kw.items())), seed)


def scan_of(img, truth) -> Scan:
    bits = truth.get("bit_depth")
    return Scan.from_array(img, dpi=truth["dpi"],
                           bit_depth=bits if img.dtype.kind in "ui" else None)


def evaluate(det, truth, camera: str, scene: np.ndarray | None = None,
             scene_shift: bool = False) -> dict:
    """Compare a detection with the truth: counts, errors, CRB.

    With ``scene`` (the render without marks and noise, :func:`scene_of`) each cross's bound
    is :func:`softplot.marks.crb.render_crb`, pixel by pixel against the scene it hides, with
    saturated pixels censored; without it, the flat-background bound at the cross's mean
    contrast from the truth. With ``scene_shift`` also the bound with the scene's position
    under each half-arm unknown (``crb_shift``, for the sweep's log; else the same as ``crb``).
    """
    tm = {m["name"]: m for m in truth["marks"]}
    r = truth["render"]
    cam = load_camera(camera)
    ppm = truth["dpi"] / 25.4
    shape = cross_shape(cam, ppm)
    noise = effective_noise(r["noise_sigma"], truth.get("bit_depth"))
    crb1 = centre_crb(shape, r["blur_sigma_px"], 1.0, noise)  # bound at unit contrast
    bound, bound_shift = {}, {}
    if scene is not None:
        mp = TruthMapping.from_truth(truth)
        rs = [m for m in truth["marks"] if m["kind"] == "reseau"]
        film = np.array([[m["film_x"], m["film_y"]] for m in rs])
        A = np.linalg.inv(mp.jacobian(film) @ np.diag([1.0 / ppm, -1.0 / ppm]))
        xy = np.array([[m["x"], m["y"]] for m in rs])
        args = (A, shape, r["blur_sigma_px"], r["mark_level"], noise)
        b = render_crb(scene, xy, *args)
        bound = {m["name"]: v for m, v in zip(rs, b, strict=True) if np.isfinite(v)}
        if scene_shift:  # the scene's position under each half-arm unknown (docs/accuracy.md)
            b = render_crb(scene, xy, *args, scene_shift=True)
            bound_shift = {m["name"]: v for m, v in zip(rs, b, strict=True) if np.isfinite(v)}
    out = dict(visible=0, measured=0, missed=[], wrong=[], claimed=[], err=[], crb=[], cnr=[],
               crb_flat=[], crb_shift=[])
    for i, name in enumerate(det.name):
        t = tm[name]
        if det.kind[i] != "reseau":
            continue
        vis = bool(t["visible"])
        out["visible"] += vis
        if det.status[i] != "measured":
            if vis:
                out["missed"].append((name, det.status[i], det.reason[i], bool(t.get("damaged"))))
            continue
        if not vis:
            out["claimed"].append((name, t["state"]))
            continue
        e = det.xy[i] - (t["x"], t["y"])
        if np.hypot(*e) > 1.0:
            out["wrong"].append((name, e.tolist()))
            continue
        out["measured"] += 1
        c = abs(float(t.get("contrast", r["contrast"])))
        out["err"].append(e)
        out["crb_flat"].append(crb1 / max(c, 1e-6))
        out["crb"].append(bound.get(name, out["crb_flat"][-1]))
        out["crb_shift"].append(bound_shift.get(name, out["crb"][-1]))
        out["cnr"].append(c / noise)
    err = np.array(out["err"]).reshape(-1, 2)
    out["rms"] = float(np.sqrt(np.mean(err**2))) if len(err) else float("nan")
    out["crb_rms"] = float(np.sqrt(np.mean(np.square(out["crb"])))) if out["crb"] else float("nan")
    out["crb_flat_rms"] = (float(np.sqrt(np.mean(np.square(out["crb_flat"]))))
                           if out["crb_flat"] else float("nan"))
    out["crb_shift_rms"] = (float(np.sqrt(np.mean(np.square(out["crb_shift"]))))
                            if out["crb_shift"] else float("nan"))
    out["cnr_min"] = float(np.min(out["cnr"])) if out["cnr"] else float("nan")
    out["line_px"] = shape.width
    return out


#: the issue's criteria (point 6): RMS <= 1.5 x the bound of the render; at least 99.5 % of
#: the visible crosses of the sweep measured (pooled: ``conftest.POOLED_RATE``)
FACTOR = 1.5
#: the per-scan guard (ours, not the issue's): at least this share measured, at most
#: max(1, ...) lost (per scan of 121 crosses: 1); on a busy scene at least BUSY_SCAN_RATE
SCAN_RATE = 0.995
BUSY_SCAN_RATE = 0.90


def check(res: dict, label: str, busy: bool = False) -> None:
    assert not res["wrong"], f"{label}: wrong row/col {res['wrong']}"
    assert not res["claimed"], f"{label}: claimed where not visible {res['claimed']}"
    rate = BUSY_SCAN_RATE if busy else SCAN_RATE
    allowed = max(1, int((1.0 - rate) * res["visible"]))
    assert len(res["missed"]) <= allowed, f"{label}: missed {len(res['missed'])} {res['missed']}"
    assert res["rms"] <= FACTOR * res["crb_rms"], (
        f"{label}: rms {res['rms']:.4f} px > {FACTOR} x CRB {res['crb_rms']:.4f} px")
    if res["cnr_min"] >= 20 and res["line_px"] >= 2.0:
        assert res["rms"] <= 0.03, f"{label}: rms {res['rms']:.4f} px > 0.03 px"


def _log(label: str, res: dict) -> None:
    path = os.environ.get("SOFTPLOT_SWEEP_LOG")
    if not path:
        return
    row = {k: res[k] for k in ("visible", "measured", "rms", "crb_rms", "crb_flat_rms",
                               "crb_shift_rms", "cnr_min", "line_px")}
    row.update(case=label, missed=len(res["missed"]), wrong=len(res["wrong"]),
               claimed=len(res["claimed"]))
    with open(path, "a", encoding="utf-8") as f:
        f.write(json.dumps(row) + "\n")


# the sweep: dpi x polarity x blur x noise x scene, plus geometry and file-type variations
_BASE = []
for dpi in (600, 900, 1200, 1800, 2400):
    for pol in ("positive", "negative"):
        for blur, noise in ((0.5, 0.005), (1.0, 0.01), (1.5, 0.03)):
            for scene in ("none", "texture", "busy"):
                _BASE.append(("rollei-6006", dict(dpi=dpi, polarity=pol, blur_sigma_px=blur,
                                                  noise_sigma=noise, scene=scene)))
_EXTRA = [
    ("rollei-6006", dict(dpi=1200, rotation_deg=10.0, deform_um=100.0, anisotropy_ppm=2000.0,
                         offset_px=(35.0, -50.0))),
    ("rollei-6006", dict(dpi=1200, rotation_deg=-9.0, shrink_ppm=3000.0, deform_um=60.0)),
    ("rollei-6006", dict(dpi=2400, rotation_deg=-10.0, deform_um=100.0, anisotropy_ppm=3000.0,
                         blur_sigma_px=0.5, noise_sigma=0.005, scene="none")),
    ("rollei-6006", dict(dpi=2400, rotation_deg=6.0, deform_um=100.0, offset_px=(-80.0, 60.0))),
    ("rollei-6006", dict(dpi=1000, file_format="jpg", jpeg_quality=85)),
    ("rollei-6006", dict(dpi=1000, bits=16, noise_sigma=0.004)),
    ("rollei-6006", dict(dpi=1000, rgb=True, polarity="negative")),
    ("rollei-6008", dict(dpi=1500, polarity="negative", scene="busy", blur_sigma_px=1.2)),
    ("pentax-645", dict(dpi=1200, scene="busy")),
    ("hasselblad-mk70", dict(dpi=800, polarity="negative")),
]
def _label(cam, kw, seed) -> str:
    return f"{cam}-" + "-".join(f"{k}={v}" for k, v in sorted(kw.items())) + f"-s{seed}"


CASES = [(_label(cam, kw, seed), cam, kw, seed)
         for seed, (cam, kw) in enumerate(_BASE + _EXTRA)]


def _ids(v):
    return v if isinstance(v, str) and "-s" in v else "_"


@pytest.mark.parametrize("label,cam,kw,seed", sweep(CASES, 16, seed=3), ids=_ids)
def test_detection_accuracy_sweep(label, cam, kw, seed, record_property):
    img, truth = render(cam, seed, **kw)
    det = detect(scan_of(img, truth), cam)
    res = evaluate(det, truth, cam, scene_of(cam, seed, **kw),
                   scene_shift=bool(os.environ.get("SOFTPLOT_SWEEP_LOG")))
    _log(label, res)
    # the pooled detection rate of the run (issue 3 point 6: >= 99.5 % of the visible
    # crosses), busy renders included, is checked over all cases by conftest.py
    record_property(POOLED_RATE_KEY, (res["visible"], res["measured"]))
    check(res, label, busy=kw.get("scene") == "busy")


def test_render_crb_matches_flat_bound():
    """On an empty scene the per-render bound equals the flat-background bound (both from the
    same model), and it grows where the scene lowers the contrast or saturates."""
    kw = dict(dpi=900, blur_sigma_px=0.8, noise_sigma=0.01, scene="none")
    img, truth = render("rollei-6006", 5, **kw)
    det = detect(scan_of(img, truth), "rollei-6006")
    res = evaluate(det, truth, "rollei-6006", scene_of("rollei-6006", 5, **kw))
    assert res["crb_rms"] == pytest.approx(res["crb_flat_rms"], rel=0.05)
    cam = load_camera("rollei-6006")
    shape = cross_shape(cam, 900 / 25.4)
    flat = np.full((200, 200), 0.8)
    bright = flat.copy()
    bright[:, 100:] = 1.4  # right of the vertical arm, a scene the scanner saturates

    def bound(sc, clip=(0.0, 1.0)):
        return render_crb(sc, [[100.0, 100.0]], np.eye(2), shape, 0.8, 0.3, 0.01, clip=clip)[0]

    assert bound(flat) == pytest.approx(centre_crb(shape, 0.8, 0.5, 0.01), rel=0.05)
    assert bound(flat * 0.75 + 0.075) == pytest.approx(bound(flat) * 0.5 / 0.375, rel=0.05)
    assert bound(bright) > 1.1 * bound(bright, clip=None)  # censoring removes information
    z = np.array([-30.0, 0.0, 30.0])
    assert _censored_information(z) == pytest.approx([0.0, 0.5 + 1.0 / np.pi, 1.0], abs=1e-6)


def test_render_crb_with_the_scene_position_unknown():
    """The bound with a free shift of the scene across each half-arm (``scene_shift``): equal
    to the known-scene bound where the scene has no structure in the bars' footprints, larger
    where a scene edge runs along a bar within its blur, and the same again once the edge is
    beyond the footprint."""
    cam = load_camera("rollei-6006")
    shape = cross_shape(cam, 900 / 25.4)
    xx = np.broadcast_to(np.arange(200.0)[None, :], (200, 200))

    def ratio(sc):
        a, b = (render_crb(sc, [[100.0, 100.0]], np.eye(2), shape, 0.8, 0.9, 0.01,
                           scene_shift=f)[0] for f in (False, True))
        return b / a

    assert ratio(np.full((200, 200), 0.3)) == pytest.approx(1.0, abs=1e-9)
    # a blurred scene step running along the vertical arm, at its edge / 8 px beside it
    at_edge = 0.275 + 0.05 * ndtr((xx - 100.0 - 0.5 * shape.width - 1.0) / 0.85)
    beside = 0.275 + 0.05 * ndtr((xx - 108.0) / 0.85)
    assert ratio(at_edge) > 1.02
    assert ratio(beside) == pytest.approx(1.0, abs=1e-3)


def test_half_arm_check_removes_scene_pull(monkeypatch):
    """On a busy 2400 dpi render, a few crosses have one half-arm on a scene edge or a
    saturated road; LSM's half-arm consistency test drops that half and refits. It sees the
    pull where the cross's affine is held (a free affine turns the bar and hides it), i.e.
    in the refits of :func:`softplot.marks.measurement.shape_from_neighbours`: with the test the
    RMS is well below the RMS without it. (With the opening's scene, ``scene="opening"``:
    the joint scene estimate that ``detect`` takes here by default removes most of this pull
    itself.)"""
    import functools

    import softplot.marks.measure as measure_mod
    from softplot.marks import neighbour_prior
    from softplot.marks.lsm import lsm

    # the half-arm test judged alone: the neighbours' prior for flat fits, which comes last
    # and takes up much of this pull too, off in both runs
    monkeypatch.setattr(neighbour_prior, "PRIOR_FLAT", np.inf)
    monkeypatch.setattr(neighbour_prior, "PRIOR_ANY_RATIO", np.inf)
    label, cam, kw, seed = next(c for c in CASES if "blur_sigma_px=1.0-dpi=2400-noise_sigma=0.01"
                                "-polarity=negative-scene=busy" in c[0])
    img, truth = render(cam, seed, **kw)
    rms = {}
    for arm in (True, False):
        monkeypatch.setattr(measure_mod, "lsm", functools.partial(lsm, arm_check=arm))
        rms[arm] = evaluate(detect(scan_of(img, truth), cam, scene="opening"), truth,
                            cam)["rms"]
    assert rms[True] < 0.85 * rms[False], rms


def test_shape_from_neighbours_removes_scene_pull(monkeypatch):
    """On a busy 2400 dpi render, scene edges along some half-arms pull those halves and the
    free affine absorbs the pull by turning the bar. Marks whose affine departs from the one
    their neighbours' positions predict (beyond 2.5 robust spreads) are refitted with the
    predicted affine held, where the half-arm test sees the pull and drops that half: the
    RMS is well below that of the same detection without this test (with the opening's scene,
    as in :func:`test_half_arm_check_removes_scene_pull`).

    The candidates are taken by their correlation alone, as when this case was set up: with
    the coarse stage's arm test (:func:`softplot.marks.candidates.arm_scored`) the lattice
    holds more crosses, the fits start nearer and the pull without this test is smaller
    (0.0067 px against 0.0052 px with it; 0.0104 px from correlation alone)."""
    import functools
    import importlib

    from softplot.marks import neighbour_prior

    # the test judged alone: the neighbours' prior for flat fits off in both runs
    monkeypatch.setattr(neighbour_prior, "PRIOR_FLAT", np.inf)
    monkeypatch.setattr(neighbour_prior, "PRIOR_ANY_RATIO", np.inf)
    det_mod = importlib.import_module("softplot.marks.measurement")

    def by_correlation(pk, image, sign, arm_half, width, s, n_in, keep, turn_deg=0.0):
        return pk.select(np.arange(min(len(pk), keep)))  # the peaks come best first

    for mod in ("softplot.marks.candidates", "softplot.marks.lattice"):
        monkeypatch.setattr(importlib.import_module(mod), "arm_scored", by_correlation)
    label, cam, kw, seed = next(c for c in CASES if "blur_sigma_px=1.0-dpi=2400-noise_sigma=0.01"
                                "-polarity=negative-scene=busy" in c[0])
    img, truth = render(cam, seed, **kw)
    orig = det_mod.shape_from_neighbours
    rms = {}
    for z in (2.5, np.inf):
        monkeypatch.setattr(det_mod, "shape_from_neighbours", functools.partial(orig, z_max=z))
        res = evaluate(detect(scan_of(img, truth), cam, scene="opening"), truth, cam)
        assert not res["wrong"] and not res["claimed"]
        rms[z] = res["rms"]
    assert rms[2.5] < 0.7 * rms[np.inf], rms


@pytest.mark.parametrize("dpi,blur", [(250, 2.2), (300, 2.5)])
def test_blur_wider_than_expected_reaches_the_bound(dpi, blur):
    """A scan blurrier than the detector expects (blur sigma 2.2-2.5 px, the default expects
    1 px): windows and scene estimate sized for the expected blur cut the blurred bars' skirts
    (RMS 1.41 and 1.51 x the bound); fitted again for the blur the crosses show, within 1.3 x."""
    cam = "rollei-6006"
    kw = dict(dpi=dpi, blur_sigma_px=blur, noise_sigma=0.01, scene="none")
    img, truth = render(cam, 0, **kw)
    res = evaluate(detect(scan_of(img, truth), cam), truth, cam, scene_of(cam, 0, **kw))
    assert not res["wrong"] and not res["missed"], (res["wrong"], res["missed"])
    assert res["rms"] <= 1.3 * res["crb_rms"], (res["rms"], res["crb_rms"])
