"""The node's heap trimming: free C-heap pages go back to the system (glibc)."""

import ctypes.util
import platform

import numpy as np
import pytest

from armcal_ros.ros.memory import release_free_memory


def _rss_mb():
    with open('/proc/self/status') as f:
        for line in f:
            if line.startswith('VmRSS:'):
                return int(line.split()[1]) / 1024.0


@pytest.mark.skipif(platform.system() != 'Linux' or 'libc' not in
                    (ctypes.util.find_library('c') or ''), reason='glibc only')
def test_release_returns_freed_heap_pages():
    # Many mid-sized buffers (below the mmap threshold, so they live in the heap) with one
    # small survivor at the top: free() alone cannot shrink the heap past it.
    baseline = _rss_mb()
    blocks = [np.ones(12_000) for _ in range(8_000)]          # ~770 MB of 96 kB chunks
    keep = np.ones(8)
    del blocks
    before = _rss_mb()                    # what free() left resident (about half, measured)
    assert release_free_memory() is True
    after = _rss_mb()
    assert keep.sum() == 8
    assert after - baseline < 0.5 * (before - baseline), (baseline, before, after)
