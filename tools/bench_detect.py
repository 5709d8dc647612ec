#!/usr/bin/env python
"""Benchmark ``softplot detect`` (issue 3, point 7): speed and peak memory.

Writes its inputs to a temporary folder first, then times N runs of *load + detect* in this
process and prints medians; peak memory is measured in a fresh subprocess per case
(``tracemalloc`` peak of Python/numpy allocations, and the growth of the resident-set
high-water mark ``VmHWM`` over the resident size after the imports, the mark being reset with
``/proc/self/clear_refs``), both as a multiple of the scan's pixel bytes.

Cases
-----
* ``rollei-2400``: synthetic Rollei 6006 scan, 121 crosses, 2400 dpi (about 5400 x 5400 px,
  8-bit grey, uncompressed TIFF).
* ``rollei-1200``: the same at 1200 dpi.
* ``aerial-19k``: a 19200 x 19200 px 8-bit scan (230 mm at 12 um) of a Zeiss RMK A 15/23
  frame: a smooth grey background with grain and the 8 fiducials (4 circle-dots, 4 crosses)
  stamped at known positions (the synthetic renderer would take minutes at this size).

Usage::

    .venv/bin/python tools/bench_detect.py [--runs 5] [--cases rollei-2400,rollei-1200,aerial-19k]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CASES = ("rollei-2400", "rollei-1200", "aerial-19k")


def make_inputs(d: Path, cases) -> dict:
    from softplot.synthetic import ScanSpec, write_scan

    out = {}
    for c in cases:
        if c.startswith("rollei"):
            dpi = float(c.split("-")[1])
            img, truth = write_scan(d, "rollei-6006", ScanSpec(dpi=dpi, rotation_deg=1.5),
                                    seed=7, stem=c)
            out[c] = (img, "rollei-6006")
        elif c == "aerial-19k":
            out[c] = (make_aerial(d / "aerial-19k.tif"), "zeiss-rmk-a-15-23")
    return out


def make_aerial(path: Path, size: int = 19200) -> Path:
    """A 19200^2 8-bit RMK scan (230.4 mm at 12 um) with 8 stamped fiducials, written block by
    block."""
    import tifffile

    from softplot.camera import load_camera
    from softplot.marks.template import fiducial_shape, render

    cam = load_camera("zeiss-rmk-a-15-23")
    dpi = 25.4 / 0.012
    ppm = dpi / 25.4
    rng = np.random.default_rng(0)
    tile = (150 + rng.normal(0, 3.0, (512, 512))).clip(0, 255).astype(np.uint8)
    centre = np.array([(size - 1) / 2 + 11.3, (size - 1) / 2 - 7.8])
    th = np.radians(0.3)
    R = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]) @ np.diag([1, -1])
    stamps = []
    for f in cam.fiducials:
        p = centre + ppm * (R @ [f.x, f.y])
        shp = fiducial_shape(f, ppm)
        ip = np.round(p).astype(int)
        A = np.linalg.inv(R)
        t = render(shp, 1.0, A=A, centre=tuple(p - ip))
        stamps.append((ip, t))
    data = np.memmap(path.with_suffix(".raw"), dtype=np.uint8, mode="w+", shape=(size, size))
    for r0 in range(0, size, 512):
        r1 = min(r0 + 512, size)
        row = np.tile(tile, (1, size // 512 + 1))[: r1 - r0, :size]
        data[r0:r1] = row
    for ip, t in stamps:
        h = t.shape[0] // 2
        ys, xs = slice(ip[1] - h, ip[1] + h + 1), slice(ip[0] - h, ip[0] + h + 1)
        blk = data[ys, xs].astype(np.float32)
        data[ys, xs] = np.clip(blk * (1 - t) + 40.0 * t, 0, 255).astype(np.uint8)
    data.flush()
    tifffile.imwrite(path, data, photometric="minisblack", resolution=(dpi, dpi),
                     resolutionunit="INCH")
    del data
    os.remove(path.with_suffix(".raw"))
    return path


def _status_kib(key: str) -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


def child(path: str, camera: str) -> None:
    """Run in a subprocess: one load + detect; print peak memory figures as JSON.

    The resident-set high-water mark is reset after the imports (``/proc/self/clear_refs``),
    so ``VmHWM - VmRSS(before)`` is the peak growth caused by loading and detecting
    (memory-mapped file pages that were touched count too).
    """
    import tracemalloc

    from softplot.io import load_scan
    from softplot.marks import detect

    try:
        Path("/proc/self/clear_refs").write_text("5")
        resettable = True
    except OSError:
        resettable = False
    before = _status_kib("VmRSS")
    tracemalloc.start()
    sc = load_scan(path)
    det = detect(sc, camera)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    hwm = _status_kib("VmHWM")
    print(json.dumps({"rss_growth": (hwm - before) * 1024 if resettable else None,
                      "traced_peak": peak, "pixel_bytes": int(sc.data.nbytes),
                      "measured": int(det.measured.sum()), "n": len(det)}))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.child:
        child(a.child[0], a.child[1])
        return
    cases = [c for c in a.cases.split(",") if c]
    from softplot.io import load_scan
    from softplot.marks import detect

    with tempfile.TemporaryDirectory(prefix="bench_detect_") as tmp:
        t0 = time.perf_counter()
        inputs = make_inputs(Path(tmp), cases)
        print(f"inputs written in {time.perf_counter() - t0:.1f} s to {tmp}")
        for c in cases:
            path, cam = inputs[c]
            times = []
            det = None
            for _ in range(a.runs + 1):  # the first run warms caches and is not counted
                t = time.perf_counter()
                sc = load_scan(path)
                det = detect(sc, cam)
                times.append(time.perf_counter() - t)
            times = times[1:]
            cmd = [sys.executable, __file__, "--child", str(path), cam]
            m = json.loads(subprocess.run(cmd, capture_output=True, text=True,
                                          check=True).stdout)
            px = m["pixel_bytes"]
            rss = m["rss_growth"]
            rss_txt = (f"RSS growth {rss / px:.2f}x ({rss / 2**20:.0f} MiB)" if rss is not None
                       else "RSS growth n/a")
            print(f"{c:12s} {sc.width}x{sc.height} px  median {statistics.median(times):.3f} s "
                  f"(min {min(times):.3f}, n={len(times)})  measured {det.measured.sum()}/"
                  f"{len(det)}  peak traced {m['traced_peak'] / px:.2f}x pixel bytes, "
                  f"{rss_txt}, pixels {px / 2**20:.0f} MiB")
            stages = {k: round(v, 3) for k, v in det.timings.items()}
            print(f"{'':12s} stages (cumulative s): {stages}")


if __name__ == "__main__":
    main()
