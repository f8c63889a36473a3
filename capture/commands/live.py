"""``capture live SOURCE --actor A``: the options of a live capture; the work is :func:`capture.run.live.run_live`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def live_command(
    source: str = typer.Argument(..., help="Camera index (0), stream URL FFmpeg reads, or a video file (played at "
                                 "its frame rate)."),
    actor: str = typer.Option(..., "--actor", help="Actor name or folder."),
    detector: Optional[Path] = typer.Option(None, "--detector", help="Landmark detector FILE.onnx (+ FILE.json); "
                                            "default for a file: the one in its folder/detector/."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="Camera file; default: a 60 deg guess."),
    out: Optional[Path] = typer.Option(None, "--out", help="Folder of the take (default ./runs/live_<source>)."),
    formats: str = typer.Option("npz,usd", "--formats", help="Exports of the take: obj, ply, usd, npz."),
    lag: int = typer.Option(5, "--lag", help="Frames until a frame is final (its window is lag + 1 frames)."),
    json_to: str = typer.Option("stdout", "--json", help="Per-frame JSON lines: stdout, none or udp://HOST:PORT."),
    max_frames: Optional[int] = typer.Option(None, "--max-frames", help="Stop after this many source frames."),
    fps: Optional[float] = typer.Option(None, "--fps", help="Pace of a file source (default: its frame rate)."),
    preset: str = typer.Option("default", "--preset", help="Fit preset: default or paper."),
    threads: int = typer.Option(1, "--threads", help="Threads of the detector and of the fit (each)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Say what was done at the end (stderr)."),
) -> None:
    """Fit a camera, stream or file live: each frame final LAG frames later, one JSON line per frame; frames are
    dropped, and counted, rather than falling behind. Ctrl-C ends the capture and writes the take."""
    import sys

    from capture.export import parse_formats
    from capture.io.signals import sigterm_as_interrupt
    from capture.run.live import LiveConfig, run_live

    fmts = parse_formats(formats)
    other = [f for f in fmts if f not in ("obj", "ply", "usd", "npz")]
    if other:
        from capture.io.errors import CaptureError

        raise CaptureError(f"capture live writes no {', '.join(other)}; choose --formats from obj, ply, usd, npz")
    cfg = LiveConfig(source=source, actor=actor, detector=detector, camera=camera, out=out, formats=fmts, lag=lag,
                     json_to=json_to, max_frames=max_frames, fps=fps, preset=preset, threads=threads,
                     progress=progress)
    with sigterm_as_interrupt():
        run_live(cfg, say=(lambda m: print(m, file=sys.stderr)) if progress else None)
