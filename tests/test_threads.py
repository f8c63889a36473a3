"""capture.io.threads: the run's OpenCV and USD (TBB) pools limited to --threads, whether pxr is loaded before
the call or by the USD export after it; without USD's banner on stderr. Every BLAS pool (numpy's, OpenCV's) at one
thread, in the process and in a process forked from it (the run's fit process).

Each case runs in a fresh interpreter: the pools are process-wide."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

CHECK = """
import json, os, sys
import cv2
import numpy
from threadpoolctl import threadpool_info

def blas():
    return sorted(i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas")
if sys.argv[1] == "pxr first":
    from pxr import Work
if sys.argv[1] != "no call":
    from capture.io.threads import limit_native_pools
    returned = limit_native_pools(1)
    from capture.export.usd import _pxr
    _pxr()                                  # what the USD export loads pxr with
from pxr import Work
r, w = os.pipe()
if os.fork() == 0:                          # as the run forks its fit process
    os.write(w, json.dumps(blas()).encode())
    os._exit(0)
os.wait()
forked = json.loads(os.read(r, 1000))
out = {"cv2": cv2.getNumThreads(), "usd": Work.GetConcurrencyLimit(), "blas": blas(), "forked": forked}
if sys.argv[1] != "no call":               # what the run records in its settings
    out["returned"] = [returned["opencv"], returned["usd"], sorted(b["threads"] for b in returned["blas"])]
print(json.dumps(out))
"""


def _pools(case: str) -> tuple[dict, str]:
    """The pools in a fresh interpreter, and its stderr, with neither pool's variable in its environment."""
    env = {k: v for k, v in os.environ.items() if k not in ("PXR_WORK_THREAD_LIMIT", "OPENCV_FOR_THREADS_NUM",
                                                            "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    r = subprocess.run([sys.executable, "-c", CHECK, case], capture_output=True, text=True, check=True, env=env)
    return json.loads(r.stdout.strip().splitlines()[-1]), r.stderr


@pytest.mark.parametrize("order", ["pxr first", "pxr after"])
def test_pools_take_the_runs_threads(order):
    """With pxr loaded before the call the limit is set at once, else when the USD export loads pxr; OpenCV's
    pool either way; both BLAS libraries (numpy's and OpenCV's) at one thread, in a forked child too; nothing
    printed. Against the defaults of the same machine, which must be larger for the check to mean anything."""
    default, _ = _pools("no call")
    if default["cv2"] <= 1 or default["usd"] <= 1 or max(default["blas"]) <= 1:
        pytest.skip(f"this machine's pools already have one thread ({default})")
    got, err = _pools(order)
    ones = [1] * len(default["blas"])
    assert got == {"cv2": 1, "usd": 1, "blas": ones, "forked": ones, "returned": [1, 1, ones]}
    assert err == ""
