"""capture.io.heap: the fit process's free heap given back (glibc only)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

SCRIPT = """
import sys
sys.path.insert(0, {repo!r})
from capture.io.heap import COMPUTE, release_free_heap, set_malloc_thresholds

def anon_mb():
    for line in open("/proc/self/status"):
        if line.startswith("RssAnon"):
            return int(line.split()[1]) / 1024

import ctypes
import ctypes.util

libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
libc.malloc.restype = ctypes.c_void_p
libc.free.argtypes = [ctypes.c_void_p]
set_malloc_thresholds(*COMPUTE)                    # the fit process's: a 64 MB trim threshold
blocks = [libc.malloc(64 << 10) for _ in range(3200)]   # 200 MB of 64 KB blocks on the heap, touched
for b in blocks:
    ctypes.memset(b, 1, 64 << 10)
for i, b in enumerate(blocks):                     # every 16th block stays in use: the freed ones lie between
    if i % 16:                                     # blocks in use, where no automatic trim reaches (fragments)
        libc.free(b)
held = anon_mb()
release_free_heap()
print(held, anon_mb())
"""


@pytest.mark.skipif(not sys.platform.startswith("linux") or not Path("/proc/self/status").is_file(),
                    reason="glibc's malloc_trim and /proc: Linux only")
def test_release_free_heap_gives_back_what_the_fit_process_thresholds_keep():
    """187 MB freed in fragments between blocks still in use (as the fit process's heap ends up) stay in the
    process; the trim gives them back (RssAnon falls by most of it)."""
    out = subprocess.run([sys.executable, "-c", SCRIPT.format(repo=str(REPO))], capture_output=True, text=True,
                         check=True).stdout.split()
    held, after = float(out[0]), float(out[1])
    assert held > 190, held                     # the thresholds kept the freed blocks
    assert held - after > 150, (held, after)
