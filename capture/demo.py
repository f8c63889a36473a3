"""``capture demo``: the whole pipeline on the bundled sample, no user data and no downloads.

1. **Actor**: the pretrained demo actor (``capture/data/demo_actor``) when it is bundled, copied to
   ``OUT/actor``; otherwise a QUICK, low-accuracy actor trained from the bundled sample shapes and
   bones (``capture actor train --sample`` with a small network and few iterations).
2. **Take**: ``capture synth`` renders a short take of that actor with known truth (``OUT/take``).
3. **Run**: ``capture run`` on it with the synthetic detector and the take's camera (``OUT/run``).
4. **Check**: the mean 3D vertex error against the take's ``truth_meshes.npz`` and the reprojection
   error, and where the outputs are.

Every step skips what is already done, so running the demo again is quick and an interrupted demo
resumes.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class DemoConfig:
    """Settings of ``capture demo`` (sized to finish in about 5 minutes on 2 CPU cores)."""

    out: Path = Path("runs/demo")
    frames: int = 60
    size: str = "640x360"
    fps: float = 25.0
    landmarks: int = 300
    train_width: int = 64
    train_iterations: int = 600
    train_points_per_step: int = 2000
    fit_iterations: int | None = None       # the preset's
    window: int = 30
    threads: int = 1
    """Torch threads for training and fitting. One: on a shared or busy 2-core machine two threads spin
    against each other (measured 10x slower under load); alone they gain little on these small problems."""
    progress: bool = True


def bundled_demo_actor() -> Path | None:
    p = Path(__file__).resolve().parent / "data" / "demo_actor"
    return p if (p / "actor.json").is_file() else None


def demo_actor(cfg: DemoConfig, say) -> Path:
    actor = cfg.out / "actor"
    if (actor / "actor.json").is_file():
        say(f"actor: reusing {actor}")
        return actor
    bundled = bundled_demo_actor()
    if bundled is not None:
        shutil.copytree(bundled, actor, dirs_exist_ok=True)
        say(f"actor: the bundled pretrained demo actor, copied to {actor}")
        return actor
    say(f"actor: no pretrained demo actor bundled; training a QUICK, LOW-ACCURACY actor from the sample "
        f"(width {cfg.train_width}, {cfg.train_iterations} iterations of {cfg.train_points_per_step} points; the real one takes ~9 min on 2 cores with AMX: "
        f"capture actor train sample --sample)")
    from capture.actor.sample import sample_bones, sample_shapes_dir
    from capture.actor.training import TrainOptions, TrainingProgress, train_actor

    skull, jaw = sample_bones()
    train_actor(TrainOptions(actor=str(actor), shapes=sample_shapes_dir(), skull=skull, jaw=jaw, units="mm",
                             overrides=dict(width=cfg.train_width, iterations=cfg.train_iterations,
                                            points_per_step=cfg.train_points_per_step)),
                TrainingProgress(enabled=cfg.progress), report=say)
    return actor


def run_demo(cfg: DemoConfig, say=print) -> dict:
    """Run the demo; returns the figures it prints (3D error in mm, reprojection error in px, paths)."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(cfg.threads)
    try:
        return _run_demo(cfg, say)
    finally:
        torch.set_num_threads(threads)


def _run_demo(cfg: DemoConfig, say) -> dict:
    from capture.run.take import run_take
    from capture.run.inputs import RunConfig
    from capture.run.report import print_summary
    from capture.run.stages import iter_fits
    from capture.synth.progress import synthesize_shown
    from capture.synth.take import SynthConfig, parse_size

    t0 = time.perf_counter()
    cfg.out.mkdir(parents=True, exist_ok=True)
    actor = demo_actor(cfg, say)
    take = cfg.out / "take"
    if (take / "truth.json").is_file():
        say(f"take: reusing {take}")
    else:
        say(f"take: rendering {cfg.frames} frames at {cfg.size} with capture synth")
        synthesize_shown(SynthConfig(actor=str(actor), out=take, frames=cfg.frames, size=parse_size(cfg.size),
                                     fps=cfg.fps, landmarks=cfg.landmarks, preset="talk", overwrite=True),
                         cfg.progress)
    run_out = cfg.out / "run"
    its = "" if cfg.fit_iterations is None else f" --iterations {cfg.fit_iterations}"
    say(f"run: capture run {take / 'take.mp4'} --actor {actor} --camera {take / 'camera.json'} --out {run_out}{its}")
    report = run_take(RunConfig(video=take / "take.mp4", actor=str(actor), camera=take / "camera.json",
                                out=run_out, iterations=cfg.fit_iterations, window=cfg.window,
                                threads=cfg.threads, progress=cfg.progress))
    print_summary(report)
    fit_dir = next(s["fit_dir"] for s in report["stages"] if s["stage"] == "fit")
    with np.load(take / "truth_meshes.npz", allow_pickle=False) as z:
        truth = z["vertices"]
    err = [float(np.linalg.norm(f.vertices - truth[int(f.frame)], axis=1).mean())
           for f in iter_fits(Path(fit_dir))]
    result = {"mean_3d_error_mm": float(np.mean(err)), "worst_3d_error_mm": float(np.max(err)),
              "mean_reprojection_px": report["error"]["mean"], "run": str(run_out), "take": str(take),
              "actor": str(actor), "seconds": time.perf_counter() - t0}
    say(f"demo: mean 3D vertex error against the truth {result['mean_3d_error_mm']:.2f} mm (worst frame "
        f"{result['worst_3d_error_mm']:.2f} mm), mean reprojection error {result['mean_reprojection_px']:.2f} px "
        f"(confident landmarks)")
    say(f"demo: outputs in {run_out} (meshes/, take.usdc, params.npz, landmarks.npz, overlay.mp4, report.json); "
        f"the take and its truth in {take}; {result['seconds']:.0f} s")
    return result
