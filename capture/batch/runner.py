"""``capture batch SHOOT.toml``: every take of a shoot through ``capture run``, in parallel on Ray.

Each take (see :mod:`capture.batch.shoot` for the file) runs the stages of ``capture run`` into its own run
folder (``<out>/<take name>``, the same layout and caches as ``capture run --out``), as one Ray task
(:mod:`capture.batch.cluster`): on an embedded local Ray by default, on an existing cluster with
``--address``. Takes already done with the same settings and inputs are not run again
(:mod:`capture.batch.take`); a take that fails unexpectedly is retried once; a bad take never stops
the others. The batch writes ``batch_report.json`` and ``batch_summary.csv`` next to the run folders
(:mod:`capture.batch.report`), each take's log is ``<run folder>/batch_take.log``.

Exit status: 0 when every take is done (now or before), 1 when any take failed, 2 for a bad shoot
file or option, 130 when interrupted (running takes keep their finished work; the same command
resumes them).
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass
from datetime import datetime, timezone
from pathlib import Path


from capture.batch.report import print_summary_table, take_row, totals, write_batch_report
from capture.batch.take import done_result, take_key, write_take_state
from capture.io.errors import CaptureError, Interrupted
from capture.batch.shoot import Shoot, Take, load_shoot
from capture.io.signals import sigterm_as_interrupt

BATCH_FORMAT = "capture-batch-report"


@dataclass
class BatchConfig:
    """Settings of ``capture batch`` (saved in ``batch_report.json``)."""

    shoot: Path
    out: Path | None = None            # None: the shoot file's [shoot] out, else runs/<shoot name> beside it
    workers: int | None = None         # tasks in flight; None: this machine's (or the cluster's) cores / threads
    threads: int = 1                   # CPUs (and torch threads) per take
    address: str | None = None         # None: embedded local Ray
    segment_frames: int | None = None  # None: the shoot file's [shoot] segment_frames (default 0: off)
    dry_run: bool = False
    progress: bool = True

    def to_dict(self) -> dict:
        d = asdict(self)
        d["shoot"], d["out"] = str(self.shoot), None if self.out is None else str(self.out)
        return d


@dataclass
class PlannedTake:
    take: Take
    key: str
    frames: int                        # frames to process (0 when the video cannot be read)
    segments: list[tuple[int, int]]    # more than one: split into segments (capture.batch.segments)
    done: dict | None                  # the stored result when already done with this key


def frame_range(take: Take) -> tuple[int, int]:
    """The take's frames ``[start, end)`` from the video header and its range ((0, 0) if unreadable)."""
    from capture.run.inputs import parse_frame_range
    from capture.io.video import open_video

    try:
        with open_video(take.config.video) as reader:
            n = reader.info.frame_count
        return parse_frame_range(take.config.frames, n)
    except Exception:  # reported by the take itself when it runs
        return 0, 0


def plan(shoot: Shoot, segment_frames: int = 0) -> list[PlannedTake]:
    """What each take will do: its key, frames, segments and whether it is done already."""
    from capture.batch.segments import plan_segments

    out = []
    for t in shoot.takes:
        start, end = frame_range(t)
        segments = [(start, end)]
        if segment_frames and end > start:
            if segment_frames <= 2 * t.config.window:
                raise CaptureError(f"segment_frames {segment_frames} must be more than twice the fitting window "
                                   f"({t.config.window} frames, take {t.name}); segments overlap by a window")
            segments = plan_segments(start, end, segment_frames, t.config.window)
        key = take_key(t.config, segments if len(segments) > 1 else None)
        out.append(PlannedTake(t, key, end - start, segments, done_result(t.config, key)))
    return out


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def _rel(path: Path, base: Path) -> str:
    try:
        return str(Path(path).relative_to(base))
    except ValueError:
        return str(path)


def _problems(p: PlannedTake) -> list[str]:
    """What will make a take fail that a dry run can see without loading anything."""
    c = p.take.config
    out = [] if p.frames else ["video unreadable or missing"]
    if not (Path(c.actor) / "actor.json").is_file():
        out.append(f"no actor at {c.actor}")
    out += [f"{what} {f} missing" for what, f in (("camera", c.camera), ("detector", c.detector))
            if f is not None and not Path(f).is_file()]
    return out


def print_plan(shoot: Shoot, planned: list[PlannedTake], console) -> None:
    from rich.table import Table

    t = Table(title=f"capture batch --dry-run: {shoot.name} ({shoot.path})", title_justify="left")
    for col in ("take", "video", "frames", "actor", "would"):
        t.add_column(col, justify="right" if col == "frames" else "left", overflow="fold")
    for p in planned:
        c = p.take.config
        would = "skip (done, same settings)" if p.done else "run"
        if not p.done and len(p.segments) > 1:
            would += f" in {len(p.segments)} segments " + ", ".join(f"{s}:{e}" for s, e in p.segments)
        problems = [] if p.done else _problems(p)
        if problems:
            would += f" (will fail: {'; '.join(problems)})"
        t.add_row(p.take.name, _rel(c.video, shoot.path.parent), str(p.frames), Path(c.actor).name, would)
    console.print(t)
    n_run = sum(p.done is None for p in planned)
    console.print(f"{n_run} of {len(planned)} takes would run ({sum(p.frames for p in planned if not p.done)} frames); "
                  f"output in {shoot.out}/<take>")


class ShootProgress:
    """Progress over the whole shoot: takes done, frames fitted, frames per second, time left (rich)."""

    def __init__(self, planned: list[PlannedTake], enabled: bool, console):
        self.expected = {p.take.name: p.frames for p in planned}
        self.counted: dict[str, int] = {n: 0 for n in self.expected}
        self.total, self.n_takes, self.finished, self.failed = sum(self.expected.values()), len(planned), 0, 0
        self.console, self.bar = console, None
        if enabled and planned:
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress, ProgressColumn, TextColumn,
                                       TimeElapsedColumn)
            from rich.text import Text

            class Overall(ProgressColumn):
                """Frames per second over the whole shoot so far, and the time left at that rate."""

                def render(self, task):
                    fps = task.completed / task.elapsed if task.elapsed and task.completed else None
                    if fps is None:
                        return Text("- frames/s, time left -")
                    m, s = divmod(int((task.total - task.completed) / fps), 60)
                    h, m = divmod(m, 60)
                    return Text(f"{fps:.2f} frames/s, {h}:{m:02d}:{s:02d} left")

            self.bar = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                TextColumn("frames"), TimeElapsedColumn(), Overall(), console=console)

    def __enter__(self) -> "ShootProgress":
        if self.bar is not None:
            self.bar.start()
            self.task = self.bar.add_task(self._label(), total=max(1, self.total))
        return self

    def _label(self) -> str:
        return f"takes {self.finished}/{self.n_takes}" + (f" ({self.failed} failed)" if self.failed else "")

    def _update(self) -> None:
        if self.bar is not None:
            self.bar.update(self.task, completed=sum(self.counted.values()), total=max(1, self.total),
                            description=self._label())

    def frames(self, snapshot: dict[str, int]) -> None:
        for name, n in snapshot.items():
            if name in self.counted:
                self.counted[name] = max(self.counted[name], min(n, self.expected[name]))
        self._update()

    def take_finished(self, name: str, ok: bool, line: str) -> None:
        self.finished += 1
        if ok:
            self.counted[name] = self.expected[name]
        else:
            self.failed += 1
            self.total -= self.expected[name] - self.counted[name]
            self.expected[name] = self.counted[name]
        (self.bar.console if self.bar is not None else self.console).print(line, highlight=False)
        self._update()

    def __exit__(self, *exc) -> None:
        if self.bar is not None:
            self.bar.stop()


def run_batch(cfg: BatchConfig, console=None) -> dict:
    """Run the shoot; returns the batch report (also written to ``<out>/batch_report.json``).

    With ``dry_run`` nothing runs and nothing is written: the plan is printed and returned.
    """
    from rich.console import Console

    from capture.batch import cluster
    from capture.run.report import versions

    console = console or Console()
    if cfg.threads < 1:
        raise CaptureError(f"--threads must be at least 1, got {cfg.threads}")
    if cfg.workers is not None and cfg.workers < 1:
        raise CaptureError(f"--workers must be at least 1, got {cfg.workers}")
    shoot = load_shoot(cfg.shoot, cfg.out)
    if cfg.segment_frames is not None and cfg.segment_frames < 0:
        raise CaptureError(f"--segment-frames must be 0 (off) or a number of frames, got {cfg.segment_frames}")
    segment_frames = shoot.segment_frames if cfg.segment_frames is None else cfg.segment_frames
    planned = plan(shoot, segment_frames)
    if cfg.dry_run:
        print_plan(shoot, planned, console)
        return {"format": BATCH_FORMAT, "dry_run": True, "shoot": str(shoot.path), "out": str(shoot.out),
                "takes": [{"take": p.take.name, "would": "skip" if p.done else "run", "frames": p.frames,
                           "segments": [list(se) for se in p.segments], "out": str(p.take.config.out)}
                          for p in planned]}

    t_start = time.perf_counter()
    shoot.out.mkdir(parents=True, exist_ok=True)
    rows = {p.take.name: take_row(p.take.name, p.take.config.out, p.done, "already done" if p.done else "pending")
            for p in planned}
    to_run = [p for p in planned if p.done is None]
    by_name = {p.take.name: p for p in to_run}
    report = {"format": BATCH_FORMAT, "version": 1, "command": "capture batch", "shoot": str(shoot.path),
              "name": shoot.name, "out": str(shoot.out), "settings": cfg.to_dict(), "started": _now(),
              "finished": None, "ray": None, "versions": versions(), "totals": None, "takes": [],
              "take_settings": {p.take.name: p.take.settings for p in planned}}

    def save() -> None:
        report["takes"] = list(rows.values())
        report["totals"] = totals(report["takes"], time.perf_counter() - t_start)
        write_batch_report(shoot.out, report)

    save()
    if to_run:
        jobs = [cluster.Job(p.take.name, (p.take.config, p.take.name), p.segments if len(p.segments) > 1 else [])
                for p in to_run]
        workers = cfg.workers
        if workers is None and cfg.address is None:
            workers = max(1, (os.cpu_count() or 1) // cfg.threads)
        # The embedded Ray gets as many CPUs as the tasks can use at once (segments count one each).
        info = cluster.connect(cfg.address, min(workers or 1, sum(j.weight for j in jobs)), cfg.threads)
        if workers is None:   # a cluster without --workers: as many tasks as its CPUs hold
            workers = max(1, int(info.cpus // cfg.threads))
        report["ray"] = {**asdict(info), "workers": workers, "threads_per_take": cfg.threads}
        console.print(f"capture batch: {len(to_run)} of {len(planned)} takes to run "
                      f"({sum(p.frames for p in to_run)} frames) on {info.mode} Ray ({info.nodes} node(s), "
                      f"{info.cpus:g} CPUs), {workers} at a time x {cfg.threads} thread(s); output in {shoot.out}",
                      highlight=False)

        with ShootProgress(to_run, cfg.progress, console) as prog:
            def on_result(job: cluster.Job, res: dict) -> None:
                p = by_name[job.name]
                status = res["status"]
                row = take_row(job.name, p.take.config.out, res, status, len(job.attempts))
                rows[job.name] = row
                try:
                    write_take_state(p.take.config, job.name, p.key, status, res, job.attempts, shoot.path)
                except OSError:
                    pass  # the run folder may be unwritable: the batch report still has the row
                save()
                err = f" {row['reprojection_mean_px']:.2f} px" if row["reprojection_mean_px"] is not None else ""
                what = (f"{row['frames_fitted']}/{row['frames_requested']} frames{err}" if status == "done"
                        else row.get("error") or "")
                prog.take_finished(job.name, status == "done",
                                   f"[{prog.finished + 1}/{len(to_run)}] {job.name}: {status} {what} "
                                   f"({row['seconds'] or 0:.1f} s, attempt {len(job.attempts)})")

            try:
                with sigterm_as_interrupt():
                    cluster.run_tasks(jobs, workers, cfg.threads, on_result, prog.frames)
            except KeyboardInterrupt:
                report["finished"] = _now()
                save()
                raise Interrupted(f"batch interrupted; finished takes and work are kept in {shoot.out}: run the "
                                  f"same command to resume") from None
            finally:
                cluster.disconnect(info)
    report["finished"] = _now()
    save()
    print_summary_table(report, console)
    return report
