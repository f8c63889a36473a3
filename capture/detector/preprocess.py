"""Crops of video frames -> the detector network's input batch, as the spec's ``input`` says."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from capture.detector.crop import Crop, warp_crop
from capture.detector.spec import InputSpec


def preprocess(frames: Sequence[np.ndarray], crops: Sequence[Crop], inp: InputSpec) -> np.ndarray:
    """Crops of BGR uint8 frames -> the network's input batch (N, ...) per ``inp`` (see the spec doc)."""
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
    if inp.dtype == "float32":
        x = (x.astype(np.float32) * np.float32(inp.scale) - np.asarray(inp.mean, np.float32)) \
            / np.asarray(inp.std, np.float32)
    if inp.layout == "NCHW":
        x = x.transpose(0, 3, 1, 2)
    return np.ascontiguousarray(x)
