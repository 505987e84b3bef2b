"""Giving freed memory back to the operating system.

Tensors under glibc's mmap threshold (32 MB at most, raised as large blocks are freed) live
on the C heap; once freed, their pages stay with the process for reuse, and its resident set
does not shrink. After an evaluation epoch has kept thousands of small per-batch tensors and
joined them into one, the freed batches stay resident beside the joined copy.
``release_free_heap`` asks glibc to return every free heap page (``malloc_trim(0)``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
from collections.abc import Callable


@functools.cache
def _malloc_trim() -> Callable[[int], int] | None:
    """glibc's ``malloc_trim``; None where the C library has none (musl, macOS, Windows)."""
    name = ctypes.util.find_library("c")
    if name is None:
        return None
    try:
        return ctypes.CDLL(name).malloc_trim
    except (OSError, AttributeError):
        return None


def release_free_heap() -> bool:
    """Return the C heap's free pages to the operating system -> whether any were returned
    (False also where the C library cannot)."""
    trim = _malloc_trim()
    return bool(trim(0)) if trim is not None else False
