"""capture.io.threads: the run's OpenCV and USD (TBB) pools limited to --threads, whether pxr is loaded before
the call or by the USD export after it; without USD's banner on stderr.

Each case runs in a fresh interpreter: the pools are process-wide."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

CHECK = """
import json, sys
import cv2
if sys.argv[1] == "pxr first":
    from pxr import Work
if sys.argv[1] != "no call":
    from capture.io.threads import limit_native_pools
    limit_native_pools(1)
    from capture.export.usd import _pxr
    _pxr()                                  # what the USD export loads pxr with
from pxr import Work
print(json.dumps({"cv2": cv2.getNumThreads(), "usd": Work.GetConcurrencyLimit()}))
"""


def _pools(case: str) -> tuple[dict, str]:
    """The pools in a fresh interpreter, and its stderr, with neither pool's variable in its environment."""
    env = {k: v for k, v in os.environ.items() if k not in ("PXR_WORK_THREAD_LIMIT", "OPENCV_FOR_THREADS_NUM")}
    r = subprocess.run([sys.executable, "-c", CHECK, case], capture_output=True, text=True, check=True, env=env)
    return json.loads(r.stdout.strip().splitlines()[-1]), r.stderr


@pytest.mark.parametrize("order", ["pxr first", "pxr after"])
def test_pools_take_the_runs_threads(order):
    """With pxr loaded before the call the limit is set at once, else when the USD export loads pxr; OpenCV's
    pool either way; nothing printed. Against the defaults of the same machine, which must be larger for the
    check to mean anything."""
    default, _ = _pools("no call")
    if default["cv2"] <= 1 or default["usd"] <= 1:
        pytest.skip(f"this machine's pools already have one thread ({default})")
    got, err = _pools(order)
    assert got == {"cv2": 1, "usd": 1}
    assert err == ""
