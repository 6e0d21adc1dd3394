"""A fixed threshold for glibc's heap, so that freed arrays go back to the system (docs/ARCHITECTURE.md §4.7).

glibc's ``malloc`` serves a request above ``M_MMAP_THRESHOLD`` (128 KiB to start with) by its own
``mmap``, returned to the system when freed; but each such free *raises* the threshold to the
freed size, up to 32 MiB. After the first stages of a run have freed their tiles' arrays, the
later arrays of up to 32 MiB (a tile's points, a Jacobian's columns, a factor's supernodes) come
from the heap, and a heap only shrinks from its top: one small live object above freed megabytes
keeps them all resident. A run's resident memory then keeps the high-water mark of every stage
before it. With the threshold fixed (which also ends its raising) and the heap trimmed from the
same size, the 10-minute corridor at 100 kHz (``georefine run --no-points``, ``python
bench/memory_profile.py``) peaked at 2.15 GB instead of 2.62 in 133 s instead of 130, with the same
files byte for byte; at 128 KiB, 1.94 GB in 154 s (every medium array a fresh, zeroed mapping).

Written by hand because it is one ``mallopt`` call: no library in the dependency list sets it.
Elsewhere than glibc (macOS, musl, Windows) it does nothing. ``GEOREFINE_HEAP=default`` leaves
glibc's own behaviour, and a ``MALLOC_MMAP_THRESHOLD_`` or ``MALLOC_TRIM_THRESHOLD_`` already in
the environment is respected.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

__all__ = ["HEAP_THRESHOLD_BYTES", "bound_heap"]

HEAP_THRESHOLD_BYTES = 4 * 2**20
"""``M_MMAP_THRESHOLD`` and ``M_TRIM_THRESHOLD``: 4 MiB (module docstring: the measured choice)."""

_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's malloc.h
_ENV = {"MALLOC_MMAP_THRESHOLD_": _M_MMAP_THRESHOLD, "MALLOC_TRIM_THRESHOLD_": _M_TRIM_THRESHOLD}
_applied: bool | None = None


def bound_heap() -> bool:
    """Fix glibc's mmap and trim thresholds in this process and in the processes it starts. Idempotent.

    Returns whether this process's ``malloc`` took the setting (False off glibc, or when
    ``GEOREFINE_HEAP=default`` or the environment set its own thresholds). Child processes (a
    local Dask cluster's workers) take it from the environment variables set here.
    """
    global _applied
    if _applied is not None:
        return _applied
    _applied = False
    if os.environ.get("GEOREFINE_HEAP", "") == "default" or any(name in os.environ for name in _ENV):
        return _applied
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return _applied
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    if all(mallopt(param, HEAP_THRESHOLD_BYTES) == 1 for param in _ENV.values()):
        for name in _ENV:
            os.environ[name] = str(HEAP_THRESHOLD_BYTES)
        _applied = True
    return _applied
