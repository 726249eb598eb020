"""Keep the resident memory of a long-running service flat.

An adaptation decision allocates large temporary arrays (sensitivities over the history window,
tens of MB). glibc's malloc raises its mmap threshold dynamically after such arrays are freed, so
later ones come from the heap, whose freed pages are not returned: the process keeps its largest
working set for ever. Fixing the thresholds (which also disables the dynamic adjustment) makes
large arrays come from ``mmap`` and go back to the system when freed. No-op off glibc.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging

__all__ = ["limit_heap_retention"]

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
_done = False


def limit_heap_retention(mmap_threshold: int = 256 * 1024, trim_threshold: int = 1024 * 1024) -> bool:
    """Fix glibc's mmap and trim thresholds (once per process); True if applied."""
    global _done
    if _done:
        return True
    try:
        name = ctypes.util.find_library("c")
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    ok = bool(mallopt(M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(mallopt(M_TRIM_THRESHOLD, int(trim_threshold)))
    _done = ok
    if not ok:
        log.debug("mallopt not applied")
    return ok
