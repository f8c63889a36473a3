"""``capture run VIDEO --actor A``: the options of a take's capture; the work is :func:`capture.run.take.run_take`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer



def run_command(
    video: Path = typer.Argument(..., help="The video of the take (any format OpenCV/FFmpeg reads)."),
    actor: str = typer.Option(..., "--actor", help="Actor name or folder (see 'capture actor list')."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="Camera file (capture calibrate JSON or OpenCV "
                                          "YAML); default: a documented 60 deg guess, flagged in the report."),
    detector: Optional[Path] = typer.Option(None, "--detector", help="Landmark detector FILE.onnx with FILE.json "
                                            "beside it; default: the one in VIDEO's folder/detector/."),
    out: Optional[Path] = typer.Option(None, "--out", help="Output folder (default ./runs/<video stem>)."),
    frames: Optional[str] = typer.Option(None, "--frames", help="START:END, END exclusive (default all)."),
    formats: Optional[str] = typer.Option(None, "--formats", help="Exports: comma-separated obj, ply, usd, npz, "
                                          "overlay, curves (default obj,usd,npz,overlay; curves adds usd)."),
    overlay: Optional[str] = typer.Option(None, "--overlay", help="Overlay layers: comma-separated mesh, wireframe, "
                                          "contours, landmarks, header, or none (default mesh,contours,landmarks,"
                                          "header)."),
    preset: str = typer.Option("default", "--preset", help="Fit preset: default or paper."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the fit."),
    iterations: Optional[int] = typer.Option(None, "--iterations", help="Fit iterations of the first window "
                                             "(default: the preset's; later windows use at most as many)."),
    threads: int = typer.Option(1, "--threads", help="CPU threads of the detector and the fit (1 is safest on a "
                                 "shared machine: busy threads spinning against other jobs were 10x slower)."),
    device: str = typer.Option("cpu", "--device", help="Torch device of the fit (cpu, cuda)."),
    window: int = typer.Option(30, "--window", help="Frames per fitting window."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the run in --out (another take's, "
                                   "or redo this one from scratch)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars."),
) -> None:
    """Capture a take: detect landmarks, fit the actor, export meshes, USD, parameters and an overlay.

    Each stage skips work already done: rerunning is cheap and an interrupted run resumes."""
    from capture.run.inputs import RunConfig, parse_formats, parse_overlay
    from capture.run.report import print_summary
    from capture.run.take import run_take

    cfg = RunConfig(video=video, actor=actor, camera=camera, detector=detector, out=out, frames=frames,
                    formats=parse_formats(formats), preset=preset, seed=seed, iterations=iterations, threads=threads,
                    device=device, window=window,
                    overlap=min(6, max(0, window // 5)), overwrite=overwrite, progress=progress,
                    overlay=parse_overlay(overlay))
    report = run_take(cfg)
    print_summary(report)
