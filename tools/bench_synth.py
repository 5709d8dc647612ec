#!/usr/bin/env python3
"""Benchmark the synthetic scan renderer (median wall time of ``render_scan``).

Usage::

    .venv/bin/python tools/bench_synth.py [--repeat 5] [--big]

Cases: a Rollei 6006 scan at 1200 and 2400 dpi with the default spec (texture scene, 20 um
deformation, noise), the same without deformation (no curvature term), and with ``--big``
a 9 x 9 inch aerial frame at 12 micrometres (2117 dpi, about 19000 x 19000 px, 8 bit).
"""

from __future__ import annotations

import argparse
import statistics
import time
import tracemalloc

from softplot.synthetic import ScanSpec, render_scan

CASES = [
    ("rollei-6006 1200 dpi, default spec", "rollei-6006", ScanSpec(dpi=1200)),
    ("rollei-6006 2400 dpi, default spec", "rollei-6006", ScanSpec(dpi=2400)),
    ("rollei-6006 2400 dpi, no deformation", "rollei-6006", ScanSpec(dpi=2400, deform_um=0)),
    ("rollei-6006 2400 dpi, empty scene", "rollei-6006", ScanSpec(dpi=2400, scene="none")),
    ("rollei-6006 1200 dpi, busy, dust, 16 bit", "rollei-6006",
     ScanSpec(dpi=1200, scene="busy", dust=50, scratches=3, bits=16)),
]
BIG = ("zeiss-rmk-a-15-23 2117 dpi (12 um), 8 bit", "zeiss-rmk-a-15-23",
       ScanSpec(dpi=25.4 / 0.012, scene="texture"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--big", action="store_true", help="also the 19000 x 19000 px aerial scan")
    args = ap.parse_args()
    cases = CASES + ([BIG] if args.big else [])
    for label, cam, spec in cases:
        big = spec.dpi > 2000 and cam.startswith("zeiss")
        n = 1 if big else args.repeat
        if not big:
            render_scan(cam, spec, seed=0)  # warm-up (imports, caches)
        times = []
        for i in range(n):
            t = time.perf_counter()
            img, _ = render_scan(cam, spec, seed=i + 1)
            times.append(time.perf_counter() - t)
        shape = img.shape
        del img
        tracemalloc.start()  # an extra, untimed run for the peak of numpy allocations
        render_scan(cam, spec, seed=99)
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        med = statistics.median(times)
        print(f"{label:45s} {shape[1]:6d} x {shape[0]:<6d} median {med:6.2f} s"
              f"  (n={n}, min {min(times):.2f} s, traced peak {peak / 1e6:.0f} MB)")

if __name__ == "__main__":
    main()
