"""``capture detect VIDEO --detector X.onnx``: the detector alone; the work is :func:`capture.detector.standalone.run_detect`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def detect_command(
    video: Path = typer.Argument(..., help="The video (any format OpenCV/FFmpeg reads)."),
    detector: Optional[Path] = typer.Option(None, "--detector", help="Landmark detector FILE.onnx with FILE.json "
                                            "beside it; default: the one in VIDEO's folder/detector/."),
    out: Optional[Path] = typer.Option(None, "--out", help="Output folder (default ./runs/<video stem>, the "
                                       "folder of 'capture run', whose detection cache it shares)."),
    frames: Optional[str] = typer.Option(None, "--frames", help="START:END, END exclusive (default all)."),
    threads: int = typer.Option(1, "--threads", help="CPU threads of the detector."),
    overlay: bool = typer.Option(True, "--overlay/--no-overlay", help="Write overlay.mp4 (crops and landmarks)."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar."),
) -> None:
    """Run a landmark detector alone: landmarks, an overlay video and a summary (faces, confidence, jitter)."""
    from capture.detector.standalone import DetectConfig, print_summary, run_detect

    summary = run_detect(DetectConfig(video=video, detector=detector, out=out, frames=frames, threads=threads,
                                      overlay=overlay, progress=progress))
    print_summary(summary)
