"""What a timing was measured on, for the records that hold timings (``actor.json``, a run's ``report.json``)."""

from __future__ import annotations

import os
import platform
from pathlib import Path


FEATURES = ("avx2", "avx512f", "avx512_bf16", "amx_bf16")
"""The CPU flags that decide how fast the training's products run (bfloat16 where AMX or AVX-512 BF16 is there)."""


def machine(cpuinfo: str | Path = "/proc/cpuinfo") -> dict:
    """``{"cpu": model name, "cores": logical CPUs, "features": those of FEATURES the CPU has}``: from
    ``cpuinfo`` (Linux's ``/proc/cpuinfo``), else ``platform.processor()`` and no features (None / [] when nothing says).
    One training takes twice as long on some of the CPUs that users and CI have as on others, so a time
    means little without it."""
    cpu, flags = platform.processor() or None, set()
    try:
        with open(cpuinfo) as fh:
            for line in fh:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name":
                    cpu = value.strip()
                elif key == "flags":   # after the model name in each processor's block: the first one's
                    flags = set(value.split())
                    break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "features": [f for f in FEATURES if f in flags]}
