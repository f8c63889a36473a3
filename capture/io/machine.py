"""What a timing was measured on, for the records that hold timings (``actor.json``, a run's ``report.json``)."""

from __future__ import annotations

import os
import platform
from pathlib import Path


FEATURES = ("avx2", "avx512f", "avx512_bf16", "amx_bf16")
"""The CPU flags that decide how fast the training's products run (bfloat16 where AMX or AVX-512 BF16 is there)."""


def usable_cores() -> int:
    """The logical CPUs this process may run on (its affinity mask where the OS has one, e.g. under
    ``taskset`` or a container's cpuset), at least 1."""
    if hasattr(os, "sched_getaffinity"):
        return max(1, len(os.sched_getaffinity(0)))
    return os.cpu_count() or 1


def machine(cpuinfo: str | Path = "/proc/cpuinfo") -> dict:
    """``{"cpu": model name, "cores": logical CPUs, "features": those of FEATURES the CPU has}``: from
    ``cpuinfo`` (Linux's ``/proc/cpuinfo``, :func:`models.hardware.cpu_info`), else ``platform.processor()``
    and no features (None / [] when nothing says).
    One training takes twice as long on some of the CPUs that users and CI have as on others, so a time
    means little without it."""
    from models.hardware import cpu_info

    cpu, flags = cpu_info(cpuinfo)
    flags = flags or set()
    return {"cpu": cpu or platform.processor() or None, "cores": os.cpu_count(),
            "features": [f for f in FEATURES if f in flags]}
