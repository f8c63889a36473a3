"""capture.io.threads: the run's OpenCV and USD (TBB) pools limited to --threads, whether or not pxr is loaded.

Each case runs in a fresh interpreter: the pools are process-wide, and USD reads its limit once."""

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
from pxr import Work
print(json.dumps({"cv2": cv2.getNumThreads(), "usd": Work.GetConcurrencyLimit()}))
"""


def _pools(case: str) -> dict:
    """The pools in a fresh interpreter whose environment sets neither (a run earlier in this process sets
    USD's variable, which children inherit)."""
    from capture.io.threads import PXR_LIMIT_ENV

    env = {k: v for k, v in os.environ.items() if k not in (PXR_LIMIT_ENV, "OPENCV_FOR_THREADS_NUM")}
    r = subprocess.run([sys.executable, "-c", CHECK, case], capture_output=True, text=True, check=True, env=env)
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("order", ["pxr first", "pxr after"])
def test_pools_take_the_runs_threads(order):
    """With pxr loaded before the call the limit is set through pxr.Work, else through its environment
    variable, read when pxr loads; OpenCV's pool either way. Against the defaults of the same machine, which
    must be larger for the check to mean anything."""
    default = _pools("no call")
    if default["cv2"] <= 1 or default["usd"] <= 1:
        pytest.skip(f"this machine's pools already have one thread ({default})")
    assert _pools(order) == {"cv2": 1, "usd": 1}
