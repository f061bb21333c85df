"""
Give the C heap's free memory back to the system after each solve (glibc only).

A long-running node allocates and frees large numpy buffers on several threads (the solver's
dense blocks, decoded images, the detector's crops).  glibc keeps freed memory in per-thread
arenas for reuse, and an arena whose top chunk is pinned by one small live allocation never
shrinks; the process's resident memory then climbs for hours while the Python objects stay
flat (measured in docs/BENCHMARKS.md, section "soak").  ``malloc_trim(0)`` returns every
arena's free pages to the kernel; it costs about a millisecond, so once per solve is free.

A second cause, same symptom: glibc serves a block of at least the mmap threshold (128 kB) from
a private mapping, returned to the kernel when freed, but raises that threshold to the size of
any mapped block freed (up to 32 MB).  One oversized message (an 8 MB image on a VGA topic)
thus moves every later image buffer (300 kB - 1 MB) into the heap, where they fragment it.
:func:`fix_allocator` pins the threshold at glibc's default, which ends the adjustment.

Elsewhere (musl, macOS, Windows) there is no such call and both are no-ops.
"""

import ctypes
import ctypes.util

_libc = None


def _load():
    global _libc
    if _libc is None:
        try:
            lib = ctypes.CDLL(ctypes.util.find_library('c') or 'libc.so.6')
            _libc = lib if hasattr(lib, 'malloc_trim') else False
        except OSError:
            _libc = False
    return _libc


#: mallopt parameter numbers (glibc's malloc.h).
_M_MMAP_THRESHOLD = -3
#: glibc's default mmap threshold: blocks this large or larger get their own mapping.
MMAP_THRESHOLD = 128 * 1024


def fix_allocator() -> bool:
    """Pin glibc's mmap threshold at its default (module docstring); True if done."""
    lib = _load()
    if not lib or not hasattr(lib, 'mallopt'):
        return False
    return bool(lib.mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD))


def release_free_memory() -> bool:
    """Return the C heap's free pages to the system; True if the call exists and did so."""
    lib = _load()
    if not lib:
        return False
    return bool(lib.malloc_trim(0))
