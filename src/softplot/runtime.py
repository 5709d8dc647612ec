"""Process-wide settings an application may choose: the command line applies them.

A library should not change the process it runs in behind its caller's back; these are
offered, and :func:`softplot.cli.main` (the ``softplot`` command) applies them at start.
"""

from __future__ import annotations

import os
import threading

_TUNED = False
_THREADS: int | None = None
_POOL = None
_POOL_LOCK = threading.Lock()
_IN_POOL = threading.local()

__all__ = ["tune_allocator", "set_threads", "threads", "thread_map", "concurrent", "share",
           "idle_threads", "pooled_map"]


def set_threads(n: int | None) -> None:
    """Threads mark detection may use in this process (None: the default of :func:`threads`).

    ``softplot batch`` sets 1 in its worker processes, which already use every core.
    """
    global _THREADS, _POOL
    _THREADS = None if n is None else max(1, int(n))
    with _POOL_LOCK:
        if _POOL is not None:
            _POOL.shutdown(wait=False)
            _POOL = None


def threads() -> int:
    """The thread count: :func:`set_threads`, else ``SOFTPLOT_THREADS``, else the number of
    cores this process may run on, at most 2 (the independent pieces of one detection --
    strips of the correlation map, chunks of marks -- gain little from more)."""
    if _THREADS is not None:
        return _THREADS
    env = os.environ.get("SOFTPLOT_THREADS", "").strip()
    if env:
        if not (env.isdigit() and int(env) > 0):
            from softplot.errors import SoftplotError

            raise SoftplotError(f"SOFTPLOT_THREADS must be a positive integer, got {env!r}")
        return int(env)
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    return max(1, min(2, n))


def _run_marked(fn, x):
    was = getattr(_IN_POOL, "active", False)
    _IN_POOL.active = True
    try:
        return fn(x)
    finally:
        _IN_POOL.active = was


#: items submitted to the pool and not done yet (queued or running; :func:`_submit`)
_PENDING = 0
_PENDING_LOCK = threading.Lock()


def _done(_future) -> None:
    global _PENDING
    with _PENDING_LOCK:
        _PENDING -= 1


def _pool():
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            from concurrent.futures import ThreadPoolExecutor

            _POOL = ThreadPoolExecutor(max_workers=threads(), thread_name_prefix="softplot")
        return _POOL


def _submit(pool, fn, x):
    """``fn(x)`` submitted to the pool, counted in :data:`_PENDING` until it is done (or
    cancelled)."""
    global _PENDING
    with _PENDING_LOCK:
        _PENDING += 1
    fut = pool.submit(_run_marked, fn, x)
    fut.add_done_callback(_done)
    return fut


def concurrent() -> bool:
    """Whether :func:`thread_map` runs its items on several threads here: more than one
    thread, and not called from one of its own pool threads (where it runs sequentially)."""
    return threads() > 1 and not getattr(_IN_POOL, "active", False)


def idle_threads() -> int:
    """How many pool threads have nothing to do now (nothing queued): what :func:`share`
    may hand work to. 0 on one thread."""
    n = threads()
    if n <= 1:
        return 0
    with _PENDING_LOCK:
        return max(n - _PENDING, 0)


def thread_map(fn, items) -> list:
    """``[fn(x) for x in items]``, on :func:`threads` threads when there are several items.

    For work that releases the GIL (OpenCV, large NumPy operations, the compiled LSM kernel).
    The results are in the order of ``items`` and those of the sequential loop to float
    rounding (float32 sums may round differently with the arrays' place in memory or a
    multithreaded BLAS's split of a product); a call from
    inside a pool thread runs sequentially (no nested pools), and the first exception is
    raised in the caller.
    """
    items = list(items)
    if len(items) <= 1 or not concurrent():
        return [fn(x) for x in items]
    pool = _pool()
    futs = [_submit(pool, fn, x) for x in items]
    try:
        return [f.result() for f in futs]
    finally:
        for f in futs:  # after an exception: the items not started are not run
            f.cancel()


def pooled_map(fn, items) -> list:
    """:func:`thread_map`, each item run as on a pool thread also where there is one item or
    one thread (the caller's thread marked as one: :func:`concurrent` is false inside, as in
    the pool): the work inside an item is split as it is on a pool thread."""
    items = list(items)
    if len(items) <= 1 or not concurrent():
        return [_run_marked(fn, x) for x in items]
    return thread_map(fn, items)


def share(fn, items) -> list:
    """``[fn(x) for x in items]``, the items after the first offered to the pool threads that
    are idle now (:func:`idle_threads`), also from inside a pool thread: the caller runs the
    first item, then every offered one no thread has started (and those not offered), and
    waits for the others. For work whose result does not depend on the thread it runs on or
    on the other items (e.g. independent patches of a compiled kernel): the results are those
    of the loop, to the last bit, however the items were shared. Deadlock-free: the caller
    waits only for items already running. The first exception is raised in the caller."""
    items = list(items)
    k = min(len(items) - 1, idle_threads())
    if k <= 0:
        return [fn(x) for x in items]
    pool = _pool()
    futs = [_submit(pool, fn, x) for x in items[1 : 1 + k]]
    try:
        out = [fn(items[0])]
        for f, x in zip(futs, items[1 : 1 + k], strict=True):
            out.append(fn(x) if f.cancel() else f.result())
    finally:
        for f in futs:
            f.cancel()
    return out + [fn(x) for x in items[1 + k :]]


def tune_allocator() -> None:
    """Let glibc keep freed heap instead of returning every work array at once (Linux only).

    Mark detection allocates many short-lived arrays of 0.1-2 MB. With glibc's defaults (the
    heap trimmed whenever 128 kB lie free at its top, blocks above 128 kB mapped and unmapped
    one by one) each is paged in afresh: a third of the fine stage's time went to page faults.
    Keeping up to 32 MB of freed heap and mapping only blocks above 8 MB removes that without
    raising the peak (the heap never holds more than the largest working set). The threads of
    :func:`thread_map` share that one heap (one arena): with an arena per thread, what one
    thread frees is not reused by another and the peak grew by half at 1200 dpi. Process-wide,
    applied once; a no-op where ``mallopt`` is missing.
    """
    global _TUNED
    if _TUNED:
        return
    _TUNED = True
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 8 << 20)  # M_MMAP_THRESHOLD
        libc.mallopt(-1, 32 << 20)  # M_TRIM_THRESHOLD
        libc.mallopt(-8, 1)  # M_ARENA_MAX: the worker threads share the one heap
    except (OSError, AttributeError):
        pass
