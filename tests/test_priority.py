"""capture.io.priority: a background thread of a run yields the CPU; the thread that calls it, not its process."""

from __future__ import annotations

import os
import sys
import threading

import pytest

from capture.io.priority import BACKGROUND_NICE, background_thread


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="niceness is per thread on Linux only")
def test_background_thread_lowers_only_the_calling_threads_priority():
    """The thread that calls it gets BACKGROUND_NICE more niceness (read back from the kernel by its thread
    id); the process's other threads, here the main one, keep theirs."""
    main_before = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    if main_before + BACKGROUND_NICE > 19:
        pytest.skip(f"the tests run at niceness {main_before}: no room left to lower a thread by {BACKGROUND_NICE}")
    seen = {}

    def work():
        tid = threading.get_native_id()
        before = os.getpriority(os.PRIO_PROCESS, tid)
        seen["done"] = background_thread()
        seen["delta"] = os.getpriority(os.PRIO_PROCESS, tid) - before

    t = threading.Thread(target=work)
    t.start()
    t.join()
    assert seen["done"] and seen["delta"] == BACKGROUND_NICE
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == main_before
    assert os.getpriority(os.PRIO_PROCESS, os.getpid()) == main_before
