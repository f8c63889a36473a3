"""Shared pieces of the take benchmarks (``bench_takes.py``, ``bench_scale.py``): synthetic takes from
``capture synth`` and the accuracy figures of a 2D fit against their truth.

Conventions: vertices in mm in the camera frame (OpenCV axes), landmarks in px (pixel centres at
integers). Jitter is measured on vertex trajectories high-passed over time (signal minus its Gaussian
smoothing with sigma 2 frames).
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d

REPO = Path(__file__).resolve().parents[1]
DEFAULT_ACTOR = REPO / "capture" / "data" / "demo_actor"
HIGHPASS_SIGMA = 2.0


def peak_rss_mb() -> float:
    """Peak resident memory of this process so far (MB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def synth(actor: Path, out: Path, frames: int, size: str, preset: str, seed: int, landmarks: int,
          distortion: str | None = None) -> Path:
    """Render a take with ``capture synth`` in a child process (its memory stays out of our figures)."""
    cmd = [sys.executable, "-m", "capture.cli", "synth", "--actor", str(actor), "--out", str(out), "--frames",
           str(frames), "--size", size, "--preset", preset, "--seed", str(seed), "--landmarks", str(landmarks),
           "--no-progress", "--overwrite"]
    if distortion:
        cmd += ["--distortion", distortion]
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    r = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"capture synth failed: {r.stderr.strip()[-2000:]}")
    return out


@dataclass
class TakeInputs:
    """A synthetic take's true landmarks (+ noise) and truth meshes."""

    points2d: np.ndarray          # (T, L, 2) px, noisy
    weights: np.ndarray           # (T, L) 1 visible, 0 hidden
    template_points: np.ndarray   # (L, 3) mm, the landmarks on the template
    camera: object                # calib.camera.Camera
    truth: np.ndarray             # (T, V, 3) mm, camera frame


def load_take(take: Path, template, noise_px: float, seed: int = 0) -> TakeInputs:
    """True landmarks of a ``capture synth`` take plus Gaussian noise of ``noise_px`` (px, per axis)."""
    from calib.camera_io import read_camera

    lm = np.load(take / "truth_landmarks.npz")
    truth = np.load(take / "truth_meshes.npz")["vertices"]
    tv, tf = np.asarray(template.vertices), np.asarray(template.faces)
    tp = np.einsum("lk,lkc->lc", lm["barycentric"], tv[tf[lm["face_index"]]])
    rng = np.random.default_rng(seed)
    pts = lm["points_2d"] + rng.normal(0.0, noise_px, lm["points_2d"].shape)
    return TakeInputs(pts, lm["visible"].astype(np.float64), tp, read_camera(take / "camera.json"), truth)


def highpass(x: np.ndarray) -> np.ndarray:
    """Trajectory minus its temporal Gaussian smoothing (axis 0 = frames)."""
    return x - gaussian_filter1d(x, HIGHPASS_SIGMA, axis=0, mode="nearest")


def accuracy(vertices: np.ndarray, truth: np.ndarray, rms_px: np.ndarray) -> dict:
    """Figures of a fit: ``vertices``, ``truth`` (T, V, 3) mm; ``rms_px`` (T,) reprojection RMS per frame.

    * ``mean_mm`` / ``p95_mm``: vertex distance to the truth over all vertices and frames,
    * ``rms_px``: reprojection RMS over frames,
    * ``jitter_mm`` / ``truth_jitter_mm``: RMS length of the high-passed vertex trajectories of the fit
      and of the truth; ``jitter_excess_mm`` their difference (target <= 0.1 mm),
    * ``jitter_error_mm``: RMS length of the high-passed error trajectory ``hp(fit) - hp(truth)``.
    """
    V, Tr = np.asarray(vertices, np.float64), np.asarray(truth, np.float64)
    err = np.linalg.norm(V - Tr, axis=2)
    out = {"mean_mm": float(err.mean()), "p95_mm": float(np.percentile(err, 95)),
           "rms_px": float(np.sqrt(np.nanmean(np.asarray(rms_px) ** 2))), "per_frame_mm": err.mean(1).tolist(),
           "per_vertex_mm": err.mean(0)}
    if len(V) >= 5:
        hv, ht = highpass(V), highpass(Tr)
        rms = lambda a: float(np.sqrt((np.linalg.norm(a, axis=2) ** 2).mean()))
        out.update(jitter_mm=rms(hv), truth_jitter_mm=rms(ht), jitter_error_mm=rms(hv - ht))
        out["jitter_excess_mm"] = out["jitter_mm"] - out["truth_jitter_mm"]
    return out


def stage_ms(tm: dict, n: int) -> dict:
    """Milliseconds per frame of each stage of a ``fit_take`` timings dict."""
    return {k[:-2]: 1000.0 * tm.get(k, 0.0) / n for k in ("query_s", "pnp_s", "solve_s", "outputs_s", "total_s")}


def save_png(fig, path: Path) -> Path:
    """Write a matplotlib figure atomically."""
    from capture.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    return path


def front_heatmap(ax, vertices: np.ndarray, faces: np.ndarray, values: np.ndarray, vmax: float, title: str):
    """Per-vertex ``values`` on the template seen from the front (ICT frame: z towards the face front)."""
    tri = np.asarray(faces)[:, :3]
    a, b, c = vertices[tri[:, 0]], vertices[tri[:, 1]], vertices[tri[:, 2]]
    front = np.cross(b - a, c - a)[:, 2] > 0
    tri_f = tri[front][np.argsort(((a + b + c) / 3)[front, 2])]     # painter's order, back to front
    pc = ax.tripcolor(vertices[:, 0], vertices[:, 1], tri_f, facecolors=values[tri_f].mean(1), cmap="magma",
                      vmin=0, vmax=vmax, shading="flat")
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(title, fontsize=9)
    return pc
