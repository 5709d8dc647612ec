"""Benchmark of the orientation core (softplot.adjust / softplot.orientation).

Usage::

    .venv/bin/python tools/bench_orientation.py [--repeat 30]

Cases (synthetic, exact truth plus 4 um noise):

1. space resection, 12 and 50 control points (P3P/SQPnP start + Gauss-Newton);
2. space intersection of 100 000 points from 3 photos in one vectorised call;
3. relative orientation (essential-matrix candidates + Gauss-Helmert), 30 and 300 points;
4. absolute orientation, 10 control points;
5. the dense Gauss-Markov engine alone on a 2 000 x 60 problem.

Prints the median and the 10th/90th percentiles of the wall time and the median CPU time of
the process, in milliseconds (on a shared machine the CPU time is the steadier figure). Run
with ``OPENBLAS_NUM_THREADS=1``: the problems are small and BLAS threads only contend.
"""

from __future__ import annotations

import argparse
import platform
import time

import numpy as np

from softplot.adjust import linear_least_squares
from softplot.geometry.collinearity import project
from softplot.geometry.rotation import rotation_matrix
from softplot.orientation import absolute_orientation, intersect, relative_orientation, resect
from softplot.orientation.absolute import transform

C = 152.0
SIG = 0.004


def _time(fn, repeat):
    ts, cpu = [], []
    for _ in range(repeat):
        t0 = time.perf_counter()
        c0 = time.process_time()
        fn()
        cpu.append(time.process_time() - c0)
        ts.append(time.perf_counter() - t0)
    ms = np.asarray(ts) * 1e3
    return np.median(ms), np.percentile(ms, 10), np.percentile(ms, 90), np.median(cpu) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=30)
    a = ap.parse_args()
    rng = np.random.default_rng(0)
    rows = []

    for n in (12, 50):
        X = np.c_[rng.uniform(-500, 500, (n, 2)), rng.uniform(0, 60, n)]
        X0 = np.array([20.0, -10.0, 1500.0])
        ang = np.array([0.03, -0.02, 1.1])
        xy = project(X, X0, rotation_matrix(*ang), C) + rng.normal(0, SIG, (n, 2))
        rows.append(
            (f"resection, {n} points", _time(lambda xy=xy, X=X: resect(xy, X, C), a.repeat))
        )

    P = 100_000
    X = np.c_[rng.uniform(400, 800, P), rng.uniform(-400, 400, P), rng.uniform(-30, 80, P)]
    X0s = np.array([[0.0, 0.0, 1500.0], [600.0, 10.0, 1510.0], [1200.0, -5.0, 1495.0]])
    angs = np.array([[0.01, -0.02, 0.03], [-0.02, 0.01, -0.04], [0.0, 0.03, 0.02]])
    xy = np.vstack([project(X, X0s[k], rotation_matrix(*angs[k]), C) for k in range(3)])
    xy += rng.normal(0, SIG, xy.shape)
    pt = np.tile(np.arange(P), 3)
    ph = np.repeat(np.arange(3), P)
    rows.append(
        (
            "intersection, 100 000 points x 3 rays",
            _time(lambda: intersect(xy, pt, ph, X0s, angs, C, sigma=SIG), max(3, a.repeat // 10)),
        )
    )

    for n in (30, 300):
        X = np.c_[rng.uniform(-60, 660, n), rng.uniform(-450, 450, n), rng.uniform(-40, 80, n)]
        xy1 = project(X, [0, 0, 1500.0], rotation_matrix(0.01, -0.02, 0.03), C)
        xy2 = project(X, [600.0, 15, 1512], rotation_matrix(-0.02, 0.01, -0.04), C)
        xy1 = xy1 + rng.normal(0, SIG, xy1.shape)
        xy2 = xy2 + rng.normal(0, SIG, xy2.shape)
        rows.append(
            (
                f"relative orientation, {n} points",
                _time(lambda a1=xy1, a2=xy2: relative_orientation(a1, a2, C, bx=100.0), a.repeat),
            )
        )

    truth = np.array([2.5, 0.03, -0.02, 1.9, 512300.0, 4987100.0, 240.0])
    m = np.c_[rng.uniform(-100, 300, 10), rng.uniform(-150, 150, 10), rng.uniform(-600, -540, 10)]
    obj = transform(truth, m) + rng.normal(0, 0.05, (10, 3))
    rows.append(
        (
            "absolute orientation, 10 points",
            _time(lambda: absolute_orientation(m, obj, 0.05), a.repeat),
        )
    )

    A = rng.normal(size=(2000, 60))
    l = A @ rng.normal(size=60) + rng.normal(0, 0.01, 2000)
    rows.append(
        (
            "Gauss-Markov engine, 2000 x 60 linear",
            _time(lambda: linear_least_squares(A, l, 0.01), a.repeat),
        )
    )

    print(f"python {platform.python_version()}, numpy {np.__version__}, {platform.machine()}")
    print(f"{'case':<42}{'median ms':>12}{'p10 ms':>10}{'p90 ms':>10}{'CPU ms':>10}")
    for name, (med, p10, p90, cpu) in rows:
        print(f"{name:<42}{med:>12.2f}{p10:>10.2f}{p90:>10.2f}{cpu:>10.2f}")


if __name__ == "__main__":
    main()
