#!/usr/bin/env python
"""Benchmark ``softplot detect``: speed and peak memory (docs/benchmarks.md, "Detection").

Writes its inputs to a temporary folder first, then times N runs of *load + detect* in this
process and prints medians (the first run is a warm-up and not counted). Peak memory is
measured in fresh subprocesses, one per figure, each as a multiple of the scan's pixel bytes
(``Scan.data.nbytes``):

* ``RSS fresh``: growth of the resident-set high-water mark ``VmHWM`` (reset through
  ``/proc/self/clear_refs`` after the imports) over ``VmRSS`` before loading, in a process
  that has imported softplot and nothing else: everything load + detect makes resident,
  including the pages of the scan file and the machine code of OpenCV, NumPy, OpenBLAS and
  SciPy that is paged in on first use (about 10 MB whatever the scan; shared, read-only);
* ``RSS scan``: the same after a warm-up detection on a small scan of the same camera (so the
  library code is resident before the mark is reset), plus the anonymous memory the warm-up
  left behind (which the measured run may have reused): an upper bound of the memory the scan
  itself costs, its pixels included. This is the figure held against the target "peak memory
  at most 3x the scan's pixel bytes";
* ``traced``: the ``tracemalloc`` peak of Python/NumPy allocations (not OpenCV's own buffers
  nor file pages).

Cases
-----
* ``rollei-2400``: synthetic Rollei 6006 scan, 121 crosses, 2400 dpi (about 5400 x 5400 px,
  8-bit grey, uncompressed TIFF).
* ``rollei-1200``: the same at 1200 dpi.
* ``rollei-1200-busy``, ``rollei-2400-busy``: the same over a busy scene (blocks, roads,
  discs): ``detect`` takes the joint scene estimate there (``scene="auto"``) for the crosses
  with a scene edge in their footprint (the other Rollei cases have the renderer's default
  texture).
* ``aerial-19k``: a 19200 x 19200 px 8-bit scan (230 mm at 12 um) of a Zeiss RMK A 15/23
  frame: a smooth grey background with grain and the 8 fiducials (4 circle-dots, 4 crosses)
  stamped at known positions (the synthetic renderer would take minutes at this size).

Busy scenes (``--busy``): the two busy cases timed in this process, load + detect each, with
the default ``scene="auto"`` (the joint scene estimate only for the crosses with a scene edge
in their footprint) and with ``scene="joint"`` (every cross), alternating; wall time (median,
min) and CPU time of the process (all threads); and ``softplot detect`` over ``--batch`` busy
1200 dpi scans in one process (a subprocess: interpreter start, imports and the compiled
kernels' loading included) against one scan per process, per scan.

One and two threads (``--threads-alternate``): the busy scans (default scene model) detected
in this process on one thread and on two, alternating detection by detection (both see the
same load of a shared machine); wall and CPU time of load + detect.

Stages (``--stages``): the busy scans' detection, wall and CPU time of each stage of
:mod:`softplot.marks.detect` (overview, lattice, prediction, mark geometry, width,
measurement, validation; CPU of the whole process, so on two threads both threads' time),
medians of ``--runs``.

Two versions (``--compare SRC``): the busy scans (``--scene texture``: the textured ones of
the default cases) detected by this checkout's code and by the code under ``SRC`` in two
worker processes side by side, alternating detection by detection (each warmed up on each
scan first), CPU and wall time of load + detect: on a machine shared with other work both
versions see the same load.

Usage::

    .venv/bin/python tools/bench_detect.py [--runs 5] [--cases rollei-2400,rollei-1200,aerial-19k]
    .venv/bin/python tools/bench_detect.py --busy [--runs 11] [--batch 8] [--threads 1]
    .venv/bin/python tools/bench_detect.py --compare OTHER/src [--runs 8] [--threads 1]
        [--scene texture]
    .venv/bin/python tools/bench_detect.py --threads-alternate [--runs 8]
    .venv/bin/python tools/bench_detect.py --stages [--runs 7] [--threads 2]
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

CASES = ("rollei-2400", "rollei-1200", "aerial-19k", "rollei-1200-busy", "rollei-2400-busy")


def make_inputs(d: Path, cases) -> dict:
    """Scans per case: ``{case: (path, camera, warm-up path)}``."""
    from softplot.synthetic import ScanSpec, write_scan

    out = {}
    warm = {}
    for c in cases:
        cam = "zeiss-rmk-a-15-23" if c == "aerial-19k" else "rollei-6006"
        if cam not in warm:  # a small scan of the same camera for the memory warm-up
            dpi = 100.0 if c == "aerial-19k" else 400.0
            warm[cam] = write_scan(d, cam, ScanSpec(dpi=dpi), seed=1, stem=f"warm-{cam}")[0]
        if c.startswith("rollei"):
            dpi = float(c.split("-")[1])
            scene = "busy" if c.endswith("-busy") else "texture"
            img, truth = write_scan(d, cam, ScanSpec(dpi=dpi, rotation_deg=1.5, scene=scene),
                                    seed=7, stem=c)
            out[c] = (img, cam, warm[cam])
        elif c == "aerial-19k":
            out[c] = (make_aerial(d / "aerial-19k.tif"), cam, warm[cam])
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


def child(path: str, camera: str, mode: str, warm: str) -> None:
    """Run in a fresh subprocess: one load + detect; print one memory figure as JSON.

    ``mode``: "fresh" (RSS high-water growth), "warm" (the same after a warm-up detection on
    ``warm``, plus the anonymous memory that warm-up left) or "traced" (tracemalloc peak).
    """
    import gc
    import tracemalloc

    from softplot.errors import SoftplotError
    from softplot.io import load_scan
    from softplot.marks import detect
    from softplot.runtime import tune_allocator

    tune_allocator()  # as the softplot command does
    if mode != "fresh":
        # the compiled LSM kernel (numba's JIT runtime and machine code, some 40 MiB, the same
        # for any scan) is library code: loaded before the measurement, like the imports
        from softplot.marks import kernels

        kernels.load()
    leftover = 0
    if mode == "warm":
        anon0 = _status_kib("RssAnon")
        try:
            detect(load_scan(warm), camera)
        except SoftplotError:
            pass
        gc.collect()
        leftover = max(_status_kib("RssAnon") - anon0, 0) * 1024
    try:
        Path("/proc/self/clear_refs").write_text("5")
        resettable = True
    except OSError:
        resettable = False
    before = _status_kib("VmRSS")
    if mode == "traced":
        tracemalloc.start()
    sc = load_scan(path)
    det = detect(sc, camera)
    if mode == "traced":
        value = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    else:
        value = (_status_kib("VmHWM") - before) * 1024 + leftover if resettable else None
    print(json.dumps({"value": value, "leftover": leftover, "pixel_bytes": int(sc.data.nbytes),
                      "measured": int(det.measured.sum()), "n": len(det)}))


def _memory(path, cam, warm) -> dict:
    out = {}
    for mode in ("fresh", "warm", "traced"):
        cmd = [sys.executable, __file__, "--child", str(path), cam, mode, str(warm)]
        out[mode] = json.loads(subprocess.run(cmd, capture_output=True, text=True,
                                              check=True).stdout)
    return out


def _fig(m: dict, k: str, px: int) -> str:
    v = m[k]["value"]
    return "n/a" if v is None else f"{v / px:.2f}x ({v / 2**20:.0f} MiB)"


def _load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def busy(runs: int, batch: int, n_threads: int | None = None) -> None:
    """The busy-scene figures (see the module docstring)."""
    from softplot.io import load_scan
    from softplot.marks import detect, kernels
    from softplot.runtime import set_threads, threads, tune_allocator
    from softplot.synthetic import ScanSpec, write_scan

    tune_allocator()  # as the softplot command does
    if n_threads:
        set_threads(n_threads)
    kernels.load()
    variants = {"auto (default)": "auto", "joint on every cross": "joint"}
    print(f"load average at start: {_load()} (2 cores; figures taken above 1 are provisional); "
          f"{threads()} threads")
    with tempfile.TemporaryDirectory(prefix="bench_busy_") as tmp:
        d = Path(tmp)
        for dpi in (1200, 2400):
            path, _ = write_scan(d, "rollei-6006", ScanSpec(dpi=dpi, rotation_deg=1.5,
                                                             scene="busy"), seed=7,
                                 stem=f"busy-{dpi}")
            times = {k: [] for k in variants}
            cpu = {k: [] for k in variants}
            for i in range(runs + 1):
                for k, scene in variants.items():
                    t, c = time.perf_counter(), time.process_time()
                    det = detect(load_scan(path), "rollei-6006", scene=scene)
                    if i:  # the first round warms caches
                        times[k].append(time.perf_counter() - t)
                        cpu[k].append(time.process_time() - c)
            for k, v in times.items():
                print(f"busy {dpi} dpi, {k}: load + detect median {statistics.median(v):.3f} s "
                      f"(min {min(v):.3f}, n={len(v)}); CPU median "
                      f"{statistics.median(cpu[k]):.3f} s (min {min(cpu[k]):.3f}); "
                      f"scene model {det.scene}")
        if batch:
            paths = [write_scan(d, "rollei-6006", ScanSpec(dpi=1200, rotation_deg=1.5,
                                                            scene="busy"), seed=100 + i,
                                stem=f"batch-{i}")[0] for i in range(batch)]
            cmd = [sys.executable, "-c", "from softplot.cli import main; main()", "detect",
                   "--camera", "rollei-6006"]
            t = time.perf_counter()
            subprocess.run(cmd + [str(p) for p in paths], check=True, capture_output=True)
            many = (time.perf_counter() - t) / batch
            t = time.perf_counter()
            for p in paths[:3]:
                subprocess.run(cmd + [str(p)], check=True, capture_output=True)
            one = (time.perf_counter() - t) / 3
            print(f"softplot detect, busy 1200 dpi: {batch} scans in one process "
                  f"{many:.3f} s per scan; one scan per process {one:.3f} s per scan")
    print(f"load average at end: {_load()}")


def alternate(runs: int) -> None:
    """``--threads-alternate``: one and two threads in this process, alternating."""
    from softplot.io import load_scan
    from softplot.marks import detect, kernels
    from softplot.runtime import set_threads, tune_allocator
    from softplot.synthetic import ScanSpec, write_scan

    tune_allocator()
    kernels.load()
    print(f"load average at start: {_load()}")
    with tempfile.TemporaryDirectory(prefix="bench_thr_") as tmp:
        for dpi in (1200, 2400):
            path, _ = write_scan(Path(tmp), "rollei-6006", ScanSpec(dpi=dpi, rotation_deg=1.5,
                                                                     scene="busy"), seed=7,
                                 stem=f"busy-{dpi}")
            res = {n: ([], []) for n in (1, 2)}
            for i in range(runs + 1):
                for n in (1, 2):
                    set_threads(n)
                    t, c = time.perf_counter(), time.process_time()
                    detect(load_scan(path), "rollei-6006")
                    if i:  # the first round warms caches
                        res[n][0].append(time.perf_counter() - t)
                        res[n][1].append(time.process_time() - c)
            for n, (w, c) in res.items():
                print(f"busy {dpi} dpi, {n} thread{'s' if n > 1 else ''}: load + detect wall "
                      f"median {statistics.median(w):.3f} s (min {min(w):.3f}), CPU median "
                      f"{statistics.median(c):.3f} s, n={len(w)}")
    set_threads(None)
    print(f"load average at end: {_load()}")


#: the stages of a reseau detection timed by ``--stages`` (functions of
#: :mod:`softplot.marks.detect`)
STAGES = ("reseau_overview", "_lattice", "predict", "centred_geometry", "choose_width",
          "measure_crosses", "validate")


def stage_times(runs: int, n_threads: int) -> None:
    """``--stages``: wall and CPU time (the process's, all threads) of each stage of the busy
    scans' detection, medians of ``runs`` after a warm-up."""
    import importlib

    from softplot.io import load_scan
    from softplot.marks import kernels
    from softplot.runtime import set_threads, tune_allocator
    from softplot.synthetic import ScanSpec, write_scan

    det_mod = importlib.import_module("softplot.marks.detect")
    tune_allocator()
    set_threads(n_threads)
    kernels.load()
    acc: dict = {}

    def timed(name, f):
        def g(*args, **kw):
            t, c = time.perf_counter(), time.process_time()
            out = f(*args, **kw)
            w = acc.setdefault(name, [0.0, 0.0])
            w[0] += time.perf_counter() - t
            w[1] += time.process_time() - c
            return out
        return g

    saved = {n: getattr(det_mod, n) for n in STAGES}
    for n, f in saved.items():
        setattr(det_mod, n, timed(n, f))
    print(f"load average at start: {_load()}; {n_threads} thread(s)")
    try:
        with tempfile.TemporaryDirectory(prefix="bench_stages_") as tmp:
            for dpi in (1200, 2400):
                path, _ = write_scan(Path(tmp), "rollei-6006", ScanSpec(
                    dpi=dpi, rotation_deg=1.5, scene="busy"), seed=7, stem=f"busy-{dpi}")
                rows = []
                for i in range(runs + 1):
                    acc.clear()
                    t, c = time.perf_counter(), time.process_time()
                    det_mod.detect(load_scan(path), "rollei-6006")
                    if i:  # the first run warms caches
                        total = (time.perf_counter() - t, time.process_time() - c)
                        rows.append({"load + detect": total, **{k: tuple(v) for k, v in
                                                                 acc.items()}})
                print(f"busy {dpi} dpi, medians of {runs} (wall / CPU s):")
                for k in ("load + detect",) + STAGES:
                    w = statistics.median(r.get(k, (0.0, 0.0))[0] for r in rows)
                    c = statistics.median(r.get(k, (0.0, 0.0))[1] for r in rows)
                    print(f"  {k}: {w:.3f} / {c:.3f}")
    finally:
        for n, f in saved.items():
            setattr(det_mod, n, f)
    print(f"load average at end: {_load()}")


def _worker(n_threads: int) -> None:
    """``--worker``: detect the busy scans named on stdin, one per line; print CPU and wall
    time of each (load + detect) on stdout. Warmed up on every scan first."""
    from softplot.io import load_scan
    from softplot.marks import detect, kernels
    from softplot.runtime import set_threads, tune_allocator

    tune_allocator()
    kernels.load()
    set_threads(n_threads)
    print("ready", flush=True)
    seen = set()
    for line in sys.stdin:
        path = line.strip()
        if path not in seen:  # the first detection of a scan warms caches
            detect(load_scan(path), "rollei-6006")
            seen.add(path)
        t, c = time.perf_counter(), time.process_time()
        detect(load_scan(path), "rollei-6006")
        print(time.process_time() - c, time.perf_counter() - t, flush=True)


def compare(other: str, runs: int, n_threads: int, scene: str = "busy") -> None:
    """``--compare SRC``: this checkout's code and the code under ``SRC`` (another version's
    ``src`` folder) in two processes side by side, alternating detection by detection on the
    busy scans (``scene`` "texture": the textured ones; default scene model): on a shared
    machine both see the same load."""
    from softplot.synthetic import ScanSpec, write_scan

    here = str(Path(__file__).resolve().parents[1] / "src")
    with tempfile.TemporaryDirectory(prefix="bench_cmp_") as tmp:
        d = Path(tmp)
        scans = {dpi: write_scan(d, "rollei-6006", ScanSpec(dpi=dpi, rotation_deg=1.5,
                                                             scene=scene), seed=7,
                                 stem=f"{scene}-{dpi}")[0] for dpi in (1200, 2400)}
        procs = {}
        for name, src in (("other", other), ("this", here)):
            env = dict(os.environ, PYTHONPATH=src)
            procs[name] = subprocess.Popen([sys.executable, __file__, "--worker",
                                            str(n_threads)], env=env, text=True,
                                           stdin=subprocess.PIPE, stdout=subprocess.PIPE)
        for p in procs.values():
            assert p.stdout.readline().strip() == "ready"
        print(f"load average at start: {_load()}; {n_threads} threads")
        res = {(n, dpi): ([], []) for n in procs for dpi in scans}
        for i in range(runs + 1):
            for dpi, path in scans.items():
                for n, p in procs.items():
                    p.stdin.write(f"{path}\n")
                    p.stdin.flush()
                    c, t = map(float, p.stdout.readline().split())
                    if i:
                        res[(n, dpi)][0].append(c)
                        res[(n, dpi)][1].append(t)
        for p in procs.values():
            p.stdin.close()
            p.wait()
        for (n, dpi), (c, t) in res.items():
            print(f"{scene} {dpi} dpi, {n} ({other if n == 'other' else here}): CPU median "
                  f"{statistics.median(c):.3f} s (min {min(c):.3f}), wall median "
                  f"{statistics.median(t):.3f} s (min {min(t):.3f}), n={len(c)}")
    print(f"load average at end: {_load()}")


def dpi_estimate(runs: int) -> None:
    """``--dpi-estimate``: detection of three scans of the independent renderer
    (``softplot.synthetic.plain`` seeds 1, 22, 13: Rollei 6006, Hasselblad, Pentax 645) with
    their dpi given and with it estimated, in this process; medians of ``runs`` after a
    warm-up."""
    from softplot.io import Scan
    from softplot.marks import detect
    from softplot.synthetic.plain import make_plain

    print(f"load average at start: {_load()}")
    for seed in (1, 22, 13):
        c = make_plain(seed)
        for known in (True, False):
            t = []
            for i in range(runs + 1):
                t0 = time.perf_counter()
                detect(Scan.from_array(c.image, dpi=c.dpi if known else None), c.camera)
                if i:
                    t.append(time.perf_counter() - t0)
            print(f"plain {seed} {c.camera} {c.image.shape[1]} x {c.image.shape[0]} px, dpi "
                  f"{'given' if known else 'estimated'}: detect median "
                  f"{statistics.median(t):.3f} s (n={len(t)})")
    print(f"load average at end: {_load()}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument("--busy", action="store_true", help="the busy-scene figures only")
    ap.add_argument("--batch", type=int, default=8, help="scans of the --busy batch run")
    ap.add_argument("--threads", type=int, default=None,
                    help="--busy: threads of the detections timed in this process (default: "
                         "SOFTPLOT_THREADS or the cores, at most 2)")
    ap.add_argument("--compare", metavar="SRC",
                    help="the busy scans, this code against the code under SRC (another "
                         "version's src folder), alternating in two processes")
    ap.add_argument("--scene", default="busy", choices=("busy", "texture"),
                    help="--compare: the busy scans (default) or the textured ones")
    ap.add_argument("--threads-alternate", action="store_true",
                    help="the busy scans on one and two threads, alternating in this process")
    ap.add_argument("--stages", action="store_true",
                    help="the busy scans: wall and CPU time of each detection stage "
                         "(--threads, default 1)")
    ap.add_argument("--child", nargs=4, help=argparse.SUPPRESS)
    ap.add_argument("--worker", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--dpi-estimate", action="store_true",
                    help="detection with the dpi given and estimated (independent scans)")
    a = ap.parse_args()
    if a.dpi_estimate:
        dpi_estimate(a.runs)
        return
    if a.child:
        child(*a.child)
        return
    if a.worker:
        _worker(a.worker)
        return
    if a.threads_alternate:
        alternate(a.runs)
        return
    if a.compare:
        compare(a.compare, a.runs, a.threads or 1, a.scene)
        return
    if a.stages:
        stage_times(a.runs, a.threads or 1)
        return
    if a.busy:
        busy(a.runs, a.batch, a.threads)
        return
    cases = [c for c in a.cases.split(",") if c]
    from softplot.io import load_scan
    from softplot.marks import detect
    from softplot.runtime import tune_allocator

    tune_allocator()  # the allocator setting the softplot command applies at start

    print(f"load average at start: {_load()} (2 cores; figures taken above 1 are provisional)")
    with tempfile.TemporaryDirectory(prefix="bench_detect_") as tmp:
        t0 = time.perf_counter()
        inputs = make_inputs(Path(tmp), cases)
        print(f"inputs written in {time.perf_counter() - t0:.1f} s to {tmp}")
        for c in cases:
            path, cam, warm = inputs[c]
            times = []
            det = None
            for _ in range(a.runs + 1):  # the first run warms caches and is not counted
                t = time.perf_counter()
                sc = load_scan(path)
                det = detect(sc, cam)
                times.append(time.perf_counter() - t)
            times = times[1:]
            m = _memory(path, cam, warm)
            px = m["fresh"]["pixel_bytes"]

            print(f"{c:16s} {sc.width}x{sc.height} px, pixels {px / 2**20:.1f} MiB: median "
                  f"{statistics.median(times):.3f} s (min {min(times):.3f}, n={len(times)}), "
                  f"measured {det.measured.sum()}/{len(det)}, scene model {det.scene}")
            print(f"{'':16s} peak memory: RSS scan {_fig(m, 'warm', px)} [warm-up leftover "
                  f"{m['warm']['leftover'] / 2**20:.1f} MiB included], "
                  f"RSS fresh {_fig(m, 'fresh', px)}, "
                  f"traced {_fig(m, 'traced', px)}")
            stages = {k: round(v, 3) for k, v in det.timings.items()}
            print(f"{'':16s} stages (cumulative s): {stages}")
    print(f"load average at end: {_load()}")


if __name__ == "__main__":
    main()
