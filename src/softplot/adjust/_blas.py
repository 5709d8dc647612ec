"""Limit the OpenBLAS thread count for a block of code (no third-party dependency).

Small dense factorisations (a few hundred unknowns) gain nothing from BLAS threads, and on a
shared machine a busy second core makes OpenBLAS's threads wait: a 441 x 441 Cholesky that takes
2 ms on one thread was measured at 270 ms with two contended threads. :func:`blas_threads`
sets the thread count of every OpenBLAS already loaded into the process (NumPy's and SciPy's
bundled copies) through ``ctypes`` and restores it afterwards; where no such library or symbol
exists it does nothing.
"""

from __future__ import annotations

import ctypes
from contextlib import contextmanager

__all__ = ["blas_threads"]

_SETTERS = (
    "scipy_openblas_set_num_threads64_",
    "scipy_openblas_set_num_threads",
    "openblas_set_num_threads64_",
    "openblas_set_num_threads",
)
_GETTERS = (
    "scipy_openblas_get_num_threads64_",
    "scipy_openblas_get_num_threads",
    "openblas_get_num_threads64_",
    "openblas_get_num_threads",
)
_libs: list | None = None


def _loaded_openblas() -> list:
    global _libs
    if _libs is not None:
        return _libs
    found = []
    try:
        with open("/proc/self/maps") as fh:
            paths = {ln.split()[-1] for ln in fh if "openblas" in ln.lower() and ".so" in ln}
    except OSError:
        paths = set()
    for p in sorted(paths):
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        setter = next((getattr(lib, s) for s in _SETTERS if hasattr(lib, s)), None)
        getter = next((getattr(lib, s) for s in _GETTERS if hasattr(lib, s)), None)
        if setter is not None and getter is not None:
            setter.argtypes = [ctypes.c_int]
            getter.restype = ctypes.c_int
            found.append((setter, getter))
    _libs = found
    return found


@contextmanager
def blas_threads(n: int | None):
    """Run the block with ``n`` OpenBLAS threads (``None``: leave unchanged)."""
    if n is None:
        yield
        return
    libs = _loaded_openblas()
    old = [g() for _, g in libs]
    try:
        for s, _ in libs:
            s(int(n))
        yield
    finally:
        for (s, _), o in zip(libs, old, strict=True):
            s(int(o))
