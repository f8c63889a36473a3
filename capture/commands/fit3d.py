"""``capture fit3d MESHES --actor A``: the options of a 3D fit; the work is :func:`capture.run.fit3d.fit3d_take`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer



def fit3d_command(
    meshes: Path = typer.Argument(..., help="Folder of registered OBJ/PLY meshes in the actor's topology, one per "
                                  "frame, in file-name order."),
    actor: str = typer.Option(..., "--actor", help="Actor name or folder."),
    out: Optional[Path] = typer.Option(None, "--out", help="Output folder (default ./runs/<folder name>)."),
    units: str = typer.Option("mm", "--units", help="Units of the meshes: mm, cm, m, in."),
    fps: float = typer.Option(30.0, "--fps", help="Frame rate of the sequence (USD time samples)."),
    formats: Optional[str] = typer.Option(None, "--formats", help="Exports: obj, ply, usd, npz (default obj,usd,npz)."),
    preset: str = typer.Option("default", "--preset", help="Fit preset: default (dense per-point coefficient "
                               "field, every vertex), networks (Adam on F_T/F_W, 1,000 vertices) or paper."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the fit."),
    iterations: Optional[int] = typer.Option(None, "--iterations", help="Fit iterations of the first window "
                                             "(default: the preset's; later windows use at most as many)."),
    threads: int = typer.Option(1, "--threads", help="CPU threads of the fit (raise it on a dedicated machine)."),
    device: str = typer.Option("cpu", "--device", help="Torch device (cpu, cuda)."),
    window: int = typer.Option(30, "--window", help="Frames per fitting window."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace the run in --out."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars."),
) -> None:
    """Fit an actor to a registered 3D mesh sequence (offline reprocessing of scans)."""
    from capture.run.fit3d import FIT3D_FORMATS, Fit3dConfig, fit3d_take
    from capture.run.inputs import parse_formats
    from capture.run.report import print_summary

    cfg = Fit3dConfig(meshes=meshes, actor=actor, out=out, units=units, fps=fps,
                      formats=parse_formats(formats, FIT3D_FORMATS), preset=preset, seed=seed, iterations=iterations,
                      threads=threads, device=device,
                      window=window, overlap=min(6, max(0, window // 5)), overwrite=overwrite, progress=progress)
    print_summary(fit3d_take(cfg))
