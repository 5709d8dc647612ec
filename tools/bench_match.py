"""Benchmark of automatic matching, epipolar resampling and the DSM on a 2400 dpi Rollei pair.

Usage::

    PYTHONPATH=src OPENBLAS_NUM_THREADS=1 python tools/bench_match.py [--dpi 2400]
        [--work /tmp/bench-match] [--repeat 3]

The pair (the ``softplot demo`` Rollei 6006 geometry over a textured hill, rendered with
exact ray casting) and its mark detections are written once into ``--work`` and reused.
Each stage runs ``--repeat`` times in a fresh process (so that peak memory is the stage's
own); printed: median wall time, the peak resident memory growth over the process after
loading the scans (RSS; the memory-mapped scans are read once before, so their pages count
as loaded), in MB and in multiples of one scan's pixel bytes.

Stages: ``match`` (softplot match: overviews, SIFT, RANSAC, least-squares matching,
relative orientation; marks given), ``epipolar`` (both normalised images at the scan pixel,
maps kept), ``dsm`` (the DSM at 5x the scan pixel's ground size; also printed, measured
after the time and memory: its height RMS against the exact surface and the RMS of the
errors over the stated precision).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _rss_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return float(line.split()[1]) / 1024.0
    return float("nan")


def _cpu_s() -> float:
    """CPU seconds (user + system) of this process so far: less sensitive than the wall
    time to other jobs on a shared machine."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def prepare(work: Path, dpi: float) -> None:
    sys.path.insert(0, str(HERE.parent / "tests"))
    from matching_scenes import make_scene, true_session

    t = time.perf_counter()
    sc = make_scene(str(work / "scene"), dpi)
    true_session(sc, work / "session")
    print(f"scene ready in {time.perf_counter() - t:.0f} s ({work})", file=sys.stderr)


def stage(name: str, work: Path, dpi: float) -> dict:
    import numpy as np

    from softplot.cli.epipolar import open_session
    from softplot.io import load_scan

    scene = work / "scene"
    if name == "match":
        from softplot.cli.match import load_pair
        from softplot.matching.ties import match_pair

        scans = [load_scan(scene / f"{s}.tif") for s in ("left", "right")]
        [s.pixels for s in scans]
        base, peak0 = _rss_mb(), _peak_mb()
        t = time.perf_counter()
        _, _, maps = load_pair(scene / "left.tif", scene / "right.tif", "rollei-6006",
                               scene / "left.detection.json", scene / "right.detection.json")
        r = match_pair(scans[0], scans[1], maps[0], maps[1])
        dt = time.perf_counter() - t
        extra = {"ties": r.n, "rms_px": r.rms_px}
        nbytes = scans[0].data.nbytes
    else:
        s, maps, scans = open_session(work / "session")
        imgs = [np.asarray(x.data) for x in scans]
        # the scans are memory-mapped: read them once so that their pages count as loaded
        [int(a.sum(dtype=np.uint64)) for a in imgs]
        base, peak0 = _rss_mb(), _peak_mb()
        t, c0 = time.perf_counter(), _cpu_s()
        if name == "epipolar":
            from softplot.matching.epipolar import resample_pair

            geo, out, _ = resample_pair(s.model, maps, imgs)
            extra = {"size": [geo.cols[0], geo.cols[1], geo.rows]}
        else:
            from softplot.matching.dsm import dense_surface

            gsd = 5 * 25.4 / dpi / 1000.0 * (s.model.left.X0[2] - 230.0) / s.model.left.c * 1000
            d = dense_surface(s.model, maps, imgs, gsd)
            extra = {"gsd_m": gsd, "cells_valid": d.info["cells_valid"]}
        dt = time.perf_counter() - t
        extra["cpu_s"] = round(_cpu_s() - c0, 2)
        nbytes = imgs[0].nbytes
    grow = max(_peak_mb(), _rss_mb()) - base
    if name == "dsm":  # against the exact surface (after the time and memory are taken)
        sys.path.insert(0, str(HERE.parent / "tests"))
        from matching_scenes import make_scene

        sc = make_scene(str(scene), dpi)
        X, Y = d.centres()
        v = np.isfinite(d.Z)
        err = (d.Z - sc.terrain[0].surface(X, Y))[v]
        extra.update({"cells_interpolated": d.info.get("cells_interpolated", 0),
                      "height_rms_m": round(float(np.sqrt(np.mean(err**2))), 4),
                      "err_over_sigma_rms": round(float(np.sqrt(np.mean((err / d.sigma[v])**2))),
                                                  3)})
    return {"stage": name, "seconds": dt, "rss_growth_mb": grow,
            "scan_mb": nbytes / 2**20, "x_scan": grow / (nbytes / 2**20),
            "peak_before_mb": peak0, **extra}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dpi", type=float, default=2400.0)
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench-match"))
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--stage", help=argparse.SUPPRESS)
    ap.add_argument("--stages", default="match,epipolar,dsm")
    a = ap.parse_args()
    if a.stage:
        print(json.dumps(stage(a.stage, a.work, a.dpi)))
        return
    prepare(a.work, a.dpi)
    for name in a.stages.split(","):
        runs = []
        for _ in range(a.repeat):
            out = subprocess.run([sys.executable, __file__, "--stage", name, "--work",
                                  str(a.work), "--dpi", str(a.dpi)], capture_output=True,
                                 text=True, env=os.environ, check=True)
            runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
        med = {k: statistics.median(r[k] for r in runs) for k in ("seconds", "rss_growth_mb",
                                                                   "x_scan")}
        skip = ("stage", "seconds", "rss_growth_mb", "x_scan", "scan_mb", "peak_before_mb")
        extra = {k: v for k, v in runs[0].items() if k not in skip}
        if all("cpu_s" in r for r in runs):
            extra["cpu_s"] = statistics.median(r["cpu_s"] for r in runs)
        print(f"{name:9s} median {med['seconds']:.2f} s, peak RSS growth "
              f"{med['rss_growth_mb']:.0f} MB = {med['x_scan']:.1f} x one scan "
              f"({runs[0]['scan_mb']:.0f} MB); {json.dumps(extra)}", flush=True)


if __name__ == "__main__":
    main()
