"""Benchmark of the film correction (docs/benchmarks.md; --accuracy: docs/accuracy.md).

    .venv/bin/python tools/bench_correct.py [--points 2000000] [--repeat 7] [--json OUT.json]

Measures, on a Rollei 6006 (11 x 11 reseau, 100-quad homography mesh, Brown k1 distortion)
with a 40 um smooth film deformation from the synthetic truth mapping at 2400 dpi:

* pixel -> photo mm, vectorised, N points (target >= 5 M points/s);
* pixel -> photo mm, one point at a time (the plotter's cycle; target <= 20 us);
* film -> pixel, vectorised;
* resampling a 2400 dpi scan (5527 x 5532 px, uint8) onto the film grid at the scan's pixel
  size: maps + one cv2.remap (target <= 1.5 s);
* building the mesh and the leave-one-out / checkerboard comparison of all methods.

Medians of ``--repeat`` runs. The scan content does not matter for the speed, so the image is
random noise and the marks come from the truth mapping (no rendering).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time

import numpy as np

from softplot.camera import load_camera
from softplot.correction import FilmCorrection, resample
from softplot.geometry.crossval import cross_validate
from softplot.geometry.models import ReferenceMarks
from softplot.synthetic import Deformation, Scanner, TruthMapping

DPI = 2400.0


def _setup():
    cam = load_camera("rollei-6006")
    rng = np.random.default_rng(0)
    s = DPI / 25.4
    w, h = cam.format_mm
    tm = TruthMapping(
        Deformation.random(cam.format_mm, 40.0, 120.0, rng),
        Scanner(DPI, 0.8, 300.0, (w / 2 + 1) * s + 20, (h / 2 + 1) * s - 15),
    )
    R = cam.reseau
    film = R.film().reshape(R.rows, R.cols, 2)
    marks = ReferenceMarks(film, tm.film_to_pixel(film))
    size = (int(round((w + 2) * s)) + 60, int(round((h + 2) * s)) + 60)
    return cam, tm, marks, size


_CPU: dict = {}


def _median_time(fn, repeat, key=None):
    """Median wall time; the median process CPU time goes to ``_CPU[key]``.

    On a machine shared with other jobs the wall time of a single-threaded run stretches
    while its CPU time does not: both are reported.
    """
    ts, cs = [], []
    for _ in range(repeat):
        c = time.process_time()
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
        cs.append(time.process_time() - c)
    if key:
        _CPU[key] = statistics.median(cs)
    return statistics.median(ts)


def accuracy(seeds=range(6), noise=(0.0, 0.01, 0.03, 0.1), detector=False) -> None:
    """Error budget (docs/accuracy.md): film error (um RMS) per method and mark noise.

    Points: 20000 uniform over the whole 56 x 56 mm format ("all") and those inside the
    reseau ("in"); truth mapping with a 40 um smooth deformation; marks exact plus Gaussian
    noise of ``noise`` px (2400 dpi: 1 px = 10.58 um), or measured by the detector on a
    rendered scan (``detector=True``).
    """
    from softplot.geometry.models import METHODS, build_model

    cam = load_camera("rollei-6006")
    R = cam.reseau
    film = R.film().reshape(R.rows, R.cols, 2)
    q = np.random.default_rng(7).uniform(-28, 28, (20000, 2))
    print("method            noise_px  rms_all_um  rms_in_um  max_in_um  (median over seeds)")
    for method in METHODS[1:]:
        for sig in noise:
            rows = []
            for seed in seeds:
                rng = np.random.default_rng(seed)
                tm = TruthMapping(
                    Deformation.random(cam.format_mm, 40.0, rng.uniform(-200, 200), rng),
                    Scanner(DPI, rng.uniform(-3, 3), rng.uniform(-800, 800), 2700, 2680),
                )
                px = tm.film_to_pixel(film)
                px = px + np.random.default_rng(100 + seed).normal(0, sig, px.shape)
                m = build_model(method, ReferenceMarks(film, px))
                f, fl = m.pixel_to_film(tm.film_to_pixel(q))
                e = np.hypot(*(f - q).T) * 1000
                rows.append((np.sqrt(np.mean(e**2)), np.sqrt(np.mean(e[fl == 0] ** 2)),
                             e[fl == 0].max()))
            r = np.median(np.array(rows), axis=0)
            print(f"{method:<17} {sig:8.2f}  {r[0]:10.3f}  {r[1]:9.3f}  {r[2]:9.3f}")
    if detector:
        from softplot.correction import marks_from_detection
        from softplot.marks import detect
        from softplot.synthetic import ScanSpec, render_scan

        print("detector: dpi seed  det_rms_px  mesh_rms_all_um  noise_free_rms_all_um")
        for dpi in (1200.0, 2400.0):
            for seed in (1, 2):
                spec = ScanSpec(dpi=dpi, scene="texture", deform_um=40, rotation_deg=0.8,
                                anisotropy_ppm=500, noise_sigma=0.01, blur_sigma_px=0.8)
                img, truth = render_scan(cam, spec, seed=seed)
                tm = TruthMapping.from_truth(truth)
                det = detect(img, cam, dpi=dpi).to_json()
                mk = marks_from_detection(cam, det)
                ok = np.all(np.isfinite(mk.grid_pixel), axis=2)
                d = mk.grid_pixel[ok] - tm.film_to_pixel(mk.grid_film[ok])
                fc = FilmCorrection(cam, mk)
                f, _ = fc.pixel_to(tm.film_to_pixel(q))
                fc0 = FilmCorrection(cam, ReferenceMarks(film, tm.film_to_pixel(film)))
                f0, _ = fc0.pixel_to(tm.film_to_pixel(q))
                print(f"          {dpi:5.0f} {seed:4d}  {np.sqrt(np.mean((d**2).sum(1))):10.4f}"
                      f"  {np.sqrt(np.mean(((f - q) ** 2).sum(1))) * 1000:15.3f}"
                      f"  {np.sqrt(np.mean(((f0 - q) ** 2).sum(1))) * 1000:21.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--json", default=None)
    ap.add_argument("--accuracy", action="store_true",
                    help="print the error budget table of docs/accuracy.md instead")
    ap.add_argument("--detector", action="store_true",
                    help="with --accuracy: also render scans and measure with the detector")
    a = ap.parse_args()
    if a.accuracy:
        accuracy(detector=a.detector)
        return

    cam, tm, marks, size = _setup()
    res = {}
    t_build = _median_time(lambda: FilmCorrection(cam, marks, "mesh", size), a.repeat)
    fc = FilmCorrection(cam, marks, "mesh", size)
    assert fc.method == "mesh-homography" and fc.model.mesh.n_cells == 100
    res["mesh_build_ms"] = t_build * 1e3

    rng = np.random.default_rng(1)
    q = rng.uniform(-28, 28, (a.points, 2))
    p = tm.film_to_pixel(q)
    fc.pixel_to(p[:1000], "photo")  # warm up
    mesh = fc.model.mesh
    post = fc.interior.film_to_photo_xy
    t = _median_time(lambda: fc.pixel_to(p, "photo"), a.repeat)
    res["pixel_to_photo_Mpts_per_s"] = a.points / t / 1e6
    t = _median_time(
        lambda: mesh.pixel_to_film(p, post, fc.bounds, threads=1), a.repeat, "one_thread"
    )
    res["pixel_to_photo_1thread_Mpts_per_s"] = a.points / t / 1e6
    res["pixel_to_photo_1thread_cpu_Mpts_per_s"] = a.points / _CPU["one_thread"] / 1e6
    t = _median_time(lambda: fc.model.film_to_pixel(q), a.repeat)
    res["film_to_pixel_Mpts_per_s"] = a.points / t / 1e6

    pts = [tuple(v) for v in p[:20000].tolist()]
    f1 = fc.pixel_to_photo_point

    def singles():
        for x, y in pts:
            f1(x, y)

    singles()
    t = _median_time(singles, a.repeat, "single")
    res["single_point_us"] = t / len(pts) * 1e6
    res["single_point_cpu_us"] = _CPU["single"] / len(pts) * 1e6

    img = np.random.default_rng(2).integers(0, 256, (size[1], size[0]), dtype=np.uint8)
    ps = 25.4 / DPI
    out = resample(img, fc, ps)
    t = _median_time(lambda: resample(img, fc, ps), a.repeat, "resample")
    res["resample_s"] = t
    res["resample_cpu_s"] = _CPU["resample"]
    res["resample_in"] = f"{size[0]} x {size[1]} uint8"
    res["resample_out"] = f"{out.image.shape[1]} x {out.image.shape[0]}"

    t = _median_time(lambda: cross_validate(marks), max(1, a.repeat // 3))
    res["compare_all_methods_s"] = t

    res["machine"] = f"{platform.processor() or platform.machine()}, {os.cpu_count()} cpu"
    res["load_average_1min"] = os.getloadavg()[0]
    res["points"] = a.points
    res["repeat"] = a.repeat
    w = max(len(k) for k in res)
    for k, v in res.items():
        print(f"{k:<{w}}  {v:.3f}" if isinstance(v, float) else f"{k:<{w}}  {v}")
    if a.json:
        with open(a.json, "w", encoding="utf-8") as fh:
            json.dump(res, fh, indent=1)


if __name__ == "__main__":
    main()
