"""Library log noise: FFmpeg, OpenCV, onnxruntime and Ray stay quiet unless ``--verbose``.

A user sees our one-line error or summary, not 55 lines of FFmpeg's container warnings before it.
:func:`configure` runs once at the start of the command line, before those libraries log anything:
it sets the environment variables they read (OpenCV's and FFmpeg's log levels are read when the
first video opens; nothing is imported here, so commands stay quick to start) and the Python
loggers' levels. ``--verbose`` (or ``CAPTURE_VERBOSE=1``) leaves
every library at its own default.
"""

from __future__ import annotations

import logging
import os

#: Environment of a quiet run (only set where the user did not set the variable already).
QUIET_ENV = {
    "OPENCV_LOG_LEVEL": "ERROR",        # OpenCV's own logging (errors we turn into one line anyway)
    "OPENCV_FFMPEG_LOGLEVEL": "-8",     # AV_LOG_QUIET: FFmpeg's container and codec warnings
    "OPENCV_VIDEOIO_DEBUG": "0",
    "RAY_DEDUP_LOGS": "1",
    "TF_CPP_MIN_LOG_LEVEL": "3",
}
QUIET_LOGGERS = ("ray", "onnxruntime", "trimesh", "matplotlib", "PIL", "numba", "filelock")

_verbose = False


def configure(verbose: bool) -> None:
    """Quiet the libraries (or not, with ``verbose``); safe to call more than once."""
    global _verbose
    _verbose = bool(verbose)
    if _verbose:
        return
    for k, v in QUIET_ENV.items():
        os.environ.setdefault(k, v)
    for name in QUIET_LOGGERS:
        logging.getLogger(name).setLevel(logging.ERROR)


def verbose() -> bool:
    """True when the user asked to see the libraries' own logs."""
    return _verbose or os.environ.get("CAPTURE_VERBOSE", "") not in ("", "0")
