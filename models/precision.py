"""Reduced-precision products in the hidden SIREN layers, where the hardware makes them faster.

Training an actor is compute-bound on the ``(points x 256) @ (256 x 256)`` products of the hidden
sine layers (67 % of a float32 step). CPUs with AMX (and GPUs) multiply bfloat16 matrices many times
faster than float32 ones: on a 2-core Xeon with AMX 5-7x for one such product, a whole training
step 1.4-1.5x (BENCHMARKS.md, issue 13). Rounding the products' inputs to bfloat16 (8 bits of
mantissa) perturbs a pre-activation by about 0.2 % of its size; on the sample actor that costs
2-3 % of error at an equal number of steps, so the trainer uses it for the first part of a training
only and finishes, solves and evaluates in float32 (:class:`models.train.TrainSettings`
``hidden_matmul``). On the CPU the products run through oneDNN with float32 tensors in and out and
bfloat16 inside the kernel (:class:`models.siren.SineLayer`) where that mode really rounds (AMX; probed by
:func:`models.siren.onednn_bf16_rounds`: on an AMD EPYC with AVX-512 BF16 it stayed float32-accurate and
only 1.2-1.4x faster), elsewhere on bfloat16 copies (there 1.9x faster than float32 for the forward product).

Whether bfloat16 is faster is decided by the CPU's instructions where Linux lists them
(:func:`models.hardware.has_bf16_products`: AMX, AVX-512 BF16 or ARM BF16; without them oneDNN emulates
bfloat16 and it is slower than float32), and measured elsewhere (:func:`bf16_speedup`). A timed probe
alone made the choice depend on what else ran: two trainings started together on a busy 2-core AMD EPYC
came out on either side of the threshold, one in float32 at half the speed of the other, in bfloat16 (the
same command, two different actors); timed by CPU time instead, a probe beside a busy program on the same
core still measured 3.2x where it measured 5.6x alone.
"""

from __future__ import annotations

import contextlib
import time
from pathlib import Path

import torch

from models.hardware import has_bf16_products
from models.siren import SineLayer

HIDDEN_MATMUL = ("fp32", "bf16", "auto")
_SPEEDUP_CACHE: dict[tuple[str, int, int], float] = {}


def hidden_layers(module: torch.nn.Module) -> list[SineLayer]:
    """The hidden (not first) sine layers of every SIREN in ``module``."""
    return [m for m in module.modules() if isinstance(m, SineLayer) and not m.is_first]


@contextlib.contextmanager
def hidden_matmul_dtype(module: torch.nn.Module, dtype: torch.dtype | None):
    """Within the block, the hidden sine layers of ``module`` multiply in ``dtype`` (None = float32);
    the previous setting is restored after it."""
    layers = hidden_layers(module)
    before = [layer.matmul_dtype for layer in layers]
    for layer in layers:
        layer.matmul_dtype = dtype
    try:
        yield
    finally:
        for layer, d in zip(layers, before):
            layer.matmul_dtype = d


def bf16_speedup(device: torch.device | str = "cpu", width: int = 256, rows: int = 8192) -> float:
    """Measured time of a float32 ``(rows x width) @ (width x width)`` product over the bfloat16 one
    (best of 5 after a warm-up, the two interleaved), on ``device`` with the current thread count; cached
    per process.

    On the CPU the time is the process's CPU time, not the wall clock, which counts the time other programs
    kept it off a core: under load six wall-clock probes measured 4.5-12.1x on the AMD EPYC, six CPU-time
    probes 4.5-4.9x. It still moves with the load (3.2x beside a busy program on the same core), so
    :func:`resolve_hidden_matmul` uses it only where the CPU's flags are not known."""
    device = torch.device(device)
    key = (str(device), width, torch.get_num_threads())
    if key in _SPEEDUP_CACHE:
        return _SPEEDUP_CACHE[key]
    g = torch.Generator(device="cpu").manual_seed(0)
    a = torch.rand(rows, width, generator=g).to(device)
    b = torch.rand(width, width, generator=g).to(device)

    clock = time.perf_counter if device.type == "cuda" else time.process_time

    def timed(x, y) -> float:
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        t = clock()
        x @ y
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return clock() - t

    try:
        low = (a.bfloat16(), b.bfloat16())
        timed(*low)
    except RuntimeError:  # a backend without bfloat16 products
        low = None
    full, fast = [], []
    for i in range(7):
        full.append(timed(a, b))
        fast.append(timed(*low) if low is not None else float("inf"))
    fast_s = min(fast[2:])
    speedup = min(full[2:]) / fast_s if fast_s > 0 else 1.0
    _SPEEDUP_CACHE[key] = speedup
    return speedup


def resolve_hidden_matmul(setting: str, device: torch.device | str = "cpu", width: int = 256,
                          min_speedup: float = 2.0, cpuinfo: str | Path = "/proc/cpuinfo") -> str:
    """``"fp32"`` or ``"bf16"`` for a :class:`TrainSettings` ``hidden_matmul`` of ``setting``.

    ``"auto"`` on the CPU: ``"bf16"`` where the CPU multiplies bfloat16 in hardware
    (:func:`models.hardware.has_bf16_products` of ``cpuinfo``), so the same machine always trains the same
    actor; where its flags are not known, and on other devices, where a bfloat16 product of the layers'
    size is measured at least ``min_speedup`` times faster than a float32 one (the whole step gains less:
    conversions, sines and the output layers stay float32)."""
    if setting not in HIDDEN_MATMUL:
        raise ValueError(f"hidden_matmul must be one of {', '.join(HIDDEN_MATMUL)}, got {setting!r}")
    if setting != "auto":
        return setting
    if torch.device(device).type == "cpu":
        hardware = has_bf16_products(cpuinfo)
        if hardware is not None:
            return "bf16" if hardware else "fp32"
    return "bf16" if bf16_speedup(device, width) >= min_speedup else "fp32"
