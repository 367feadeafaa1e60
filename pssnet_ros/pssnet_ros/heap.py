"""Giving freed heap memory back to the system after work.

glibc's malloc keeps memory freed by the process in its arenas (one per thread that allocated) for reuse,
and returns it only from the top of each heap: a burst of large or varied requests (image buffers, the
checked sampler's proposals) leaves the node's RSS at its high-water mark. ``malloc_trim(0)`` releases the free
pages of every arena. No Python library exposes it, hence ctypes.
"""

from __future__ import annotations

import ctypes
import ctypes.util


def _malloc_trim() -> ctypes._CFuncPtr | None:
    path = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(path).malloc_trim if path else None
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to trim this way
        return None


_TRIM = _malloc_trim()


def trim_heap() -> bool:
    """Returns the free memory of every malloc arena to the system; False when the C library has no
    ``malloc_trim`` (then this is a no-op)."""
    if _TRIM is None:
        return False
    _TRIM(0)
    return True
