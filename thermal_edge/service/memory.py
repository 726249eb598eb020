"""Keep the resident memory of a long-running service flat.

An adaptation decision allocates large temporary arrays (sensitivities over the history window,
tens of MB). glibc's malloc raises its mmap threshold dynamically after such arrays are freed, so
later ones come from the heap, whose freed pages are not returned: the process keeps its largest
working set for ever. Fixing the thresholds (which also disables the dynamic adjustment) makes
large arrays come from ``mmap`` and go back to the system when freed; it must happen before the
model is loaded (its network's construction frees a 26 MB temporary). The many smaller arrays of a
decision still leave free pages inside the heaps (the adapter thread has its own): after each
decision :func:`release_free_heap` gives them back (glibc ``malloc_trim``, well under a
millisecond; about 5-15 MB each time). No-ops off glibc.
"""
from __future__ import annotations

import ctypes
import ctypes.util
import logging

__all__ = ["limit_heap_retention", "release_free_heap"]

log = logging.getLogger(__name__)

M_TRIM_THRESHOLD = -1
M_MMAP_THRESHOLD = -3
_done = False
_libc: ctypes.CDLL | None = None


def _c_library() -> ctypes.CDLL | None:
    global _libc
    if _libc is None:
        try:
            name = ctypes.util.find_library("c")
            _libc = ctypes.CDLL(name or "libc.so.6")
        except OSError:
            return None
    return _libc


def limit_heap_retention(mmap_threshold: int = 256 * 1024, trim_threshold: int = 1024 * 1024) -> bool:
    """Fix glibc's mmap and trim thresholds (once per process); True if applied."""
    global _done
    if _done:
        return True
    libc = _c_library()
    mallopt = getattr(libc, "mallopt", None)
    if mallopt is None:
        return False
    ok = bool(mallopt(M_MMAP_THRESHOLD, int(mmap_threshold))) and bool(mallopt(M_TRIM_THRESHOLD, int(trim_threshold)))
    _done = ok
    if not ok:
        log.debug("mallopt not applied")
    return ok


def release_free_heap() -> bool:
    """Return the free pages of every malloc arena to the system (``malloc_trim(0)``); True if
    some were returned, False if none or off glibc."""
    trim = getattr(_c_library(), "malloc_trim", None)
    return bool(trim(0)) if trim is not None else False
