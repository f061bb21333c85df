"""
Give the C heap's free memory back to the system after each solve (glibc only).

A long-running node allocates and frees large numpy buffers on several threads (the solver's
dense blocks, decoded images, the detector's crops).  glibc keeps freed memory in per-thread
arenas for reuse, and an arena whose top chunk is pinned by one small live allocation never
shrinks; the process's resident memory then climbs for hours while the Python objects stay
flat (measured in docs/BENCHMARKS.md, section "soak").  ``malloc_trim(0)`` returns every
arena's free pages to the kernel; it costs about a millisecond, so once per solve is free.

Elsewhere (musl, macOS, Windows) there is no such call and this is a no-op.
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


def release_free_memory() -> bool:
    """Return the C heap's free pages to the system; True if the call exists and did so."""
    lib = _load()
    if not lib:
        return False
    return bool(lib.malloc_trim(0))
