"""Giving freed heap memory back to the system after work.

glibc's malloc keeps memory freed by the process in its arenas (one per thread that allocated) for reuse,
and returns it only from the top of each heap: a burst of large or varied requests (image buffers, the
checked sampler's proposals) leaves the node's RSS at its high-water mark. ``malloc_trim(0)`` releases the free
pages of every arena, and the unused top of the main arena alone: a thread's own arena keeps its top up to glibc's
trim threshold, twice the mmap threshold, which rises with the largest buffer freed (up to 32 MiB). After
12-megapixel requests the executor threads' arenas kept 30-50 MiB that no trim returned (RELIABILITY.md). So the
node serves every thread from the main arena (:func:`use_one_arena`, called before its threads start); its threads
allocate large buffers, not many small ones, so they hardly contend. No Python library exposes either call, hence
ctypes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os

#: mallopt's parameter number of the arena limit (glibc's malloc.h)
M_ARENA_MAX = -8


def _libc_function(name: str) -> ctypes._CFuncPtr | None:
    path = ctypes.util.find_library("c")
    try:
        return getattr(ctypes.CDLL(path), name) if path else None
    except (OSError, AttributeError):  # not glibc (musl, macOS): nothing to tune this way
        return None


_TRIM = _libc_function("malloc_trim")
_MALLOPT = _libc_function("mallopt")


def trim_heap() -> bool:
    """Returns the free memory of every malloc arena to the system; False when the C library has no
    ``malloc_trim`` (then this is a no-op)."""
    if _TRIM is None:
        return False
    _TRIM(0)
    return True


def use_one_arena() -> bool:
    """Serves every thread started from now on from glibc's main arena, the one whose top ``malloc_trim`` returns
    (a ``MALLOC_ARENA_MAX`` in the environment wins: the caller's choice); False where the C library has no
    ``mallopt`` or refuses."""
    if _MALLOPT is None or "MALLOC_ARENA_MAX" in os.environ:
        return False
    return bool(_MALLOPT(M_ARENA_MAX, 1))
