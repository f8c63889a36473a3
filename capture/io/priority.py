"""Scheduling priority of a pipeline's threads: the stages that run ahead yield the CPU to the one that
sets the pace.

In ``capture run`` decoding and detection run far ahead of the fit (its rows wait in the fit process's
inbox; ``benchmarks/bench_pipeline.py``), yet on two cores they compete with the fit process for the CPU,
most of all while it imports torch and builds the actor's networks, before its first window. Their
threads take a higher niceness (:data:`BACKGROUND_NICE`), so the fit gets the CPU first when both want
it, and they still have whatever it leaves. Linux only: there niceness is per thread; elsewhere
``setpriority`` would name a process, so nothing is changed.
"""

from __future__ import annotations

import os
import sys
import threading

#: Niceness added to a background thread (0-19 above the process's; 5 gives the other stages about 3x
#: the CPU share when both are busy).
BACKGROUND_NICE = 5


def background_thread(nice: int = BACKGROUND_NICE) -> bool:
    """Lower the calling thread's priority by ``nice`` (Linux); True when done."""
    if not sys.platform.startswith("linux") or nice <= 0:
        return False
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + int(nice)))
    except OSError:       # not permitted (a sandbox): the thread keeps its priority
        return False
    return True
