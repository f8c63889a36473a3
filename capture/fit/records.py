"""The fit's plain records: how a take is cut and solved (:class:`WindowedFit`) and one frame's fit
(:class:`FrameFit`).

numpy only (no torch): the processes that only read fits (the parent of the fit process, the exporters,
the report) load them without importing torch. :mod:`capture.fit.take` re-exports both.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from models.fit_settings import FitSettings


@dataclass(frozen=True)
class WindowedFit:
    """How a take is cut and solved: settings, windows, cache, device.

    ``settings`` is a :class:`FitSettings` or a preset name of :data:`models.fit.FIT_PRESETS`;
    ``window`` frames per window, ``overlap`` of them shared by consecutive windows; ``cache_dir`` keeps
    solved windows for resume (None: nothing written); ``threads`` torch threads while solving (None:
    leave torch's setting).
    """

    settings: FitSettings | str | None = "default"
    window: int = 30
    overlap: int = 6
    cache_dir: str | Path | None = None
    device: str = "cpu"
    threads: int | None = None


@dataclass
class FrameFit:
    """The fit of one frame. Lengths in mm, camera frame (OpenCV axes); ``x_cam = head_R @ x + head_t``."""

    frame: int                         # position in the take
    head_R: np.ndarray                 # (3, 3) head (template) frame -> camera
    head_t: np.ndarray                 # (3,) mm
    jaw_R: np.ndarray                  # (3, 3) about the actor's jaw pivot (head frame)
    jaw_t: np.ndarray                  # (3,) mm
    code: np.ndarray                   # (f,) frame code z_j
    coefficients_landmarks: np.ndarray  # (L, E) w_j(c) at the fit points (landmarks; fit3d: sampled vertices)
    vertices: np.ndarray               # (V, 3) float32 mm, camera frame, full template topology
    landmarks_fit: np.ndarray          # (L, 2) px reprojected model landmarks ((0, 2) for fit3d)
    reprojection_rms_px: float         # over the frame's valid landmarks; NaN when it has none (bridged)
    status: str                        # "fitted" | "bridged"
    error3d_mm: float = float("nan")   # fit3d: mean distance to the given mesh over all vertices
    window_start: int = 0              # first frame of the (later) window this frame came from
    coefficients_base: np.ndarray | None = None  # (E,) the per-frame base: w_j(c) = base + F_W(z_j, c)
