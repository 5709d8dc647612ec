"""Benchmark of the sparse bundle adjustment (figures go to docs/benchmarks.md).

Run:  .venv/bin/python tools/bench_bundle.py [--repeat 3] [--json out.json] [--quick]

1. BAL Ladybug (problem-49-7776-pre): seconds from the given start to convergence (Ceres
   default tolerances) and to the first cost <= 1.34e4, final cost, iterations.
2. Synthetic 100-model aerial block (5 strips x 21 photos, 60 % / 30 % overlap) with
   self-calibration (c, x0, y0, k1 free): seconds of the adjustment incl. covariance blocks.
3. Growth of the time with the block size: 10, 100 and 400 photos (same generator).
4. Blocks of thousands (``--large``): 500, 1000 and 2000 photos (10 strips x 50, 100, 200;
   and 20 strips x 100) with
   self-calibration, default covariance (``auto``: the interior orientation only above 8000
   camera-side unknowns), time of ``bundle_adjust`` and, in a separate run, its peak
   traced memory (tracemalloc).

Medians over ``--repeat`` runs. The machine is shared: say so when quoting the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np

from softplot.adjust.bal import read_bal, solve_bal
from softplot.orientation.bundle import bundle_adjust
from softplot.orientation.bundle_init import initialize
from softplot.synthetic.block import make_block

LADYBUG = Path(__file__).resolve().parents[2] / "shared/data/bal/problem-49-7776-pre.txt"


def bench_bal(repeat: int) -> dict:
    prob = read_bal(LADYBUG)
    runs = []
    cpu = []
    for _ in range(repeat):
        c0 = time.process_time()
        r = solve_bal(prob)
        cpu.append(time.process_time() - c0)
        hit = next((h["seconds"] for h in r.history if h["cost"] <= 1.34e4), None)
        runs.append((r.seconds, hit, r.final_cost, r.iterations))
    return {
        "median_cpu_seconds": statistics.median(cpu),
        "problem": LADYBUG.name,
        "median_seconds": statistics.median(x[0] for x in runs),
        "median_seconds_to_1.34e4": statistics.median(x[1] for x in runs if x[1] is not None),
        "final_cost": runs[0][2],
        "iterations": runs[0][3],
        "runs": runs,
    }


def _block(strips, photos, seed=0):
    net = make_block(n_strips=strips, photos_per_strip=photos, seed=seed)
    net.intr_given[0, :3] = [152.0, 0.0, 0.0]
    net.intr_given[0, 3] = 0.0
    d = net.to_bundle_data(free=("c", "x0", "y0", "k1"))
    initialize(d)
    return net, d


def bench_block(strips, photos, repeat: int, memory: bool = False) -> dict:
    import copy
    import tracemalloc

    net, d0 = _block(strips, photos)
    times, lm, cpu = [], [], []
    res = None
    peak = None
    if memory:  # peak memory in a separate run: tracing slows the allocations down
        tracemalloc.start()
        bundle_adjust(copy.deepcopy(d0))
        peak = tracemalloc.get_traced_memory()[1] / 2**20
        tracemalloc.stop()
    for _ in range(repeat):
        d = copy.deepcopy(d0)
        t0, c0 = time.perf_counter(), time.process_time()
        res = bundle_adjust(d)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
        lm.append(res.seconds)
    return {
        "median_cpu_seconds": statistics.median(cpu),
        "photos": len(d.photo_names),
        "models": net.info["n_models"],
        "points": len(d.point_names),
        "observations": int(d.obs_photo.size),
        "median_seconds": statistics.median(times),
        "median_lm_seconds": statistics.median(lm),
        "iterations": res.iterations,
        "sigma0": res.sigma0,
        "check_rms_m": res.check_rms(),
        "peak_traced_mib": peak,
        "intrinsics_std": res.intrinsics_std[0, :4].tolist(),
    }


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", default=None)
    ap.add_argument("--quick", action="store_true", help="skip the 400-photo block")
    ap.add_argument("--large", action="store_true", help="only the 500-2000 photo blocks")
    a = ap.parse_args(argv)
    out = {
        "machine": f"{platform.machine()}, {os.cpu_count()} cores, {platform.python_version()}",
        "load_average_at_start": os.getloadavg(),
    }
    if a.large:
        large = []
        for strips, photos in [(10, 50), (10, 100), (10, 200), (20, 100)]:
            g = bench_block(strips, photos, a.repeat, memory=True)
            large.append(g)
            print(
                f"  {g['photos']:4d} photos {g['observations']:6d} obs: "
                f"{g['median_seconds']:.2f} s (CPU {g['median_cpu_seconds']:.2f} s, LM "
                f"{g['median_lm_seconds']:.2f} s, {g['iterations']} it, peak "
                f"{g['peak_traced_mib']:.0f} MiB traced)"
            )
        out["large"] = large
        out["load_average_at_end"] = os.getloadavg()
        if a.json:
            Path(a.json).write_text(json.dumps(out, indent=1, default=float) + "\n")
        return out
    if LADYBUG.is_file():
        out["bal_ladybug"] = bench_bal(a.repeat)
        b = out["bal_ladybug"]
        print(
            f"BAL ladybug: {b['median_seconds']:.2f} s (CPU {b['median_cpu_seconds']:.2f} s) "
            "to convergence "
            f"({b['median_seconds_to_1.34e4']:.2f} s to <= 1.34e4), final cost "
            f"{b['final_cost']:.6g}, {b['iterations']} iterations"
        )
    out["block_100_models"] = bench_block(5, 21, a.repeat)
    b = out["block_100_models"]
    print(
        f"100-model block, self-calibration: {b['median_seconds']:.2f} s "
        f"(CPU {b['median_cpu_seconds']:.2f} s) "
        f"({b['photos']} photos, {b['observations']} observations, {b['iterations']} it)"
    )
    growth = []
    for strips, photos in [(2, 5), (5, 20)] + ([] if a.quick else [(10, 40)]):
        g = bench_block(strips, photos, a.repeat)
        growth.append(g)
        print(
            f"  {g['photos']:4d} photos {g['observations']:6d} obs: {g['median_seconds']:.3f} s "
            f"(CPU {g['median_cpu_seconds']:.3f} s, LM {g['median_lm_seconds']:.3f} s, "
            f"{g['iterations']} it)"
        )
    out["growth"] = growth
    out["load_average_at_end"] = os.getloadavg()
    if a.json:
        Path(a.json).write_text(json.dumps(out, indent=1, default=float) + "\n")
    return out


if __name__ == "__main__":
    np.seterr(all="ignore")
    main()
