"""Threads inside one detection (softplot.runtime.thread_map): same results, no nesting."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from softplot import runtime
from softplot.marks import detect
from softplot.synthetic import ScanSpec, render_scan


@pytest.fixture
def restore_threads():
    yield
    runtime.set_threads(None)


def test_thread_map_keeps_order_runs_on_threads_and_never_nests(restore_threads):
    runtime.set_threads(2)
    names = []

    def inner(x):
        names.append(threading.current_thread().name)
        return x * x

    def outer(x):
        # a nested call runs in the calling pool thread, one item after the other
        return runtime.thread_map(inner, range(x, x + 3))

    out = runtime.thread_map(outer, range(6))
    assert out == [[x * x for x in range(i, i + 3)] for i in range(6)]
    assert all(n.startswith("softplot") for n in names)
    with pytest.raises(ZeroDivisionError):
        runtime.thread_map(lambda x: 1 // x, [1, 0, 2])
    runtime.set_threads(1)
    names.clear()
    assert runtime.thread_map(inner, [3]) == [9]
    assert names == [threading.current_thread().name]


def test_detection_is_the_same_on_one_and_two_threads(restore_threads):
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=600, scene="busy", rotation_deg=2.0),
                             3)
    out = {}
    for n in (1, 2):
        runtime.set_threads(n)
        out[n] = detect(img, "rollei-6006", dpi=truth["dpi"])
    assert out[1].status == out[2].status
    # equal to float rounding: float32 sums may round differently with the arrays' place in
    # memory or a multithreaded BLAS's split of a product (seen in CI, not on every machine)
    m = out[1].measured
    assert m.sum() >= 100
    assert np.array_equal(m, out[2].measured)
    assert np.abs(out[1].xy[m] - out[2].xy[m]).max() < 1e-6


def test_detection_without_the_compiled_kernel_is_the_same(monkeypatch):
    """The NumPy path (no numba, or SOFTPLOT_JIT=0) measures the same crosses to well below
    their precision: the two model implementations differ by float32 rounding only."""
    from softplot.marks import kernels

    if not kernels.AVAILABLE:
        pytest.skip("numba not installed: only the NumPy path exists")
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=600, rotation_deg=-1.0), 4)
    jit = detect(img, "rollei-6006", dpi=truth["dpi"])
    monkeypatch.setattr(kernels, "AVAILABLE", False)
    ref = detect(img, "rollei-6006", dpi=truth["dpi"])
    assert jit.status == ref.status and jit.measured.sum() >= 115
    m = jit.measured
    d = np.abs(jit.xy[m] - ref.xy[m]).max()
    assert d < 0.05 * float(np.median(jit.sigma[m])), d


def test_a_kernel_that_fails_to_compile_falls_back_to_numpy(monkeypatch):
    from softplot.marks import kernels

    def broken(*args):
        raise RuntimeError("no LLVM target for this CPU")

    monkeypatch.setattr(kernels, "AVAILABLE", True)
    monkeypatch.setattr(kernels, "_LOADED", False)
    monkeypatch.setattr(kernels, "_kernel", broken)
    img, truth = render_scan("rollei-6006", ScanSpec(dpi=500), 6)
    with pytest.warns(RuntimeWarning, match="compiled LSM kernel unavailable"):
        det = detect(img, "rollei-6006", dpi=truth["dpi"])
    assert not kernels.AVAILABLE
    assert det.measured.sum() >= 115


def test_thread_count_from_the_environment(monkeypatch, restore_threads):
    from softplot.errors import SoftplotError

    runtime.set_threads(None)
    monkeypatch.setenv("SOFTPLOT_THREADS", "3")
    assert runtime.threads() == 3
    monkeypatch.setenv("SOFTPLOT_THREADS", "zero")
    with pytest.raises(SoftplotError, match="SOFTPLOT_THREADS must be a positive integer"):
        runtime.threads()
    runtime.set_threads(1)  # an explicit setting wins over the environment
    assert runtime.threads() == 1


def test_batch_workers_detect_on_one_thread(restore_threads):
    """`softplot batch`'s worker processes already use every core: run_one sets 1 thread
    there, and leaves a process that is not a dask worker alone."""
    from dask.distributed import Client, LocalCluster

    from softplot.pipeline.batch import _one_thread_in_worker

    runtime.set_threads(2)
    _one_thread_in_worker()
    assert runtime.threads() == 2

    def in_worker():
        _one_thread_in_worker()
        return runtime.threads()

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster, Client(cluster) as client:
        assert client.submit(in_worker, pure=False).result() == 1


def test_fine_stage_does_not_depend_on_the_chunking():
    """Each mark's LSM iterations and the acceptance tests (over all marks of a pass) do not
    depend on which marks share a chunk: chunks of 4 and one chunk of all give the same."""
    from softplot.camera import load_camera
    from softplot.marks import measure as ME
    from softplot.marks.detect import as_scan
    from softplot.marks.template import cross_shape

    img, truth = render_scan("rollei-6006", ScanSpec(dpi=600, scene="busy"), 5)
    ppm = truth["dpi"] / 25.4
    shape = cross_shape(load_camera("rollei-6006"), ppm)
    marks = [m for m in truth["marks"] if m["kind"] == "reseau" and m["visible"]][:30]
    rng = np.random.default_rng(0)
    c0 = np.array([[m["x"], m["y"]] for m in marks]) + rng.normal(0.0, 0.3, (len(marks), 2))
    A0 = np.broadcast_to(np.eye(2), (len(marks), 2, 2))  # upright scan: pixel = mark frame
    scan = as_scan(img, truth["dpi"])
    s0 = float(np.hypot(truth["render"]["blur_sigma_px"], np.sqrt(1.0 / 12.0)))
    sign = -1 if truth["polarity"] == "positive" else 1
    f = {k: ME.measure(scan, shape, c0, A0, s0, 0.75, sign, chunk=k) for k in (4, 64)}
    assert f[4].ok.sum() >= 25
    assert np.array_equal(f[4].ok, f[64].ok) and f[4].reason == f[64].reason
    ok = f[4].ok
    assert np.abs(f[4].xy[ok] - f[64].xy[ok]).max() < 1e-6


def test_single_chunk_split_on_two_threads_is_the_same(restore_threads, monkeypatch):
    """A single chunk of marks (refits, retries) is fitted in two halves on two threads
    (measure._halves: the opening's LSM and each joint-scene pass): each mark's fit is its
    own, so the outcome is that of one thread."""
    from softplot.camera import load_camera
    from softplot.marks import measure as ME
    from softplot.marks.detect import as_scan
    from softplot.marks.template import cross_shape

    img, truth = render_scan("rollei-6006", ScanSpec(dpi=600, scene="busy"), 5)
    ppm = truth["dpi"] / 25.4
    shape = cross_shape(load_camera("rollei-6006"), ppm)
    marks = [m for m in truth["marks"] if m["kind"] == "reseau" and m["visible"]][:30]
    rng = np.random.default_rng(1)
    xy = np.array([[m["x"], m["y"]] for m in marks])
    c0 = xy + rng.normal(0.0, 0.3, (len(marks), 2))
    A0 = np.broadcast_to(np.eye(2), (len(marks), 2, 2))  # upright scan: pixel = mark frame
    scan = as_scan(img, truth["dpi"])
    s0 = float(np.hypot(truth["render"]["blur_sigma_px"], np.sqrt(1.0 / 12.0)))
    sign = -1 if truth["polarity"] == "positive" else 1
    sizes = []
    real = ME.lsm

    def spy(patches, *a, **k):
        sizes.append(len(patches))
        return real(patches, *a, **k)

    monkeypatch.setattr(ME, "lsm", spy)
    f = {}
    for n in (1, 2):
        runtime.set_threads(n)
        sizes.clear()
        f[n] = ME.measure(scan, shape, c0, A0, s0, 0.75, sign, chunk=64, scene_tv=2)
        if n == 1:
            assert max(sizes) == len(marks)  # one chunk, one fit of all
        else:
            assert max(sizes) <= 16  # the opening and both passes in halves
    ok = f[1].ok
    assert f[1].scene_tv == 2 and ok.sum() >= 25
    assert np.array_equal(ok, f[2].ok) and f[1].reason == f[2].reason
    # the fits found the crosses (not an equality of two failures): median error < 0.05 px
    assert np.median(np.hypot(*(f[1].xy[ok] - xy[ok]).T)) < 0.05
    assert np.abs(f[1].xy[ok] - f[2].xy[ok]).max() < 1e-6
    # covariances to float32 rounding of the residual sums (the packed pixel arrays' width
    # follows the marks fitted together): 1e-4 of each cross's variance
    var = np.trace(f[1].cov[ok], axis1=1, axis2=2)
    d = np.abs(f[1].cov[ok] - f[2].cov[ok]).max((1, 2))
    assert (d < 1e-4 * var).all(), (d / var).max()
