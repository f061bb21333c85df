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


@pytest.mark.skipif(platform.system() != 'Linux' or 'libc' not in
                    (ctypes.util.find_library('c') or ''), reason='glibc only')
def test_a_huge_block_freed_no_longer_moves_later_buffers_into_the_heap():
    # In a child process: the allocator's settings are per process.
    code = '''
import numpy as np
from armcal_ros.ros.memory import fix_allocator
def rss():
    return [int(l.split()[1]) / 1024 for l in open('/proc/self/status')
            if l.startswith('VmRSS')][0]
import sys
if sys.argv[1] == 'fixed':
    fix_allocator()
big = np.ones(1_000_000)          # 8 MB, mapped; freeing it raises glibc's threshold
del big
base = rss()
bufs = [np.ones(40_000) for _ in range(3000)]      # 320 kB each: ~960 MB
keep = [np.ones(1) for _ in range(3000)]           # small survivors between them
del bufs
print(rss() - base)
'''
    import subprocess
    import sys
    grown = {}
    for mode in ('default', 'fixed'):
        out = subprocess.run([sys.executable, '-c', code, mode], capture_output=True,
                             text=True, check=True).stdout
        grown[mode] = float(out.strip())
    # Default: the freed image-sized buffers stay resident in the heap; pinned: they were
    # mappings of their own and went back to the kernel when freed.
    assert grown['default'] > 300 and grown['fixed'] < 50, grown
