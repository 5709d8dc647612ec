"""Process-wide settings an application may choose: the command line applies them.

A library should not change the process it runs in behind its caller's back; these are
offered, and :func:`softplot.cli.main` (the ``softplot`` command) applies them at start.
"""

from __future__ import annotations

_TUNED = False

__all__ = ["tune_allocator"]


def tune_allocator() -> None:
    """Let glibc keep freed heap instead of returning every work array at once (Linux only).

    Mark detection allocates many short-lived arrays of 0.1-2 MB. With glibc's defaults (the
    heap trimmed whenever 128 kB lie free at its top, blocks above 128 kB mapped and unmapped
    one by one) each is paged in afresh: a third of the fine stage's time went to page faults.
    Keeping up to 32 MB of freed heap and mapping only blocks above 8 MB removes that without
    raising the peak (the heap never holds more than the largest working set). Process-wide,
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
    except (OSError, AttributeError):
        pass
