"""Freed memory handed back to the system, so that a long run's resident size follows what it
holds now, not the most it once held: glibc's malloc keeps freed blocks inside its heaps
(numpy's temporaries under the mmap threshold, a window's many small arrays) until
malloc_trim. Elsewhere (no glibc) these do nothing but the collection."""

from __future__ import annotations

import contextlib
import ctypes
import gc


def trim() -> None:
    """glibc's malloc_trim(0): the free pages inside every heap back to the system (a few ms)."""
    with contextlib.suppress(AttributeError, OSError):
        ctypes.CDLL(None).malloc_trim(0)


def release() -> None:
    """A garbage collection (objects in reference cycles), then `trim`."""
    gc.collect()
    trim()
