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


def repeated_rows(a: np.ndarray) -> np.ndarray:
    """``a`` (L, E) as a read-only view of its first row repeated L times when all its rows are equal (the
    2D fit while F_W is zero: one coefficient vector at every fit point), else ``a`` itself.

    Such a view holds E numbers, not L x E: a :class:`FrameFit` pickles it as one row (to and from the fit
    process) and the fit cache stores one row per frame (:func:`capture.run.store.save_frame_fits`)."""
    a = np.asarray(a)
    if a.ndim == 2 and len(a) > 1 and a.strides[0] != 0 and (a == a[0]).all():
        return np.broadcast_to(a[0].copy(), a.shape)
    return a


def is_repeated_rows(a) -> bool:
    """Is ``a`` a view made by :func:`repeated_rows` (2-D, first axis of stride 0)?"""
    return isinstance(a, np.ndarray) and a.ndim == 2 and len(a) > 1 and a.strides[0] == 0


ROW_SUFFIX, ROWS_SUFFIX = "@row", "@rows"   # in an NPZ: a (T, L, E) field stored as its rows (T, E) and L (T,)


def stored_rows(name: str, per_frame: list[np.ndarray]) -> dict[str, np.ndarray] | None:
    """``{NAME@row: (T, E), NAME@rows: (T,)}`` for per-frame (L, E) arrays that each repeat one row (views
    of :func:`repeated_rows`, or plain arrays whose rows are all equal); None when one of them does not."""
    if not per_frame or not all(is_repeated_rows(repeated_rows(a)) for a in per_frame):
        return None
    return {name + ROW_SUFFIX: np.stack([np.asarray(a)[0] for a in per_frame]),
            name + ROWS_SUFFIX: np.array([len(a) for a in per_frame], np.int64)}


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
    # (3, 8 + 3E) float32 where every vertex has the same coefficients (F_W zero): vertices = its map of the
    # actor's features (models.fit_state.map_vertices); a fit sent between processes may come without its
    # vertices, which the receiver makes from this (capture.fit.process.FitWorker.results)
    mesh_map: np.ndarray | None = None

    def __getstate__(self) -> dict:
        """Pickled with ``coefficients_landmarks`` as one row when it is :func:`repeated_rows` (90 KB less per
        frame of 468 landmarks and 24 shapes between the fit process and the run)."""
        state = dict(self.__dict__)
        w = state["coefficients_landmarks"]
        if is_repeated_rows(w):
            state["coefficients_landmarks"] = ("repeated rows", np.ascontiguousarray(w[0]), len(w))
        return state

    def __setstate__(self, state: dict) -> None:
        w = state["coefficients_landmarks"]
        if isinstance(w, tuple) and w[:1] == ("repeated rows",):
            state = {**state, "coefficients_landmarks": np.broadcast_to(w[1], (w[2], len(w[1])))}
        self.__dict__.update(state)
