"""Benchmark of ``softplot batch``: scans per second with 1 and 2 dask workers.

Usage::

    .venv/bin/python tools/bench_batch.py [--scans 10] [--dpi 600] [--repeat 1]

Renders ``--scans`` synthetic Rollei 6006 scans (texture scene, film deformation, scanner
rotation; not timed), then runs :func:`softplot.pipeline.batch.run_batch` with the task
:func:`softplot.pipeline.process.process_scan` (detection, cross-validation of every
correction method, QC, per-scan JSON) on a fresh output folder with a LocalCluster of 1 and
of 2 single-threaded worker processes. Reported per case: the median wall time of the whole
batch (cluster start-up included) and scans per second, and for reference the serial
in-process figure (:func:`softplot.pipeline.process.process_scans`).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scans", type=int, default=10)
    ap.add_argument("--dpi", type=float, default=600.0)
    ap.add_argument("--repeat", type=int, default=1)
    a = ap.parse_args()

    from softplot.pipeline.batch import run_batch
    from softplot.pipeline.process import process_scan, process_scans
    from softplot.synthetic import ScanSpec, write_scan

    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / "scans"
        scans = []
        for i in range(a.scans):
            spec = ScanSpec(dpi=a.dpi, scene="texture", deform_um=15, shrink_ppm=100,
                            rotation_deg=0.4 * ((i % 5) - 2))
            scans.append(write_scan(src, "rollei-6006", spec, seed=100 + i, stem=f"s{i:03d}")[0])
        kw = {"camera": "rollei-6006"}
        rows = []
        cases = [("serial, in-process", None), ("dask LocalCluster, 1 worker", 1),
                 ("dask LocalCluster, 2 workers", 2)]
        for name, workers in cases:
            times = []
            for r in range(a.repeat):
                out = Path(tmp) / f"out-{workers}-{r}"
                t0 = time.perf_counter()
                if workers is None:
                    rep = process_scans(scans, out, progress=False, **kw)
                else:
                    rep = run_batch(scans, out, process_scan, kw, workers=workers,
                                    progress=False)
                times.append(time.perf_counter() - t0)
                if rep.done != len(scans):
                    raise SystemExit(f"{name}: {rep.failed} scans failed:\n{rep.table()}")
            t = statistics.median(times)
            rows.append((name, t, len(scans) / t))
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"# {platform.python_version()}, {os.cpu_count()} cores, load average {load:.1f}; "
          f"{a.scans} scans at {a.dpi:.0f} dpi, median of {a.repeat}")
    print("| case | wall s | scans/s |")
    print("|---|---|---|")
    for name, t, sps in rows:
        print(f"| {name} | {t:.1f} | {sps:.2f} |")


if __name__ == "__main__":
    main()
