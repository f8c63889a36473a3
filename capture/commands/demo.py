"""``capture demo``: the whole pipeline on the bundled sample; the work is :func:`capture.demo.run_demo`."""

from __future__ import annotations

from pathlib import Path

import typer

from capture.io.errors import CaptureError


def demo_command(
    out: Path = typer.Option(Path("runs/demo"), "--out", help="Folder for the demo's actor, take and run."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars."),
) -> None:
    """The whole pipeline on the bundled sample (actor, synthetic take, capture run, error against the truth)."""
    from capture.demo import DemoConfig, run_demo

    if out.exists() and not out.is_dir():
        raise CaptureError(f"--out {out} is a file; give a folder")
    run_demo(DemoConfig(out=out, progress=progress), say=typer.echo)
