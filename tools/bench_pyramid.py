"""Benchmark: building the viewer's image pyramid of a large 16-bit scan.

Writes a synthetic ``N x N`` uint16 uncompressed TIFF (default 19 000 px: an aerial frame
scanned at about 12 um, 722 MB), then builds its pyramid (``softplot.ui.pyramid``) ``--runs``
times into fresh cache folders, with the content hash given (as ``softplot view`` has it from
the session; hashing is reported apart). Reports the median wall time, seconds per gigapixel,
and the peak anonymous memory (RssAnon: the process's own allocations; the memory-mapped scan
is page cache, shared and reclaimable) against the scan's size.

    OPENBLAS_NUM_THREADS=1 python tools/bench_pyramid.py [--size 19000] [--runs 3]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import tifffile


def _rss_anon() -> int:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) * 1024
    return 0


class Peak:
    def __init__(self):
        self.peak, self.stop = _rss_anon(), False
        self.t = threading.Thread(target=self.run, daemon=True)

    def run(self):
        while not self.stop:
            self.peak = max(self.peak, _rss_anon())
            time.sleep(0.005)

    def __enter__(self):
        self.base = _rss_anon()
        self.t.start()
        return self

    def __exit__(self, *a):
        self.stop = True
        self.t.join()


def write_scan(path: Path, n: int) -> None:
    m = tifffile.memmap(path, shape=(n, n), dtype=np.uint16, photometric="minisblack",
                        resolution=(2117.0, 2117.0), resolutionunit="INCH")
    x = np.arange(n, dtype=np.float32)
    rng = np.random.default_rng(0)
    for r0 in range(0, n, 1024):
        r = np.arange(r0, min(r0 + 1024, n), dtype=np.float32)[:, None]
        band = 20000 + 15000 * np.sin(x / 370.0) * np.cos(r / 290.0)
        band += rng.normal(0, 800, band.shape).astype(np.float32)
        m[r0:r0 + len(r)] = np.clip(band, 0, 65535).astype(np.uint16)
    m.flush()
    del m


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=19000)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--tile", type=int, default=256)
    a = ap.parse_args()
    from softplot.io import fingerprint
    from softplot.ui.pyramid import build_pyramid

    tmp = Path(tempfile.mkdtemp(prefix="bench-pyramid-"))
    try:
        scan = tmp / "scan.tif"
        write_scan(scan, a.size)
        nbytes = a.size * a.size * 2
        t0 = time.perf_counter()
        sha = fingerprint(scan)["sha256"]
        t_hash = time.perf_counter() - t0
        times, peaks = [], []
        for k in range(a.runs):
            with Peak() as pk:
                t0 = time.perf_counter()
                pyr = build_pyramid(scan, tmp / f"cache{k}", sha256=sha, tile=a.tile)
                times.append(time.perf_counter() - t0)
            peaks.append(pk.peak - pk.base)
            levels = len(pyr.sizes)
            del pyr
        gp = a.size * a.size / 1e9
        med = statistics.median(times)
        print(f"scan {a.size} x {a.size} uint16 ({nbytes / 1e6:.0f} MB, {gp:.3f} gigapixel), "
              f"{levels} levels, tile {a.tile}")
        print(f"build: median {med:.2f} s of {a.runs} ({', '.join(f'{t:.2f}' for t in times)})"
              f" = {med / gp:.2f} s per gigapixel")
        print(f"peak anonymous memory above start: {max(peaks) / 1e6:.0f} MB = "
              f"{max(peaks) / nbytes:.2f} x the scan's bytes")
        print(f"content hash (sha256, once per scan; the session records it): {t_hash:.2f} s")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
