"""Giving the C heap's free memory back to the system when a render nears its memory limit.

Embree's builds of the fast BVH's pieces (``scenes.Scene``) take their blocks from the C heap
(each is smaller than glibc's mmap threshold), and a build reuses the pages an evicted
domain's build freed, which the kernel then need not zero again: out of core, most of what
building in pieces saved (``bench/README.md``, session 66). The heap keeps those pages
resident, though, past what the caches' model of memory charges (the 100 M store's render in
6 GiB peaked at 5.0 GiB where it peaked at 4.0). So a cache under a memory limit checks the
RSS before each build and, above ``TRIM_ABOVE`` of the limit, asks glibc to give its free
memory back (``malloc_trim``): the reuse stays wherever the limit leaves room, and the limit
holds where it does not.
"""

from __future__ import annotations

import ctypes
import ctypes.util

#: The share of ``--memory-limit`` above which a cache trims the heap before a build.
TRIM_ABOVE = 0.9

_trim = None  # glibc's malloc_trim, or False where the C library has none


def trim_heap() -> bool:
    """Give the C heap's free memory back to the system (glibc's ``malloc_trim(0)``, tens of
    milliseconds with a few hundred MB free); False, doing nothing, where the C library has
    no ``malloc_trim`` (musl, macOS)."""
    global _trim
    if _trim is None:
        try:
            _trim = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
            _trim.argtypes, _trim.restype = [ctypes.c_size_t], ctypes.c_int
        except (OSError, AttributeError):
            _trim = False
    if not _trim:
        return False
    _trim(0)
    return True


def rss_ceiling(memory_limit: int | None) -> int | None:
    """The RSS above which a cache under ``memory_limit`` bytes trims the heap before a build
    (``TRIM_ABOVE`` of it); None without a limit."""
    return None if memory_limit is None else int(TRIM_ABOVE * memory_limit)
