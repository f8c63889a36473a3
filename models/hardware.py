"""What this CPU is and which of its instructions decide the speed of the networks' products.

Read from Linux's ``/proc/cpuinfo`` (the first processor's block): its model name and its flags (x86
``flags``, ARM ``Features``). Nothing is known elsewhere (macOS, Windows): the callers then measure or say so.
"""

from __future__ import annotations

from pathlib import Path

BF16_FLAGS = ("avx512_bf16", "amx_bf16", "bf16")
"""Flags of CPUs that multiply bfloat16 in hardware: x86 AVX-512 BF16 and AMX, ARMv8.6 BF16."""


def cpu_info(cpuinfo: str | Path = "/proc/cpuinfo") -> tuple[str | None, set[str] | None]:
    """``(model name, flags)`` of the first processor in ``cpuinfo``; ``None`` for what it does not say
    (flags ``None``: not known, as on systems without ``/proc/cpuinfo``)."""
    model, flags = None, None
    try:
        with open(cpuinfo) as fh:
            for line in fh:
                key, _, value = line.partition(":")
                key = key.strip()
                if key in ("model name", "Model name") and model is None:
                    model = value.strip()
                elif key in ("flags", "Features"):   # after the model name on x86: the first block's
                    flags = set(value.split())
                    break
    except OSError:
        pass
    return model, flags


def has_bf16_products(cpuinfo: str | Path = "/proc/cpuinfo") -> bool | None:
    """Does the CPU multiply bfloat16 in hardware (one of :data:`BF16_FLAGS`)? ``None`` when its flags are
    not known. Without such instructions oneDNN emulates bfloat16 and it is slower than float32."""
    _, flags = cpu_info(cpuinfo)
    return None if flags is None else bool(flags & set(BF16_FLAGS))
