"""Benchmark of the plotter loop and of the GRBL serial round trip.

Usage::

    .venv/bin/python tools/bench_plotter.py [--cycles 20000] [--serial 300]

1. Plotter cycle (operator input -> restitution -> DX/DY command through the Motors
   interface) with VirtualMotors, in contour and single-point mode, without and with affine
   film corrections (numpy callables). Target: median <= 100 us (the STEREOBIT/20 took 20 ms).
2. Round trip through GrblMotors over the simulated serial line (pty, pyserial): a status
   query ``?`` -> ``<...>``, a motion line ``G90G1..`` -> ``ok``, and the plotter's own
   command ``move_to(wait=False)`` (char-count streaming: returns once the line is written).

Prints median, 10th and 99th percentiles in microseconds.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from softplot.motors import AxisConfig, VirtualMotors
from softplot.stereo import OrientedPhoto, Plotter, StereoModel
from softplot.synthetic.stereo import aerial_pair


def _model(t, corrections):
    photos = []
    for k in range(2):
        f2p, p2f = t.corrections(k) if corrections else (None, None)
        photos.append(OrientedPhoto(t.X0[k], t.angles[k], t.c[k], t.x0[k], t.y0[k], f2p, p2f))
    return StereoModel(*photos)


def _stats(ts):
    us = np.asarray(ts) * 1e6
    return np.median(us), np.percentile(us, 10), np.percentile(us, 99)


def bench_cycle(n: int, mode: str, corrections: bool):
    t = aerial_pair(seed=1, deform=corrections)
    ax = AxisConfig(resolution_mm=0.01, min_mm=-150, max_mm=150)
    mot = VirtualMotors(ax, ax)
    pl = Plotter(_model(t, corrections), mot, mode=mode, height=300.0)
    C = t.contour_truth(300.0, 256)
    rf, lf = t.film(1, C), t.film(0, C)
    ts = np.empty(n)
    perf = time.perf_counter
    for i in range(n):
        j = i % 256
        X, Y = float(rf[j, 0]), float(rf[j, 1])
        px = float(lf[j, 0]) - X
        t0 = perf()
        if mode == "single":
            pl.cycle(X, Y, px)
        else:
            pl.cycle(X, Y)
        ts[i] = perf() - t0
    return _stats(ts)


def bench_serial(n: int):
    from softplot.motors.grbl import GrblMotors
    from softplot.motors.simulator import GrblSimulator

    with GrblSimulator(time_scale=1000.0) as sim, GrblMotors(sim.path, timeout=2) as m:
        st = []
        for _ in range(n):
            t0 = time.perf_counter()
            m.status()
            st.append(time.perf_counter() - t0)
        rt = []
        for i in range(n):
            t0 = time.perf_counter()
            m.command(f"G90G1X{0.01 * (i % 50):.3f}Y0F600", sync=False)
            rt.append(time.perf_counter() - t0)
            m.wait(timeout=5)
        mv = []
        for i in range(n):
            t0 = time.perf_counter()
            m.move_to(0.01 * (i % 50) + 0.005, 0.0, wait=False)
            mv.append(time.perf_counter() - t0)
            m.wait(timeout=5)
        return _stats(st), _stats(rt), _stats(mv)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cycles", type=int, default=20000)
    ap.add_argument("--serial", type=int, default=300)
    a = ap.parse_args()
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, "
        f"{platform.machine()}, numpy {np.__version__}"
    )
    print("| case | median us | p10 us | p99 us |")
    print("|---|---|---|---|")
    for mode in ("contour", "single"):
        for corr in (False, True):
            med, p10, p99 = bench_cycle(a.cycles, mode, corr)
            label = f"cycle {mode}, {'affine film correction' if corr else 'no film correction'}"
            print(f"| {label} | {med:.1f} | {p10:.1f} | {p99:.1f} |")
    st, rt, mv = bench_serial(a.serial)
    for label, (med, p10, p99) in (
        ("GRBL status round trip (? -> <..>)", st),
        ("GRBL motion line round trip (G1 -> ok)", rt),
        ("GrblMotors.move_to(wait=False), char-count streaming", mv),
    ):
        print(f"| {label} | {med:.0f} | {p10:.0f} | {p99:.0f} |")


if __name__ == "__main__":
    main()
