"""The take-level fit: a whole video's landmarks (or a 3D mesh sequence) in, one :class:`FrameFit` per frame out.

Streaming and resumable. The take is solved in overlapping windows of frames with the paper's
neurally reparameterised sequence fit (:mod:`models.fit`):

* **Initialisation** (:mod:`capture.fit.init`): a rigid head pose per frame from a PnP of the
  actor's neutral at the landmarks' template points against the detections (confidence-selected,
  RANSAC then LM), interpolated over frames without a face and smoothed over time. ``F_T`` learns a
  correction on top of it.
* **Windows**: ``[0, W), [W-O, 2W-O), ...`` (``W = window``, ``O = overlap``; the last one may be
  shorter). Each window after the first is warm-started from the previous one: ``F_T`` and ``F_W``
  are copied, the overlap frames' codes and base (head and jaw pose, coefficient offsets) are the
  previous window's of the same frames, the new frames' codes and jaw/coefficient base start at the
  previous window's last frame's, their head base at their initial pose moved by the correction the
  solve made at the last overlap frame (:func:`_warm_state`). The first window runs
  ``settings.iterations``, later ones ``settings.warm_iterations`` (both may stop early, see
  :class:`~models.fit.FitSettings`).
* **Seams**: every per-frame output of an overlap frame is the blend of the two windows' solutions
  with a smoothstep weight that goes from the earlier window to the later one across the overlap
  (rotations blended and re-orthonormalised), so there is no step at a window border.
* **Cost**: the frozen actor is queried once at the fit points (landmarks) and once at all template
  vertices; during the fit ``F_W`` runs only at the landmarks; full-topology vertices are evaluated
  once per window after it is solved.
* **Memory** is flat in the take length: at most one window of vertices is held (plus the overlap).
* **Resume**: with ``cache_dir`` every solved window writes ``win_<start>.pt`` (the
  :class:`~models.fit.SequenceFit` state; tensors only, read with ``weights_only=True``) and then
  ``win_<start>.npz`` (its frames' parameters, codes and a key; coefficients that repeat one row over
  the landmarks as ``coefficients_landmarks@row`` (J, E) and ``@rows`` (J,)). The key chains the settings, the
  window's inputs and the previous window's key, so a rerun reuses exactly the windows that are still
  valid; outputs (vertices included) are recomputed from the state, so a resumed run equals an
  uninterrupted one.

Frames without a face (``face_found`` False, or no landmark with weight > 0) get weight 0 on their
landmarks; the temporal prior on the codes bridges them and they are marked ``status="bridged"``.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np
import torch

from calib.camera import Camera
from calib.projection import camera_tensors, project_points
from capture.fit.records import FrameFit, WindowedFit, repeated_rows, stored_rows  # noqa: F401  (their home before)
from capture.io.atomic import atomic_path
from capture.fit.init import PnPSettings, initial_head_poses, rigid_align
from models.fit import (FIT3D_PRESETS, FIT_PRESETS, ActorAtPoints, FitSettings, Observations, SequenceFit, fit_sequence,
                        pose_face)
from models.fit_state import mesh_basis, shared_pose_maps
from models.mesh_map import map_vertices
from models.fit_noise import face_px_per_mm, residual_noise_px, temporal_prior_scale

__all__ = ["FrameFit", "fit_take", "fit_meshes", "resolve_settings", "resolved_settings_dict", "window_plan",
           "farthest_point_sample"]

# 2: SequenceFit has a jaw and coefficient base; 3: and a coefficient field; 4: the LM solve uses the robust
# loss's curvature (models.fit_lm.REWEIGHTED_STEPS), so its windows differ from version 3's
CACHE_VERSION = 4


@dataclass(frozen=True)
class TakeLandmarks:
    """A take's 2D landmarks as the fit reads them.

    ``points`` ``(T, L, 2)`` full-frame px (OpenCV pixel centres), NaN where missing; ``weights``
    ``(T, L)`` confidence in [0, 1] (None: 1 where finite); ``face_found`` ``(T,)`` bool (None: every
    frame; frames without a face get weight 0 and are bridged); ``template_points`` ``(L, 3)`` mm, the
    landmarks on the actor's template (the embedding).
    """

    points: np.ndarray
    weights: np.ndarray | None
    face_found: np.ndarray | None
    template_points: np.ndarray


def resolve_settings(settings: FitSettings | str | None, kind: str = "2d") -> FitSettings:
    """A :class:`FitSettings` from itself, a preset name or None (``default``); names are looked up in
    :data:`models.fit.FIT_PRESETS` for ``kind`` ``2d`` (landmarks) and in :data:`FIT3D_PRESETS` for ``3d``."""
    presets = FIT3D_PRESETS if kind == "3d" else FIT_PRESETS
    if settings is None:
        return presets["default"]
    if isinstance(settings, str):
        if settings not in presets:
            raise ValueError(f"unknown fit preset '{settings}'; choose one of {', '.join(presets)}")
        return presets[settings]
    if not isinstance(settings, FitSettings):
        raise TypeError(f"settings must be FitSettings or a preset name, got {type(settings).__name__}")
    return settings


def resolved_settings_dict(settings: FitSettings | str | None, window: int, overlap: int,
                           pnp: PnPSettings | None = None, threads: int | None = None, kind: str = "2d") -> dict:
    """Everything that decides a take fit, as plain data (for reports and cache keys)."""
    s = resolve_settings(settings, kind)
    preset = next((k for k, v in (FIT3D_PRESETS if kind == "3d" else FIT_PRESETS).items() if v == s), None)
    return {"preset": preset, "fit": s.to_dict(), "window": int(window), "overlap": int(overlap),
            "pnp": (pnp or PnPSettings()).to_dict(), "threads": threads, "blend": "smoothstep over the overlap"}


def window_plan(n_frames: int, window: int, overlap: int) -> list[tuple[int, int]]:
    """Windows ``[(start, end), ...]`` covering ``n_frames``: stride ``window - overlap``, last may be shorter."""
    _check_window(window, overlap)
    plan, s = [], 0
    while True:
        e = min(n_frames, s + window)
        plan.append((s, e))
        if e >= n_frames:
            return plan
        s = e - overlap


def _check_window(window: int, overlap: int) -> None:
    if window < 2 or overlap < 0 or overlap >= window:
        raise ValueError(f"need window >= 2 and 0 <= overlap < window; got window={window}, overlap={overlap}")


def farthest_point_sample(points: np.ndarray, n: int, start: int = 0) -> np.ndarray:
    """Indices of ``n`` farthest-point samples of ``points (N, 3)`` (deterministic from ``start``)."""
    N = len(points)
    if n >= N:
        return np.arange(N)
    idx = np.empty(n, np.int64)
    idx[0] = start
    d = np.linalg.norm(points - points[start], axis=1)
    for k in range(1, n):
        idx[k] = int(np.argmax(d))
        d = np.minimum(d, np.linalg.norm(points - points[idx[k]], axis=1))
    return np.sort(idx)


# ----------------------------------------------------------------------------------------------
# sources: what a window is fitted to


def reprojection_metrics(points: np.ndarray, weights: np.ndarray, landmarks_fit: np.ndarray) -> tuple[float, float]:
    """(RMS px over the landmarks used: weight > 0 and finite, NaN when none; NaN: no 3D error in 2D).

    ``points``, ``landmarks_fit`` ``(L, 2)`` px; ``weights`` ``(L,)``.
    """
    ok = (weights > 0) & np.isfinite(points).all(1)
    if not ok.any():
        return float("nan"), float("nan")
    r = landmarks_fit[ok] - points[ok]
    return float(np.sqrt((r ** 2).sum(1).mean())), float("nan")


@dataclass
class _Window:
    start: int
    end: int
    obs: Observations
    head_R0: torch.Tensor
    head_t0: torch.Tensor
    bridged: np.ndarray     # (J,) bool
    digest: str
    last: bool


class _LandmarkSource:
    """2D landmarks of a whole take (arrays of T x L: small, held in memory)."""

    def __init__(self, points2d, weights, face_found, head_R0, head_t0, K, dist, dtype, device):
        self.p, self.w, self.found = points2d, weights, face_found
        self.R0, self.t0 = head_R0, head_t0
        self.K, self.dist = K, dist
        self.dtype, self.device = dtype, device
        self.T = len(points2d)

    def window(self, s: int, window: int) -> _Window:
        e = min(self.T, s + window)
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=self.dtype, device=self.device)
        obs = Observations(points2d=t(self.p[s:e]), weights=t(self.w[s:e]), K=self.K, dist=self.dist)
        h = hashlib.sha1()
        for a in (self.p[s:e], self.w[s:e], self.R0[s:e], self.t0[s:e]):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
        bridged = ~(self.w[s:e] > 0).any(1)
        return _Window(s, e, obs, t(self.R0[s:e]), t(self.t0[s:e]), bridged, h.hexdigest(), e >= self.T)

    def frame_metrics(self, j: int, vertices: np.ndarray, landmarks_fit: np.ndarray) -> tuple[float, float]:
        return reprojection_metrics(self.p[j], self.w[j], landmarks_fit)

    def release(self, before: int) -> None:
        pass


class _MeshSource:
    """A registered mesh sequence, array or iterator, read window by window (frames kept until used)."""

    def __init__(self, meshes, sample_idx: np.ndarray, neutral_samples: np.ndarray, dtype, device):
        self.it = iter(meshes)
        self.buf: dict[int, np.ndarray] = {}
        self.next_frame = 0
        self.done = False
        self.idx = sample_idx
        self.neutral = neutral_samples
        self.dtype, self.device = dtype, device

    def _fill(self, upto: int) -> None:
        while not self.done and self.next_frame < upto:
            try:
                m = np.asarray(next(self.it), dtype=np.float64)
            except StopIteration:
                self.done = True
                break
            if m.ndim != 2 or m.shape[1] != 3:
                raise ValueError(f"mesh frame {self.next_frame}: expected (V, 3) vertices, got {m.shape}")
            self.buf[self.next_frame] = m
            self.next_frame += 1

    def window(self, s: int, window: int) -> _Window:
        self._fill(s + window + 1)  # one more: is this the last window?
        e = min(self.next_frame, s + window)
        if e <= s:
            raise ValueError("no mesh frames to fit")
        obs_np = np.stack([self.buf[j][self.idx] for j in range(s, e)])
        R0, t0 = zip(*(rigid_align(self.neutral, o) for o in obs_np))
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=self.dtype, device=self.device)
        h = hashlib.sha1(obs_np.tobytes())
        return _Window(s, e, Observations(points3d=t(obs_np)), t(np.stack(R0)), t(np.stack(t0)),
                       np.zeros(e - s, bool), h.hexdigest(), self.done and e >= self.next_frame)

    def frame_metrics(self, j: int, vertices: np.ndarray, landmarks_fit: np.ndarray) -> tuple[float, float]:
        m = self.buf[j]
        if m.shape != vertices.shape:
            raise ValueError(f"mesh frame {j} has {m.shape[0]} vertices; the actor's template has {vertices.shape[0]}")
        return float("nan"), float(np.linalg.norm(vertices - m, axis=1).mean())

    def release(self, before: int) -> None:
        for j in [j for j in self.buf if j < before]:
            del self.buf[j]


# ----------------------------------------------------------------------------------------------
# the window engine


@contextlib.contextmanager
def _num_threads(n: int | None):
    if not n:
        yield
        return
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def _warm_state(prev: dict, prev_start: int, prev_end: int, start: int, n_frames: int,
                head_R0: torch.Tensor, head_t0: torch.Tensor) -> dict:
    """The previous window's state moved to ``[start, start + n_frames)`` (see the module docstring).

    Per-frame tensors (codes and the base: jaw pose, coefficient offsets) of the overlap frames are
    the previous window's of the same frames, new frames take the previous window's last frame's.
    The head base keeps the previous window's on the overlap frames; a new frame's is its initial pose
    ``(head_R0, head_t0)`` (camera frame, ``x_cam = R x + t``) moved by the correction the solve made
    at the last overlap frame: with ``C = R_s R_i^T`` and ``d = t_s - C t_i`` (solved ``s`` and initial
    ``i`` pose there), ``(C R, C t + d)``. So the new frames start where the solved motion goes on, not
    with a step back to the initial poses that the solve's smooth-motion prior would have to undo.
    """
    state = dict(prev)
    n_ov = max(0, min(prev_end - start, n_frames))
    off = start - prev_start

    def moved(x: torch.Tensor, fill: torch.Tensor | None = None) -> torch.Tensor:
        new = x[-1:].expand(n_frames, *x.shape[1:]).clone() if fill is None else fill.clone()
        if n_ov:
            new[:n_ov] = x[off:off + n_ov]
        return new

    for k in ("codes", "jaw_R0", "jaw_t0", "coeff0", "field"):
        if k in prev:
            state[k] = moved(prev[k])
    R, t = head_R0, head_t0
    if n_ov:
        C = prev["head_R0"][off + n_ov - 1] @ head_R0[n_ov - 1].transpose(-1, -2)
        d = prev["head_t0"][off + n_ov - 1] - C @ head_t0[n_ov - 1]
        R, t = C @ head_R0, head_t0 @ C.transpose(-1, -2) + d
    state["head_R0"] = moved(prev["head_R0"], R)
    state["head_t0"] = moved(prev["head_t0"], t)
    return state


def _load_cached(cache_dir: Path | None, start: int, key: str) -> dict | None:
    if cache_dir is None:
        return None
    npz, pt = cache_dir / f"win_{start:06d}.npz", cache_dir / f"win_{start:06d}.pt"
    if not (npz.is_file() and pt.is_file()):
        return None
    try:
        from capture.io.arrays import npz_members

        npz_members(npz, max_bytes=64 << 20)  # headers only: a crafted archive is never loaded whole
        with np.load(npz, allow_pickle=False) as z:
            if str(z["key"]) != key:
                return None
        if pt.stat().st_size > 256 << 20:
            return None
        state = torch.load(pt, map_location="cpu", weights_only=True)
        return state if isinstance(state, dict) and all(isinstance(v, torch.Tensor) for v in state.values()) else None
    except Exception:  # OSError, ValueError, UnpicklingError, zip errors: damaged or crafted, solve again
        return None


def _save_cached(cache_dir: Path, start: int, key: str, state: dict, raw: dict) -> None:
    npz, pt = cache_dir / f"win_{start:06d}.npz", cache_dir / f"win_{start:06d}.pt"
    with atomic_path(pt) as tmp:
        torch.save({k: v.detach().cpu() for k, v in state.items()}, tmp)
    params = {k: raw[k] for k in ("head_R", "head_t", "jaw_R", "jaw_t", "code")}
    w = raw["coefficients_landmarks"]                  # (J, L, E): as its rows where each frame repeats one
    params.update(stored_rows("coefficients_landmarks", list(w)) or {"coefficients_landmarks": w})
    with atomic_path(npz) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, key=np.array(key), start=np.array(start), **params)


@torch.no_grad()
def _window_outputs(state: dict, settings: FitSettings, fit_actor: ActorAtPoints, out_actor: ActorAtPoints,
                    K: torch.Tensor | None, dist: torch.Tensor | None) -> dict:
    """Per-frame outputs of one solved window, as numpy arrays with a leading frame axis."""
    J = state["codes"].shape[0]
    fit = SequenceFit(J, fit_actor.n_expressions, settings, state["head_R0"], state["head_t0"])
    fit.load_state_dict(state)
    pose = fit.poses()
    w_lm = fit.coefficients(fit_actor)
    net_zero = fit.net_is_zero()
    out = {"head_R": pose.head_R, "head_t": pose.head_t, "jaw_R": pose.jaw_R, "jaw_t": pose.jaw_t,
           "code": fit.codes, "coefficients_base": fit.coeff0, **({} if net_zero else {"coefficients_landmarks": w_lm})}
    out = {k: v.detach().cpu().double().numpy() for k, v in out.items()}
    if net_zero:    # w_j(c) is the base at every point: a view of the (J, E) bases (repeated_rows per frame)
        out["coefficients_landmarks"] = np.broadcast_to(out["coefficients_base"][:, None, :], tuple(w_lm.shape))
    if K is not None:
        lm3 = pose_face(fit_actor, pose.head_R, pose.head_t, pose.jaw_R, pose.jaw_t, w_lm)
        out["landmarks_fit"] = project_points(lm3, K, dist).cpu().double().numpy()
    else:
        out["landmarks_fit"] = np.zeros((J, 0, 2))
    if net_zero:   # F_W at its zero start (2D default): the same coefficients at every vertex; each frame's mesh
        # is its map of the actor's features (models.fit_state.shared_pose_maps), made into vertices as it is
        # emitted (blended over overlaps like every output: the mesh is linear in the map)
        out["mesh_map"] = shared_pose_maps(out_actor, pose.head_R, pose.head_t, pose.jaw_R, pose.jaw_t,
                                           fit.coeff0).cpu().double().numpy()
        return out
    V = out_actor.points.shape[0]
    verts = np.empty((J, V, 3), np.float32)
    for j in range(J):  # one frame at a time: F_W at every vertex is the big evaluation
        sl = slice(j, j + 1)
        verts[j] = pose_face(out_actor, pose.head_R[sl], pose.head_t[sl], pose.jaw_R[sl], pose.jaw_t[sl],
                             fit.coefficients(out_actor, frames=sl))[0].cpu().numpy()
    out["vertices"] = verts
    return out


def _blend(a: dict, b: dict, i: int, alpha: float) -> dict:
    """Frame ``i`` of raw outputs: ``(1 - alpha) * a + alpha * b`` (rotations re-orthonormalised)."""
    out = {}
    for k in a:
        x = (1 - alpha) * a[k] + alpha * b[k]
        if k in ("head_R", "jaw_R"):
            U, _, Vt = np.linalg.svd(x)
            x = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
        out[k] = x.astype(a[k].dtype)
    return out


def _with_vertices(f: dict, basis: np.ndarray) -> dict:
    """A frame's raw outputs with its mesh as vertices (float64, as :func:`_window_outputs` gives them)."""
    if "mesh_map" not in f:
        return f
    f = dict(f)
    f["vertices"] = map_vertices(f.pop("mesh_map").astype(np.float32), basis).astype(np.float64)
    return f


def _frame(raw: dict, i: int) -> dict:
    return {k: v[i] for k, v in raw.items()}


def _smoothstep(x: float) -> float:
    return x * x * (3 - 2 * x)


def _run_windows(source, fit_actor: ActorAtPoints, out_actor: ActorAtPoints, settings: FitSettings, window: int,
                 overlap: int, cache_dir: Path | None, progress: Callable[[int, int | None], None] | None,
                 threads: int | None, base_key: str, total: int | None, K, dist,
                 timings: dict | None = None, vertices: bool = True) -> Iterator[FrameFit]:
    """The windows of ``source`` solved, blended over their overlaps and emitted frame by frame.

    ``vertices=False``: a frame whose mesh is a map of the actor's features (``FrameFit.mesh_map``) comes
    without its vertices, which the receiver makes with :func:`models.mesh_map.map_vertices` (the fit
    process sends under 1 KB a frame instead of 113 KB)."""
    tm = timings if timings is not None else {}
    basis = mesh_basis(out_actor)       # what a frame's mesh map maps (FrameFit.mesh_map); a few ms, once
    for k in ("solve_s", "outputs_s", "iterations", "lm_iterations", "windows_solved", "windows_cached"):
        tm.setdefault(k, 0)
    if cache_dir is not None:
        cache_dir = Path(cache_dir)
        cache_dir.mkdir(parents=True, exist_ok=True)
    prev_state, prev_range, prev_key = None, None, base_key
    held: list[tuple[int, dict]] = []   # the previous window's overlap frames, awaiting the blend
    adaptive = settings.adaptive_ref_px > 0 and K is not None   # 2D fits: smoothing follows the noise
    neutral = fit_actor.neutral.cpu().double().numpy() if adaptive else None   # (L, 3) the landmarks' template
    scale = 1.0                         # of coeff_temporal_weight, read from the previous window
    s = 0
    done = 0
    while True:
        win = source.window(s, window)
        if win is None:   # a stream that ended on the previous window's border (no overlap: nothing held)
            assert not held
            return
        J = win.end - win.start
        key = hashlib.sha1(f"{prev_key}|{win.start}:{win.end}|{win.digest}".encode()).hexdigest()
        with _num_threads(threads):
            state = _load_cached(cache_dir, win.start, key)
            t0 = time.perf_counter()
            if state is None:
                warm = None if prev_state is None else _warm_state(prev_state, *prev_range, win.start, J,
                                                                    win.head_R0, win.head_t0)
                n_it = settings.iterations if warm is None else (settings.warm_iterations or settings.iterations)
                state, raw = _solve_window(win, fit_actor, out_actor, _with_temporal_scale(settings, scale), settings,
                                           warm, n_it, K, dist, tm)
                if adaptive and prev_state is None:   # the first window: its own noise sets its scale
                    first = _noise_scale(win.obs, raw, settings, neutral, None)
                    if first != scale:
                        scale = first
                        state, raw = _solve_window(win, fit_actor, out_actor, _with_temporal_scale(settings, scale),
                                                   settings, state, n_it, K, dist, tm)
                tm["windows_solved"] += 1
                if cache_dir is not None:
                    _save_cached(cache_dir, win.start, key, state, raw)
            else:
                raw = _window_outputs(state, settings, fit_actor, out_actor, K, dist)
                tm["outputs_s"] += time.perf_counter() - t0
                tm["windows_cached"] += 1
        n_held = len(held)
        n_hold = 0 if win.last else min(overlap, J - 1)
        for i in range(J - n_hold):
            j = win.start + i
            f = _frame(raw, i)
            if i < n_held:
                hj, hf = held[i]
                assert hj == j
                if ("mesh_map" in hf) != ("mesh_map" in f):    # F_W zero in one window only: blend the meshes
                    hf, f = _with_vertices(hf, basis), _with_vertices(f, basis)
                f = _blend(hf, f, i, _smoothstep((i + 1) / (n_held + 1)))
            if "mesh_map" in f:
                mesh_map = f["mesh_map"].astype(np.float32)
                verts = map_vertices(mesh_map, basis) if vertices else None
            else:
                mesh_map, verts = None, f["vertices"].astype(np.float32)
            rms, err3d = source.frame_metrics(j, verts, f["landmarks_fit"])
            yield FrameFit(frame=j, head_R=f["head_R"], head_t=f["head_t"], jaw_R=f["jaw_R"], jaw_t=f["jaw_t"],
                           code=f["code"], coefficients_landmarks=repeated_rows(f["coefficients_landmarks"]),
                           vertices=verts, landmarks_fit=f["landmarks_fit"],
                           reprojection_rms_px=rms, status="bridged" if win.bridged[i] else "fitted",
                           error3d_mm=err3d, window_start=win.start, coefficients_base=f["coefficients_base"],
                           mesh_map=mesh_map)
            done += 1
            if progress is not None:
                progress(done, total)
        held = [(win.start + i, _frame(raw, i)) for i in range(J - n_hold, J)]
        source.release(win.end - n_hold)
        prev_state, prev_range, prev_key = state, (win.start, win.end), key
        if adaptive:
            scale = _noise_scale(win.obs, raw, settings, neutral, tm)
        if win.last:
            return
        s = win.end - n_hold


def _solve_window(win, fit_actor: ActorAtPoints, out_actor: ActorAtPoints, solve_settings: FitSettings,
                  settings: FitSettings, warm: dict | None, n_it: int, K, dist, tm: dict) -> tuple[dict, dict]:
    """One window solved with ``solve_settings`` from ``warm``: ``(state, per-frame outputs)``; timings in ``tm``."""
    t0 = time.perf_counter()
    res = fit_sequence(fit_actor, win.obs, solve_settings, win.head_R0, win.head_t0, warm_start=warm, iterations=n_it)
    state = {k: v.detach().clone() for k, v in res.fit.state_dict().items()}
    tm["solve_s"] += time.perf_counter() - t0
    tm["iterations"] += len(res.losses)
    tm["lm_iterations"] += res.lm_iterations
    t0 = time.perf_counter()
    raw = _window_outputs(state, settings, fit_actor, out_actor, K, dist)
    tm["outputs_s"] += time.perf_counter() - t0
    return state, raw


def _with_temporal_scale(settings: FitSettings, scale: float) -> FitSettings:
    return settings if scale == 1.0 else replace(settings, coeff_temporal_weight=settings.coeff_temporal_weight * scale)


def _noise_scale(obs: Observations, raw: dict, settings: FitSettings, neutral: np.ndarray, tm: dict | None) -> float:
    """The temporal prior's scale for the next solve, from a solved window's residuals (models.fit_noise);
    records the window's noise and the scales' range in ``tm`` (unless None)."""
    p2, w2 = obs.points2d.cpu().numpy(), obs.weights.cpu().numpy()
    sigma, per_frame = residual_noise_px(p2, w2, raw["landmarks_fit"])
    ppm = face_px_per_mm(p2, w2, neutral) if settings.adaptive_ref_px_per_mm > 0 else float("nan")
    k = temporal_prior_scale(sigma, per_frame, settings.adaptive_ref_px, settings.adaptive_ref_landmarks,
                             settings.adaptive_max, ppm, settings.adaptive_ref_px_per_mm)
    if tm is None:
        return k
    if np.isfinite(sigma):
        noise = tm.setdefault("_landmark_noise_px", [])
        noise.append(sigma)
        tm["landmark_noise_px"] = float(np.median(noise))
        tm["landmarks_per_frame"] = per_frame
        if np.isfinite(ppm):
            tm["face_px_per_mm"] = ppm
    tm["temporal_prior_scale_min"] = min(k, tm.get("temporal_prior_scale_min", k))
    tm["temporal_prior_scale_max"] = max(k, tm.get("temporal_prior_scale_max", k))
    return k


def _fingerprint(*parts) -> str:
    h = hashlib.sha1()
    for p in parts:
        if isinstance(p, torch.Tensor):
            p = p.detach().cpu().double().numpy()
        if isinstance(p, np.ndarray):
            h.update(np.ascontiguousarray(p, dtype=np.float64).tobytes())
        else:
            h.update(json.dumps(p, sort_keys=True, default=str).encode())
    return h.hexdigest()


def _query(actor, points: np.ndarray, device) -> ActorAtPoints:
    return ActorAtPoints.query(actor.model, torch.as_tensor(points, dtype=torch.float32, device=device),
                               getattr(actor, "jaw_rot6d", None), getattr(actor, "jaw_t", None))


def template_vertices(actor) -> np.ndarray:
    """``(V, 3)`` float64 mm: the actor's template vertices (its arrays, without building a trimesh)."""
    v = getattr(actor, "template_vertices", None)
    return np.asarray(actor.template.vertices if v is None else v, np.float64)


def query_template(actor, device) -> ActorAtPoints:
    """The actor at every template vertex: its cached evaluation (``Actor.at_template``) when it has one
    on ``device``."""
    tv = template_vertices(actor)
    cached = getattr(actor, "at_template", None)
    if cached is None or next(iter(actor.model.parameters())).device != torch.device(device):
        return _query(actor, tv, device)
    return ActorAtPoints.query(actor.model, torch.as_tensor(tv, dtype=torch.float32, device=device),
                               getattr(actor, "jaw_rot6d", None), getattr(actor, "jaw_t", None), evaluated=cached())


# ----------------------------------------------------------------------------------------------
# public entry points


def fit_take(actor, landmarks: TakeLandmarks, camera: Camera, how: WindowedFit = WindowedFit(),
             pnp: PnPSettings | None = None, progress: Callable[[int, int | None], None] | None = None,
             timings: dict | None = None) -> Iterator[FrameFit]:
    """Fit ``actor`` to a take's 2D landmarks; yields one :class:`FrameFit` per frame, in frame order.

    Args:
        actor: a loaded actor (:func:`capture.actor.package.load_actor`): ``.model`` and ``.template``.
        landmarks: the take's landmarks, confidences and their template points (:class:`TakeLandmarks`).
        camera: the calibrated camera (K, dist).
        how: settings, windows, cache, device and threads (:class:`WindowedFit`).
        pnp: how the initial head poses are found.
        progress: ``progress(frames_done, total_frames)`` after each yielded frame.
        timings: a dict that receives seconds per stage (``query_s``, ``pnp_s``, ``solve_s``,
            ``outputs_s``) and counts (``iterations``, ``windows_solved``, ``windows_cached``).

    Raises ValueError on mismatched shapes, bad window settings or when no frame has a usable face.
    """
    s = resolve_settings(how.settings)
    window, overlap, device = how.window, how.overlap, how.device
    _check_window(window, overlap)
    pnp = pnp or PnPSettings()
    points2d, weights, face_found = landmarks.points, landmarks.weights, landmarks.face_found
    landmark_template_points = landmarks.template_points
    points2d = np.asarray(points2d, np.float64)
    if points2d.ndim != 3 or points2d.shape[2] != 2:
        raise ValueError(f"points2d should be (T, L, 2); got {points2d.shape}")
    T, L = points2d.shape[:2]
    finite = np.isfinite(points2d).all(2)
    w = finite.astype(np.float64) if weights is None else np.asarray(weights, np.float64).copy()
    if w.shape != (T, L):
        raise ValueError(f"weights should be ({T}, {L}) like points2d; got {w.shape}")
    found = np.ones(T, bool) if face_found is None else np.asarray(face_found, bool)
    if found.shape != (T,):
        raise ValueError(f"face_found should be ({T},); got {found.shape}")
    tp = np.asarray(landmark_template_points, np.float64)
    if tp.shape != (L, 3):
        raise ValueError(f"landmark_template_points should be ({L}, 3) for {L} landmarks; got {tp.shape}")
    w = np.where(finite & found[:, None] & np.isfinite(w), np.clip(w, 0.0, None), 0.0)

    tm = timings if timings is not None else {}
    t_start = time.perf_counter()
    fit_actor = _query(actor, tp, device)
    out_actor = query_template(actor, device)
    tm["query_s"] = time.perf_counter() - t_start
    t_start = time.perf_counter()
    R0, t0, _ = initial_head_poses(fit_actor.neutral.cpu().double().numpy(), points2d, w, camera.K,
                                   camera.dist, pnp)
    tm["pnp_s"] = time.perf_counter() - t_start
    K, dist = camera_tensors(camera, torch.float32, device)
    src = _LandmarkSource(points2d, w, found, R0, t0, K, dist, torch.float32, device)
    base = _fingerprint(CACHE_VERSION, "2d", resolved_settings_dict(s, window, overlap, pnp), fit_actor.neutral,
                        fit_actor.expressions, out_actor.neutral, camera.K, camera.dist)
    return _run_windows(src, fit_actor, out_actor, s, window, overlap,
                        None if how.cache_dir is None else Path(how.cache_dir), progress, how.threads, base, T, K,
                        dist, tm)


def fit_meshes(actor, meshes: np.ndarray | Iterable[np.ndarray], how: WindowedFit = WindowedFit(),
               n_samples: int | None = None, progress: Callable[[int, int | None], None] | None = None,
               timings: dict | None = None) -> Iterator[FrameFit]:
    """Fit ``actor`` to a registered mesh sequence (``capture fit3d``); yields :class:`FrameFit` per frame.

    ``meshes`` is ``(T, V, 3)`` or an iterator of ``(V, 3)`` arrays in the template's vertex order
    (mm, any rigid frame). ``how.settings`` names a preset of :data:`models.fit.FIT3D_PRESETS`. The 3D
    position loss uses ``n_samples`` farthest-point samples of the template vertices (None: every
    vertex with a coefficient field, whose solve grows mildly with them, else 1,000); outputs are
    evaluated at all vertices and ``error3d_mm`` is their mean distance to the given mesh. The initial
    head pose per frame is the rigid (Kabsch) alignment of the actor's neutral at the samples.
    """
    s = resolve_settings(how.settings, "3d")
    window, overlap, device = how.window, how.overlap, how.device
    _check_window(window, overlap)
    tv = template_vertices(actor)
    if n_samples is None:
        n_samples = len(tv) if s.field_centres > 0 and s.field_iterations > 0 else 1000
    idx = farthest_point_sample(tv, n_samples)
    fit_actor = _query(actor, tv[idx], device)
    out_actor = query_template(actor, device)
    total = len(meshes) if hasattr(meshes, "__len__") else None
    src = _MeshSource(meshes, idx, fit_actor.neutral.cpu().double().numpy(), torch.float32, device)
    base = _fingerprint(CACHE_VERSION, "3d", resolved_settings_dict(s, window, overlap, kind="3d"), n_samples,
                        fit_actor.neutral, out_actor.neutral)
    return _run_windows(src, fit_actor, out_actor, s, window, overlap,
                        None if how.cache_dir is None else Path(how.cache_dir), progress, how.threads, base, total,
                        None, None, timings)
