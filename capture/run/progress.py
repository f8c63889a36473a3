"""Progress bars of ``capture run`` stages: frames done, frames per second and time left (rich).

:func:`progress_listener` lets a caller follow the stages without bars (``capture batch`` forwards
the frames of each take to its shoot-wide progress).
"""

from __future__ import annotations

import contextlib
from typing import Callable, Iterator

_LISTENERS: list[Callable[[str, int], None]] = []


@contextlib.contextmanager
def progress_listener(fn: Callable[[str, int], None]) -> Iterator[None]:
    """Within the block every stage's ``advance(n)`` also calls ``fn(stage label, n)``, bars shown or not."""
    _LISTENERS.append(fn)
    try:
        yield
    finally:
        _LISTENERS.remove(fn)


class StageProgress:
    """One bar per stage; a no-op when disabled. Use as a context manager."""

    def __init__(self, label: str, total: int, enabled: bool = True):
        self.label, self.total, self.enabled = label, int(total), enabled
        self.bar = None
        self.task = None

    def __enter__(self) -> "StageProgress":
        if self.enabled and self.total > 0:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn,
                                       TimeElapsedColumn, TimeRemainingColumn)
            from rich.text import Text

            class Speed(ProgressColumn):
                def render(self, task):
                    return Text(f"{task.speed:.2f} frames/s" if task.speed else "- frames/s")

            self.bar = Progress(TextColumn(f"{self.label:<8}"), BarColumn(), MofNCompleteColumn(), Speed(),
                                TimeElapsedColumn(), TimeRemainingColumn(), TextColumn("left"))
            self.bar.start()
            self.task = self.bar.add_task(self.label, total=self.total)
        return self

    def advance(self, n: int = 1) -> None:
        for fn in _LISTENERS:
            fn(self.label, n)
        if self.bar is not None and n:
            self.bar.advance(self.task, n)

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.stop()
