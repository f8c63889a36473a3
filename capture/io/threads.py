"""The native thread pools of a run's own process, set once: OpenCV's and USD's (TBB).

``capture run`` gives every stage its threads (capture.run.stream); the libraries' own pools added
workers of their own to each call: OpenCV's pool (resizes and warps of the detector's crops, the report's
face crops) and USD's TBB workers (the USD export) waited for work by spinning, 49,000-70,000
``sched_yield`` calls in one 1,200-frame run on two cores, beside the stages that set the pace. Limited to
the run's ``--threads`` there are none (``BENCHMARKS.md``, streaming pipeline, sixteenth round: the whole
run's time did not move measurably on that machine, where a spinning thread yields at once to a busy one).
torch's threads are set by the fit's process (:mod:`capture.fit.process`), onnxruntime's by the detector's
session (:mod:`capture.detector.session`).
"""

from __future__ import annotations

import sys

_LIMIT: dict[str, int] = {}


def limit_native_pools(threads: int) -> None:
    """OpenCV's worker threads and USD's (``pxr.Work``) concurrency to ``threads`` (>= 1) in this process.

    OpenCV with 1 runs its parallel loops in the calling thread (no pool). USD's limit is set now if ``pxr`` is
    loaded, else when the USD export loads it (:func:`limit_usd_pool`): this does not import pxr.
    """
    n = max(1, int(threads))
    import cv2

    cv2.setNumThreads(n)
    _LIMIT["threads"] = n
    if "pxr" in sys.modules:
        limit_usd_pool()


def limit_usd_pool() -> None:
    """USD's concurrency to the limit :func:`limit_native_pools` set, if it was called (for the code that loads
    pxr: :mod:`capture.export.usd`). Through ``pxr.Work``: USD's ``PXR_WORK_THREAD_LIMIT`` would do the same but
    makes USD print a banner on stderr."""
    n = _LIMIT.get("threads")
    if n is not None:
        from pxr import Work

        Work.SetConcurrencyLimit(n)
