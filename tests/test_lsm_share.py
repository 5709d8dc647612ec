"""LSM's compiled fine stage shared with an idle thread (issue 20 point 5, busy-scene speed):
where a thread of the process has nothing to do, :func:`softplot.marks.kernels.fine_steps`
steps its marks in two halves on two threads (:func:`softplot.runtime.share`). Each mark steps
alone over its own row of the gathered arrays and writes only its own rows, so every value of
the fit must be the one of all marks stepped in one pass, bit for bit."""

from __future__ import annotations

import inspect
from dataclasses import fields

import numpy as np
import pytest

from softplot import runtime
from softplot.marks import kernels
from softplot.marks.lsm import lsm
from softplot.marks.template import MarkShape, render

pytestmark = pytest.mark.skipif(not kernels.AVAILABLE, reason="numba not installed")

SHAPE = MarkShape("cross", length=30.0, width=1.4)


@pytest.fixture
def restore_threads():
    yield
    runtime.set_threads(None)


def _patches(n, seed, half=24):
    """``n`` patches (pixel system) of a dark cross blurred 0.9 px at a sub-pixel offset
    over a tilted grey with noise 0.01; the true centres (pixel system)."""
    rng = np.random.default_rng(seed)
    size = 2 * half + 1
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    out, centres = [], []
    for i in range(n):
        d = rng.uniform(-0.5, 0.5, 2)
        t = render(SHAPE, 0.9, half=half, centre=tuple(d))
        out.append(0.6 + 0.001 * x - 0.3 * t + rng.normal(0, 0.01, t.shape))
        centres.append((100.0 * i + half + d[0], 50.0 + half + d[1]))
    origin = np.array([(100.0 * i, 50.0) for i in range(n)])
    return np.array(out, np.float32), origin, np.array(centres)


@pytest.mark.parametrize("n", [2, 5, 8])
def test_fine_steps_shared_with_an_idle_thread_are_the_one_pass_bit_for_bit(
        n, restore_threads, monkeypatch):
    g, origin, truth = _patches(n, seed=n)
    c0 = truth + np.random.default_rng(n).normal(0, 0.3, truth.shape)
    A0 = np.eye(2)
    runtime.set_threads(1)
    want = lsm(g, origin, c0, A0, SHAPE, 0.9, init_err=0.5)
    runtime.set_threads(2)
    rows = []
    real = kernels._fine

    at = list(inspect.signature(real.py_func if hasattr(real, "py_func") else real)
              .parameters).index("rows")

    def spy(*a):
        rows.append(len(a[at]))  # the marks stepped by this call
        return real(*a)

    monkeypatch.setattr(kernels, "_fine", spy)
    got = lsm(g, origin, c0, A0, SHAPE, 0.9, init_err=0.5)
    # the fine stage in two halves (and the arm-check refits of dropped halves, if any)
    k = sum(rows[:2])  # the marks not converged by the first (NumPy) step
    assert k >= 2 and sorted(rows[:2]) == [k // 2, k - k // 2]
    for f in fields(want):
        a, b = getattr(want, f.name), getattr(got, f.name)
        if isinstance(a, np.ndarray):
            assert np.array_equal(a, b, equal_nan=True), f.name
        else:
            assert a == b, f.name
    # the fits found the crosses (not an equality of two failures)
    assert np.hypot(*(got.centre - truth).T).max() < 0.05
