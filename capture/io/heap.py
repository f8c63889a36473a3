"""glibc's malloc thresholds, set per process: where large blocks come from and when the heap shrinks.

glibc adjusts both thresholds by itself until one is set; then both stay where they are, the trim
threshold at its 128 KB default unless it is set too. Two processes of a run want different settings:

* the run's own process decodes frames of MBs: a fixed 1 MiB mmap threshold serves them by mmap and
  gives them back when freed (the heaps of the decode and detect threads otherwise fragment: 1.1 GB at
  75 frames of 1080p, 1.5 GB at 300); a 64 MB trim threshold keeps a fit in that process (``capture
  batch``) from giving memory back and faulting it in again at every step (the fit alone 1.2x slower,
  a 300-frame take 15.2 -> 14.2 s; peak memory the same);
* the fit process allocates tensors of several MB at every step: mapped and unmapped each time with a
  1 MiB threshold, its fit ran 1.4x slower (7.2 -> 10 s for 300 frames, most of it system time), so it
  sets thresholds as large as glibc's dynamic ones grow to.

:func:`release_free_heap` gives the free parts of the heap back to the system (``malloc_trim``): the fit
process calls it every 2,400 frames (``capture.fit.process.TRIM_EVERY_FRAMES``), since with its large trim
threshold the free memory it held grew with the take (396 -> 487 MB over a 12,000-frame take, of which a
trim gave back about 100 MB).

No-op off glibc.

:func:`populated` maps a large buffer with its pages already in place (``MADV_POPULATE_WRITE``): one system call
instead of a page fault per 4 KB at first touch. The frame pool's buffers come from it: in a streamed run
those first touches came while the detect and export threads of the same process allocated and freed,
and cost 2.9 s of system time for 131,000 faults (22 us each, against 3 us in a process alone).
"""

from __future__ import annotations

import mmap

import numpy as np

FRAMES_OFF_HEAP = (1 << 20, 64 << 20)     # (mmap, trim) bytes: the run's process
COMPUTE = (32 << 20, 64 << 20)            # glibc's largest dynamic mmap threshold on 64-bit, twice it to trim


def _libc():
    """glibc through ctypes, or None where there is none."""
    import ctypes
    import ctypes.util

    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    except OSError:
        return None


def set_malloc_thresholds(mmap_bytes: int, trim_bytes: int) -> None:
    """Fix glibc's ``M_MMAP_THRESHOLD`` and ``M_TRIM_THRESHOLD`` for this process (see the module docstring)."""
    try:
        libc = _libc()
        libc.mallopt(-3, int(mmap_bytes))     # M_MMAP_THRESHOLD
        libc.mallopt(-1, int(trim_bytes))     # M_TRIM_THRESHOLD
    except AttributeError:                    # no libc, or not glibc
        pass


def release_free_heap() -> None:
    """Return the heap's free memory to the system (glibc ``malloc_trim(0)``; a few ms). No-op off glibc."""
    try:
        _libc().malloc_trim(0)
    except AttributeError:                    # no libc, or not glibc
        pass


MADV_POPULATE_WRITE = 23          # Linux >= 5.14: fault in the pages of a range, writable
_MADVISE: list = []               # [libc's madvise] once it worked, [None] once it did not


def populated(shape: tuple[int, ...], dtype=np.uint8) -> np.ndarray:
    """A zeroed, writable, C-contiguous array of ``shape`` whose pages are mapped at once (a plain ``np.zeros``
    where the system cannot). Its memory is unmapped with the last array that views it.

    The pages are put in place by ``madvise(MADV_POPULATE_WRITE)`` called through ctypes, which lets go of the
    GIL while the kernel zeroes them; ``mmap.mmap`` with ``MAP_POPULATE`` (where that madvise is not known, Linux
    before 5.14) holds it. On this project's 2-vCPU machine a 720p run's pool of 99 frames (273 MB) took
    0.09-1.0 s to map, as the cost of fresh pages varies from hour to hour; with ``MAP_POPULATE`` every other
    thread of the run waited for the GIL that long."""
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    flag = getattr(mmap, "MAP_POPULATE", 0)
    if not flag or nbytes == 0:
        return np.zeros(shape, dtype)
    if _MADVISE != [None]:
        buf = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
        array = np.frombuffer(buf, dtype).reshape(shape)
        if _populate(array):
            return array
        del array, buf
    buf = mmap.mmap(-1, nbytes, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS | flag)
    return np.frombuffer(buf, dtype).reshape(shape)


def _populate(array: np.ndarray) -> bool:
    """Fault in ``array``'s pages (page-aligned: a mapping of its own) with the GIL let go; False where the
    kernel or the C library cannot (remembered: the next arrays go by ``MAP_POPULATE``)."""
    import ctypes

    if not _MADVISE:
        libc = _libc()
        fn = getattr(libc, "madvise", None) if libc is not None else None
        if fn is not None:
            fn.argtypes, fn.restype = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int), ctypes.c_int
        _MADVISE.append(fn)
    fn = _MADVISE[0]
    if fn is None or fn(array.ctypes.data, array.nbytes, MADV_POPULATE_WRITE) != 0:
        _MADVISE[:] = [None]
        return False
    return True
