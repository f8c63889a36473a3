"""The take fit on landmarks that arrive one frame at a time (``capture run``'s streaming pipeline, ``capture live``).

:func:`fit_take_stream` gives exactly what :func:`capture.fit.take.fit_take` gives on the whole take (the
same windows, warm starts, blends, cache keys and numbers), but it reads the landmarks from an iterator
and solves each window as soon as the frames it depends on have arrived:

* A window ``[s, e)`` needs its frames' landmarks and their initial head poses. A pose is the per-frame
  PnP (causal: each frame starts from the previous one's), interpolated over frames without a pose
  (slerp between the nearest good frames) and Gaussian-smoothed over ``r = int(4 sigma + 0.5)`` frames
  (:func:`capture.fit.init.initial_head_poses`). So the poses of ``[s, e)`` are final once a frame
  with a pose exists beyond ``e - 1 + r`` (the interpolation brackets and the smoothing support of
  the window's frames are then those of the whole take), or the take has ended. They are computed
  by the same functions on the prefix received so far, so they equal the whole-take poses bit for bit.
* With ``causal=True`` (``capture live``) the poses use no future frames: no smoothing, and a frame
  without a pose holds the last good one (frames before the first face hold the first good pose once
  it arrives). A frame is then final when its window is solved: at most ``window - 1`` frames after it.

Landmarks: each item of the iterator is ``(points (L, 2) px, weights (L,) in [0, 1] or None, face_found)``;
the weights are treated as :func:`capture.fit.take.fit_take` treats a row of its ``weights``. An item may
also be ``(points, weights, face_found, pose)`` with the rows cleaned by :func:`capture.fit.init.clean_row`
and the head pose that :class:`capture.fit.init.PnPChain` gave for it (``(R, t)`` or None), computed by the caller
over the same rows in the same order (:mod:`capture.fit.process` does so beside detection).
"""

from __future__ import annotations

import bisect
import hashlib
import time
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np
import torch

from calib.camera import Camera
from calib.projection import camera_tensors
from capture.fit.init import PnPChain, PnPSettings, clean_row, interpolate_poses, smooth_poses
from capture.fit.take import (CACHE_VERSION, FrameFit, WindowedFit, _check_window, _fingerprint, _query, _run_windows,
                              _Window, query_template, reprojection_metrics, resolve_settings,
                              resolved_settings_dict)
from models.fit import Observations

__all__ = ["fit_take_stream", "StreamLandmarkSource"]


class StreamLandmarkSource:
    """A take's landmarks read frame by frame; hands :func:`capture.fit.take._run_windows` its windows.

    Holds the rows from the oldest frame still needed (released as windows finish) and, for the poses,
    the per-frame PnP results of the whole take so far (12 numbers a frame; the poses of a window are
    computed from those around it, :meth:`_pose_span`). Causal: only the frames not yet released, so a
    live session can run for hours.
    """

    def __init__(self, frames: Iterable, model_points: np.ndarray, K: np.ndarray, dist: np.ndarray,
                 pnp: PnPSettings, K_t: torch.Tensor, dist_t: torch.Tensor, dtype, device, causal: bool = False,
                 n_landmarks: int | None = None):
        self.it = iter(frames)
        self.pnp = pnp
        self.K_t, self.dist_t = K_t, dist_t
        self.dtype, self.device = dtype, device
        self.causal = causal
        self.L = n_landmarks if n_landmarks is not None else len(model_points)
        self.p: dict[int, np.ndarray] = {}
        self.w: dict[int, np.ndarray] = {}
        self.R: list[np.ndarray] = []            # raw PnP (identity where none), per frame
        self.t: list[np.ndarray] = []
        self.ok: list[bool] = []
        self.good: list[int] = []                # frames with a pose, in order
        self.last_good = -1
        self.n_good = 0
        self.chain = PnPChain(model_points, K, dist, pnp)
        self.n = 0                                # frames received
        self.ended = False
        sigma = pnp.smooth_sigma_frames
        self.radius = 0 if (causal or sigma <= 0) else int(4.0 * float(sigma) + 0.5)
        self.held = None                          # causal: last good pose, and the pose of each frame held
        self.first_pose = None
        self.causal_pose: dict[int, tuple | None] = {}
        self.wait_s = 0.0                         # time spent waiting for frames

    # ---------------------------------------------------------------- input
    def _pull(self) -> bool:
        """Read one more frame; False at the end of the take."""
        if self.ended:
            return False
        t0 = time.perf_counter()
        try:
            item = next(self.it)
        except StopIteration:
            self.ended = True
            self.wait_s += time.perf_counter() - t0
            return False
        self.wait_s += time.perf_counter() - t0
        j = self.n
        if len(item) == 4:       # (points, weights, found, PnP result) from a PnPChain run elsewhere
            p, w, _, res = item
        else:
            p, w = clean_row(*item, self.L, j)
            res = self.chain.next(p, w)
        self.p[j], self.w[j] = p, w
        if res is not None:
            self.last_good = j
            self.n_good += 1
            if not self.causal:
                self.good.append(j)
        if self.causal:      # the pose held from the last good frame (None before the first): O(1) per frame
            if res is not None:
                self.first_pose = self.first_pose or res
                self.held = res
            self.causal_pose[j] = self.held
        else:
            self.R.append(res[0] if res is not None else np.eye(3))
            self.t.append(res[1] if res is not None else np.zeros(3))
            self.ok.append(res is not None)
        self.n += 1
        return True

    def _ready(self, e: int) -> bool:
        """Are the poses of frames ``< e`` final, and is it known whether ``e`` ends the take?"""
        if self.ended:
            return True
        if self.causal:
            return self.n >= e
        # two poses at least: with one, interpolate_poses holds it instead of evaluating the slerp
        return self.n_good >= 2 and self.last_good > e - 1 + self.radius

    def _poses(self, s: int, e: int) -> tuple[np.ndarray, np.ndarray]:
        if self.last_good < 0:
            raise ValueError("no frame has enough landmarks for a head pose (PnP failed everywhere)")
        if self.causal:      # frames before the first face hold the first good pose
            poses = [self.causal_pose[j] or self.first_pose for j in range(s, e)]
            return np.stack([q[0] for q in poses]), np.stack([np.asarray(q[1]).reshape(3) for q in poses])
        lo, hi = self._pose_span(s, e)
        R, t = interpolate_poses(np.stack(self.R[lo:hi]), np.stack(self.t[lo:hi]), np.asarray(self.ok[lo:hi]))
        R, t = smooth_poses(R, t, self.pnp.smooth_sigma_frames)
        return R[s - lo:e - lo], t[s - lo:e - lo]

    def _pose_span(self, s: int, e: int) -> tuple[int, int]:
        """Frames ``[lo, hi)`` whose raw poses decide the poses of ``[s, e)`` as on the whole take: the
        smoothing reads ``[s - r, e - 1 + r]``, and the interpolation there reads only the good frames that
        bracket it, so the span runs from the last good frame before it (or the take's start) to the first
        good frame after it (or the frames received), with two good frames at least. Each window then costs
        the same however long the take (the whole prefix made a take of 36,000 frames cost minutes). The
        poses equal the whole take's bit for bit: Gaussian weights and slerps are per frame, and the
        quaternions' sign alignment, started at ``lo`` instead of 0, gives the same quaternions or all of
        them negated, which smooth to the negated mean and so to the same matrices."""
        g, first, last = self.good, s - self.radius, e - 1 + self.radius
        i0 = bisect.bisect_left(g, first) - 1       # the last good frame before them (-1: none)
        i1 = bisect.bisect_right(g, last)           # the first good frame after them (len: none yet)
        if len(g) >= 2:     # two good frames at least: a single one is held as given, not slerped
            i1, i0 = max(i1, 1), min(i0, len(g) - 2)
        return (g[i0] if i0 >= 0 else 0), (g[i1] + 1 if i1 < len(g) else self.n)

    # ---------------------------------------------------------------- what _run_windows calls
    def window(self, s: int, window: int) -> _Window | None:
        while not self._ready(s + window) and self._pull():
            pass
        if self.ended and self.n == 0:
            raise ValueError("no frames to fit")
        if self.ended and s >= self.n:   # the take ended on the border of a window without overlap: done
            return None
        e = min(self.n, s + window) if self.ended else s + window
        if e <= s:
            raise ValueError("no frames to fit")
        R0, t0 = self._poses(s, e)
        p = np.stack([self.p[j] for j in range(s, e)])
        w = np.stack([self.w[j] for j in range(s, e)])
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=self.dtype, device=self.device)
        obs = Observations(points2d=t(p), weights=t(w), K=self.K_t, dist=self.dist_t)
        h = hashlib.sha1()
        for a in (p, w, R0, t0):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        bridged = ~(w > 0).any(1)
        last = self.ended and e >= self.n   # causal: a take that ends on a window border gets one more window
        return _Window(s, e, obs, t(R0), t(t0), bridged, h.hexdigest(), last)

    def frame_metrics(self, j: int, vertices: np.ndarray, landmarks_fit: np.ndarray) -> tuple[float, float]:
        return reprojection_metrics(self.p[j], self.w[j], landmarks_fit)

    def release(self, before: int) -> None:
        for j in [j for j in self.p if j < before]:
            del self.p[j], self.w[j]
            self.causal_pose.pop(j, None)


def pnp_model_points(actor, template_points: np.ndarray, device="cpu") -> np.ndarray:
    """``(L, 3)`` float64 mm: the actor's neutral at the landmarks' template points, the per-frame PnP's
    3D model (as :func:`fit_take_stream` uses it)."""
    return _query(actor, np.asarray(template_points, np.float64), device).neutral.cpu().double().numpy()


def fit_take_stream(actor, frames: Iterable, template_points: np.ndarray, camera: Camera,
                    how: WindowedFit = WindowedFit(), pnp: PnPSettings | None = None, causal: bool = False,
                    progress: Callable[[int, int | None], None] | None = None,
                    timings: dict | None = None, vertices: bool = True) -> Iterator[FrameFit]:
    """Fit ``actor`` to landmarks arriving frame by frame; yields :class:`FrameFit` in frame order.

    Args:
        actor: a loaded actor (``.model``, ``.template``).
        frames: iterable of ``(points (L, 2) px, weights (L,) or None, face_found)``, one per frame of
            the take in order (it may block: each window is solved as soon as its frames are there).
        template_points: ``(L, 3)`` mm, the landmarks on the actor's template.
        camera, how, pnp: as :func:`capture.fit.take.fit_take`.
        causal: poses from past frames only (see the module docstring); False gives ``fit_take``'s
            results exactly.
        timings: receives ``query_s``, ``pnp_s``, ``wait_s`` (blocked on input) and the window figures.
        vertices: False: fits whose mesh is a map of the actor's features (``FrameFit.mesh_map``) come
            without vertices (the fit process: :class:`capture.fit.process.FitWorker` makes them).

    ``FrameFit.frame`` counts from 0 (the position in the stream).
    """
    s = resolve_settings(how.settings)
    window, overlap, device = how.window, how.overlap, how.device
    _check_window(window, overlap)
    pnp = pnp or PnPSettings()
    tp = np.asarray(template_points, np.float64)
    if tp.ndim != 2 or tp.shape[1] != 3:
        raise ValueError(f"template_points should be (L, 3); got {tp.shape}")
    tm = timings if timings is not None else {}
    t_start = time.perf_counter()
    fit_actor = _query(actor, tp, device)
    out_actor = query_template(actor, device)
    tm["query_s"] = time.perf_counter() - t_start
    K, dist = camera_tensors(camera, torch.float32, device)
    src = StreamLandmarkSource(frames, fit_actor.neutral.cpu().double().numpy(), camera.K, camera.dist, pnp, K, dist,
                               torch.float32, device, causal=causal, n_landmarks=len(tp))
    settings_key = resolved_settings_dict(s, window, overlap, pnp)
    if causal:
        settings_key["causal_poses"] = True
    base = _fingerprint(CACHE_VERSION, "2d", settings_key, fit_actor.neutral, fit_actor.expressions,
                        out_actor.neutral, camera.K, camera.dist)
    cache = None if how.cache_dir is None else Path(how.cache_dir)

    def run() -> Iterator[FrameFit]:
        try:
            yield from _run_windows(src, fit_actor, out_actor, s, window, overlap, cache, progress, how.threads, base,
                                    None, K, dist, tm, vertices=vertices)
        finally:
            tm["pnp_s"] = src.chain.seconds
            tm["wait_s"] = src.wait_s

    return run()
