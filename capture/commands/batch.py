"""``capture batch SHOOT.toml``: the options of a shoot; the work is :func:`capture.batch.runner.run_batch`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer



def batch_command(
    shoot: Path = typer.Argument(..., help="The shoot file (TOML: \\[shoot], \\[defaults], "
                                 "\\[\\[take]]; see docs/shoot_example.toml)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Batch output folder (default: the shoot file's "
                                       "\\[shoot] out, else runs/<shoot name> beside the shoot file)."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Tasks (takes, or segments of long takes) run at a "
                                          "time (default: this machine's cores / --threads; with --address, the "
                                          "cluster's CPUs / --threads)."),
    threads: int = typer.Option(1, "--threads", help="CPU cores (torch and detector threads) per take."),
    address: Optional[str] = typer.Option(None, "--address", help="Join an existing Ray cluster (e.g. "
                                          "'auto' or 'head-node:6379') instead of starting a local Ray."),
    segment_frames: Optional[int] = typer.Option(None, "--segment-frames", help="Split takes longer than this "
                                                 "into overlapping segments fitted in parallel and blended "
                                                 "(default: the shoot file's segment_frames, else 0: off)."),
    dry_run: bool = typer.Option(False, "--dry-run", help="List the takes and what would run; run nothing."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show the shoot's progress bar."),
) -> None:
    from capture.batch.runner import BatchConfig, run_batch

    # The docstring (the command's help) is set below: typer keeps its line breaks.
    report = run_batch(BatchConfig(shoot=shoot, out=out, workers=workers, threads=threads, address=address,
                                   segment_frames=segment_frames, dry_run=dry_run, progress=progress))
    if not dry_run and (report["totals"]["failed"] or report["totals"]["interrupted"]):
        raise typer.Exit(1)


batch_command.__doc__ = ("Capture every take of a shoot (like capture run on each), in parallel on Ray.\n\n"
                         "Takes done before with the same settings are skipped; a failed take is retried once "
                         "and never stops the others. Exit status 1 when any take failed.")
