"""The joint scene solve shared with an idle thread (issue 20 point 5, busy-scene speed):
where a thread of the process has nothing to do (the last chunk of crosses refitted while the
other chunks are done, a refit of a few crosses on the main thread), :func:`deconv_tv` solves
its patches in two halves on two threads (:func:`softplot.runtime.share`). Each patch is
solved on its own, so the halves must give the solve of all patches at once bit for bit: the
detections then are those of the detector before, however the work was shared."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from softplot import runtime
from softplot.marks import kernels, scene_tv
from softplot.marks.template import MarkShape, render


@pytest.fixture
def two_threads():
    runtime.set_threads(2)
    yield
    runtime.set_threads(None)


def _problem(n, seed=0, half=26):
    """``n`` patches (pixel system) of a dark blurred cross over a scene with a sharp edge at
    a random place and angle, noise 0.01: (g, T, level, B0, mu)."""
    rng = np.random.default_rng(seed)
    size = 2 * half + 1
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    T = render(MarkShape("cross", length=36.0, width=1.5), 0.9, half=half).astype(np.float32)
    g, B0 = [], []
    for _ in range(n):
        a, c = rng.uniform(0, np.pi), rng.uniform(-10, 10)
        X = 0.4 + 0.3 * ((np.cos(a) * (x - half) + np.sin(a) * (y - half)) > c)
        g.append(X * (1 - T) + 0.1 * T + rng.normal(0, 0.01, X.shape))
        B0.append(X + rng.normal(0, 0.05, X.shape))
    return (np.array(g, np.float32), np.broadcast_to(T, (n, size, size)).copy(),
            np.full(n, 0.1), np.array(B0, np.float32), np.full(n, 0.01))


@pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")
@pytest.mark.parametrize("n", [2, 3, 7])
def test_a_solve_shared_with_an_idle_thread_is_the_whole_solve_bit_for_bit(n, two_threads,
                                                                           monkeypatch):
    g, T, level, B0, mu = _problem(n, seed=n)
    runtime.set_threads(1)
    want = scene_tv.deconv_tv(g, T, level, B0, mu, 0.8, iters=30)
    runtime.set_threads(2)
    sizes, names = [], []
    real = scene_tv._kernel

    def spy(gq, *a):
        sizes.append(len(gq))
        names.append(threading.current_thread().name)
        return real(gq, *a)

    monkeypatch.setattr(scene_tv, "_kernel", spy)
    assert _settled() == 2
    got = scene_tv.deconv_tv(g, T, level, B0, mu, 0.8, iters=30)
    assert sorted(sizes) == sorted([n // 2, n - n // 2])  # shared: two halves
    for a, b in zip(want, got, strict=True):
        assert np.array_equal(a, b)
    # and the solve is a solve: the scene under the bars is continued, not the mark's level
    assert np.abs(got[1] - scene_tv.deconv_tv(g, T, level, B0, mu, 0.8, iters=0)[1]).max() > 0


def _settled(timeout=5.0):
    """idle_threads() once the futures' done callbacks have run (they follow the result)."""
    end = time.monotonic() + timeout
    while runtime.idle_threads() < runtime.threads() and time.monotonic() < end:
        time.sleep(0.001)
    return runtime.idle_threads()


def test_share_runs_on_idle_threads_in_order_and_in_the_caller_when_none_is(two_threads):
    """Offered items run on a pool thread when one is idle, in the caller otherwise (every
    worker busy: a call from inside thread_map's items); the results keep the items' order,
    and an exception reaches the caller."""
    where = {}
    started = {2: threading.Event(), 3: threading.Event()}

    def work(x):
        if x in started:
            started[x].set()
        else:  # the caller's item: until the offered ones are taken by idle workers
            assert all(e.wait(timeout=10) for e in started.values())
        where[x] = threading.current_thread().name
        return x * x

    me = threading.current_thread().name
    assert runtime.share(work, [1, 2, 3]) == [1, 4, 9]
    assert where[1] == me and where[2].startswith("softplot") and where[3].startswith("softplot")

    def outer(x):
        # both workers are busy with outer items: nothing idle to share with (no deadlock)
        return runtime.share(lambda y: (y, threading.current_thread().name), [x, x + 10])

    gate = threading.Barrier(2)

    def busy_outer(x):
        gate.wait(timeout=5)  # both workers hold an item
        return outer(x)

    out = runtime.thread_map(busy_outer, [0, 1])
    assert [[v for v, _ in o] for o in out] == [[0, 10], [1, 11]]
    assert all(o[0][1] == o[1][1] for o in out)  # each ran in its caller's thread
    with pytest.raises(ZeroDivisionError):
        runtime.share(lambda x: 1 // x, [1, 0, 2])
    with pytest.raises(ZeroDivisionError):
        runtime.share(lambda x: 1 // x, [1, 2, 0])
    assert _settled() == 2  # nothing left counted as pending
    runtime.set_threads(1)
    assert runtime.idle_threads() == 0
    assert runtime.share(lambda x: threading.current_thread().name, [1, 2]) == [me, me]
