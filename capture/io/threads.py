"""The native thread pools of a run's own process, set once: OpenCV's, USD's (TBB) and the BLAS libraries'.

``capture run`` gives every stage its threads (capture.run.stream); the libraries' own pools added
workers of their own to each call: OpenCV's pool (resizes and warps of the detector's crops, the report's
face crops) and USD's TBB workers (the USD export) waited for work by spinning, 49,000-70,000
``sched_yield`` calls in one 1,200-frame run on two cores, beside the stages that set the pace. Limited to
the run's ``--threads`` there are none (``BENCHMARKS.md``, streaming pipeline, sixteenth round: the whole
run's time did not move measurably on that machine, where a spinning thread yields at once to a busy one).
The BLAS pools (numpy's OpenBLAS, and the one OpenCV bundles) get one thread whatever ``--threads`` says. The run's
BLAS calls are small (a frame's mesh from its map, OpenCV's PnP), so a second thread never pays, and an idle
OpenBLAS worker spins: in a 1,200-frame 720p run on two cores, one such worker of the run's process took 5.7 of the
run's 25 CPU-s, and the run took 13.0-13.8 s against 10.6-10.9 with one thread (``BENCHMARKS.md``, streaming
pipeline, twentieth round). The pools are set through threadpoolctl, on the libraries loaded at the call (this
loads OpenCV's); a forked fit process inherits them.
OpenCV's pool is stopped around every fork of the run (:func:`opencv_pool_stopped`): it is not fork-safe.
torch's threads are set by the fit's process (:mod:`capture.fit.process`), onnxruntime's by the detector's
session (:mod:`capture.detector.session`).
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Iterator

_LIMIT: dict[str, int] = {}


def limit_native_pools(threads: int) -> dict:
    """OpenCV's worker threads and USD's (``pxr.Work``) concurrency to ``threads`` (>= 1) in this process, and
    every loaded BLAS library's to one (the module docstring). Returns what the pools now have, for the run's
    resolved settings: ``{"opencv": n, "usd": n, "blas": [{"library", "version", "threads"}, ...]}``.

    OpenCV with 1 runs its parallel loops in the calling thread (no pool). USD's limit is set now if ``pxr`` is
    loaded, else when the USD export loads it (:func:`limit_usd_pool`): this does not import pxr.
    """
    n = max(1, int(threads))
    import cv2  # loads numpy, and so both OpenBLAS libraries, before the limit below
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(n)
    threadpool_limits(1, user_api="blas")
    _LIMIT["threads"] = n
    if "pxr" in sys.modules:
        limit_usd_pool()
    return native_pools()


def native_pools() -> dict:
    """What this process's pools have now, for a run's record: ``{"opencv": threads, "usd": the limit set (None
    before :func:`limit_native_pools`), "blas": [{"library", "version", "threads"} per loaded BLAS library]}``."""
    import cv2
    from threadpoolctl import threadpool_info

    return {"opencv": cv2.getNumThreads(), "usd": _LIMIT.get("threads"),
            "blas": [{"library": i["internal_api"], "version": i.get("version"), "threads": i["num_threads"]}
                     for i in threadpool_info() if i["user_api"] == "blas"]}


def limit_usd_pool() -> None:
    """USD's concurrency to the limit :func:`limit_native_pools` set, if it was called (for the code that loads
    pxr: :mod:`capture.export.usd`). Through ``pxr.Work``: USD's ``PXR_WORK_THREAD_LIMIT`` would do the same but
    makes USD print a banner on stderr."""
    n = _LIMIT.get("threads")
    if n is not None:
        from pxr import Work

        Work.SetConcurrencyLimit(n)


@contextmanager
def opencv_pool_stopped() -> Iterator[None]:
    """Fork inside this: OpenCV's worker threads are ended for it and started again after (nothing to do where
    cv2 is not loaded). Only the parent runs the code after the fork, so the number of threads is restored
    only there.

    OpenCV's pthreads pool is not fork-safe. A worker that has stopped spinning and waits on its condition
    variable (one second after the last parallel call was enough) leaves the variable "in use" in a forked child,
    where that worker does not exist. The child's first call that reconfigures or uses the pool (``cv2.setNumThreads``,
    any parallel loop) then waits forever. A process that calibrated a camera and then ran ``capture run``
    hung so. With one thread the pool has no workers (their ``pthread_join`` runs here, in the parent, where
    they exist), so the child inherits none.
    """
    cv2 = sys.modules.get("cv2")
    if cv2 is None:
        yield
        return
    n = cv2.getNumThreads()
    cv2.setNumThreads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(n)
