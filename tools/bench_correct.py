"""Benchmark of the film correction (issue 4, point 8).

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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=2_000_000)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--json", default=None)
    a = ap.parse_args()

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
