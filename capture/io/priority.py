"""Scheduling priority of a pipeline's threads: the stage that can wait yields the CPU to the ones that set
the pace.

In ``capture run`` decoding and detection are the take's longest chain of work, and the fit (in a process
of its own, :mod:`capture.fit.process`) is fed by them: on two cores they compete with it for the CPU,
together with the export. The fit's threads take a higher niceness (:data:`BACKGROUND_NICE`), so that
decoding and detection get the CPU first when all want it; the fit solves its windows from its queue of
rows (at most :data:`capture.run.stream.FIT_BACKLOG_FRAMES`) with what they leave, and so has work when
they wait for each other, instead of idling there with its queue empty. On a 1,200-frame 720p take this
made a run 7 % shorter than the reverse (decoding and detection niced, which paid while the fit was 2x
slower; ``BENCHMARKS.md``, seventeenth round). ``capture live`` does not change priorities (its lag).
Linux only: there niceness is per thread (and inherited by the threads that a thread starts); elsewhere
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
    """Lower the calling thread's priority by ``nice`` (Linux); True when done. Threads that it starts
    afterwards inherit its niceness."""
    if not sys.platform.startswith("linux") or nice <= 0:
        return False
    tid = threading.get_native_id()
    try:
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + int(nice)))
    except OSError:       # not permitted (a sandbox): the thread keeps its priority
        return False
    return True
