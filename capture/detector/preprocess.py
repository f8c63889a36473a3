"""Crops of video frames -> the detector network's input batch, as the spec's ``input`` says."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from capture.detector.crop import Crop, warp_crop
from capture.detector.spec import InputSpec


def preprocess(frames: Sequence[np.ndarray], crops: Sequence[Crop], inp: InputSpec,
               buffers: dict | None = None) -> np.ndarray:
    """Crops of BGR uint8 frames -> the network's input batch (N, ...) per ``inp`` (see the spec doc).

    ``buffers``: a dict the caller keeps between calls; the float batch is then computed in arrays kept
    there (the same operations in place, so the same values), instead of four fresh ones a call. A batch
    of 3 crops of 192x192 is 1.3 MB: fresh, each such array is mapped and unmapped by malloc
    (:mod:`capture.io.heap`) and faulted in page by page. The result is overwritten by the next call.
    """
    import cv2

    out = []
    for frame, crop in zip(frames, crops):
        img = warp_crop(frame, crop, inp.size)
        if inp.color == "RGB":
            img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        elif inp.color == "GRAY":
            img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)[:, :, None]
        out.append(img)
    x = np.stack(out)  # (N, H, W, C) uint8
    if inp.dtype in ("float32", "float16"):
        f = _buffer(buffers, "float", x.shape, np.float32)
        np.copyto(f, x, casting="unsafe")                       # exact: uint8 -> float32
        f *= np.float32(inp.scale)
        f -= np.asarray(inp.mean, np.float32)
        f /= np.asarray(inp.std, np.float32)
        x = f
        if inp.dtype == "float16":                              # normalised in float32, rounded once
            x = _buffer(buffers, "half", f.shape, np.float16)
            np.copyto(x, f, casting="same_kind")
    if inp.layout == "NCHW":
        n, h, w, c = x.shape
        t = _buffer(buffers, "nchw", (n, c, h, w), x.dtype)
        np.copyto(t, x.transpose(0, 3, 1, 2))
        x = t
    return np.ascontiguousarray(x)


def _buffer(buffers: dict | None, name: str, shape: tuple, dtype) -> np.ndarray:
    """An array of ``shape``: kept in ``buffers`` under ``name`` and reused (None: a fresh one)."""
    if buffers is None:
        return np.empty(shape, dtype)
    b = buffers.get(name)
    if b is None or b.shape != shape or b.dtype != dtype:
        b = buffers[name] = np.empty(shape, dtype)
    return b
