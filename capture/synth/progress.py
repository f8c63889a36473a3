"""Rendering a synthetic take with a progress bar (one bar per stage), or silently."""

from __future__ import annotations

from pathlib import Path


def synthesize_shown(cfg, progress: bool = True) -> Path:
    """:func:`capture.synth.take.synthesize` of ``cfg`` (a ``SynthConfig``), showing a bar per stage when ``progress``."""
    from capture.synth.take import synthesize

    if not progress:
        return synthesize(cfg)
    from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TimeRemainingColumn()) as bar:
        state: dict = {}

        def on_stage(desc: str, total: int) -> None:
            state["task"] = bar.add_task(desc, total=total)

        return synthesize(cfg, on_stage=on_stage, on_frame=lambda: bar.advance(state["task"]))
