"""Handing memory the process has freed back to the system."""

from __future__ import annotations

import ctypes
import ctypes.util
import gc


def return_freed_memory() -> bool:
    """Collect garbage, then ask the C allocator to return its free pages to the system (glibc's
    ``malloc_trim(0)``).

    Memory freed as many small blocks (a factor graph's nodes, a retrieval database's rows) stays
    in the allocator's heap, where only later allocations of similar sizes reuse it; the large
    buffers of a factorization are mapped afresh, so the freed heap would add to their peak.

    Returns:
        whether the allocator was asked (``False`` where the C library has no ``malloc_trim``,
        e.g. musl or macOS: the memory is then reused by the process only).
    """
    gc.collect()
    name = ctypes.util.find_library("c")
    try:
        trim = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        trim = None
    if trim is None:
        return False
    trim.argtypes = [ctypes.c_size_t]
    trim(0)
    return True
