"""The Ray side of ``capture batch``: start or join Ray, run takes as tasks, retry once, count frames.

* :func:`connect` starts an **embedded** local Ray sized to ``workers x threads`` CPUs of this
  machine, or joins an existing cluster with ``address`` (``ray start --head`` on one machine,
  ``ray start --address ...`` on the others). When the calling process already has Ray initialised
  (a script or a test), that Ray is used as it is.
* Every take is one task asking for ``threads`` CPUs; the task pins torch to as many threads
  (:func:`capture.batch.take.process_take`). A take split into segments
  (:mod:`capture.batch.segments`) is one task per segment plus a merge task that Ray starts when
  they are done. At most ``workers`` tasks are in flight.
* Ray's own task retries are off (``max_retries=0``): a take whose task failed with an unexpected
  error, or whose worker process died, is submitted once more by :func:`run_tasks`; a take that failed
  on its input (:class:`~capture.io.errors.CaptureError`) is not (the message says what to fix).
* Fitted frames flow from the tasks to a tiny counter actor (0 CPUs) that the driver polls for the
  shoot-wide progress.

On a cluster every machine needs this package installed and must see the shoot's paths (videos,
actors, cameras, the output folder) at the same place: a shared file system.
"""

from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

from capture.io.errors import CaptureError

RETRIES = 1   # extra attempts of a take that failed with an unexpected error or a dead worker


@dataclass
class RayInfo:
    """How this batch runs on Ray (goes into the batch report)."""

    mode: str                    # "embedded" | "cluster" | "existing"
    address: str | None
    nodes: int
    cpus: float
    started: bool                # this command started Ray (and shuts it down)


def connect(address: str | None, workers: int, threads: int) -> RayInfo:
    """Start the embedded local Ray (``address`` None) or join the cluster at ``address``."""
    try:
        import ray
    except ImportError:  # pragma: no cover - a dependency
        raise CaptureError("capture batch needs Ray: pip install 'ray>=2.40,<3'") from None
    if ray.is_initialized():
        mode, started = "existing", False
    elif address:
        try:
            ray.init(address=address, log_to_driver=False, logging_level=logging.WARNING)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            raise CaptureError(f"cannot join the Ray cluster at --address {address}: {' '.join(str(exc).split())}; "
                               f"check that 'ray start --head' runs there") from None
        mode, started = "cluster", True
    else:
        root = str(Path(__file__).resolve().parents[2])   # workers import capture even without an install
        path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
        ray.init(num_cpus=workers * threads, include_dashboard=False, log_to_driver=False,
                 logging_level=logging.ERROR, runtime_env={"env_vars": {"PYTHONPATH": path}})
        mode, started = "embedded", True
    res = ray.cluster_resources()
    nodes = sum(1 for n in ray.nodes() if n.get("Alive"))
    return RayInfo(mode, address, nodes, float(res.get("CPU", 0.0)), started)


def disconnect(info: RayInfo) -> None:
    import ray

    if info.started and ray.is_initialized():
        ray.shutdown()


_REMOTE: dict[str, Any] = {}


def _remotes():
    """The remote take function and the counter actor class (defined once, after Ray is imported)."""
    if not _REMOTE:
        import ray

        @ray.remote(max_retries=0)
        def take_task(cfg, name: str, attempt: int, threads: int, counter):
            from capture.batch.take import process_take

            sink = None if counter is None else (lambda n: counter.add.remote(name, n))
            return process_take(cfg, name, attempt, threads, sink)

        @ray.remote(max_retries=0)
        def segment_task(cfg, name: str, start: int, end: int, attempt: int, threads: int, counter):
            from capture.batch.segments import fit_segment
            from capture.batch.take import guarded

            sink = None if counter is None else (lambda n: counter.add.remote(name, n))
            res = guarded(cfg, name, attempt, threads, lambda c: fit_segment(c, start, end), sink,
                          what=f"segment {start}:{end} of take")
            res["segment"] = [start, end]
            return res

        @ray.remote(max_retries=0)
        def merge_task(cfg, name: str, segments: list, attempt: int, threads: int, *segment_results):
            from capture.batch.segments import merge_segments
            from capture.batch.take import guarded, result_from_report

            bad = [r for r in segment_results if r.get("status") != "done"]
            if bad:   # the take fails like its first failed segment (and is retried if that one may be)
                r = bad[0]
                return {**r, "error": f"segment {r['segment'][0]}:{r['segment'][1]}: {r.get('error')}"}
            res = guarded(cfg, name, attempt, threads, lambda c: result_from_report(merge_segments(c, segments)),
                          what="merge of the segments of take")
            res["segments"] = [list(se) for se in segments]
            res["seconds_segments"] = [r.get("seconds") for r in segment_results]
            res["seconds"] += max(r.get("seconds") or 0.0 for r in segment_results)   # the critical path
            res["cpu_seconds"] += sum(r.get("cpu_seconds") or 0.0 for r in segment_results)
            return res

        @ray.remote(num_cpus=0)
        class FrameCounter:
            def __init__(self):
                self.frames: dict[str, int] = {}

            def add(self, name: str, n: int) -> None:
                self.frames[name] = self.frames.get(name, 0) + int(n)

            def snapshot(self) -> dict[str, int]:
                return dict(self.frames)

        _REMOTE.update(task=take_task, segment=segment_task, merge=merge_task, counter=FrameCounter)
    return _REMOTE


@dataclass
class Job:
    """One take to run: ``args`` of the take task (before attempt, threads, counter) and its attempts so far."""

    name: str
    args: tuple                  # (cfg, name) for the take task
    segments: list[tuple[int, int]] = field(default_factory=list)   # >1: one task per segment, then a merge
    attempts: list[dict] = field(default_factory=list)

    @property
    def weight(self) -> int:
        """Tasks this job runs side by side (its share of ``workers``)."""
        return max(1, len(self.segments))


def run_tasks(jobs: Sequence[Job], workers: int, threads: int, on_result: Callable[[Job, dict], None],
              on_frames: Callable[[dict[str, int]], None] | None = None, poll: float = 0.5,
              task: Any = None) -> None:
    """Run ``jobs`` with at most ``workers`` in flight; ``on_result(job, result)`` once per job, as each ends.

    A result with ``retry`` set (an unexpected error) or a task whose worker died is run once more
    (:data:`RETRIES`); every attempt's result is kept in ``job.attempts``. ``on_frames(frames per
    take)`` is called every ``poll`` seconds. ``task`` replaces the take task (tests). On
    KeyboardInterrupt the running tasks are cancelled (their finished work stays in their run
    folders), their results are collected for up to 60 s, then the interrupt is re-raised.
    """
    import ray

    remote = _remotes()
    task = task or remote["task"]
    counter = remote["counter"].remote()
    queue = [(job, 1) for job in jobs]
    queue.reverse()
    running: dict[Any, tuple[Job, int]] = {}
    helpers: dict[Any, list] = {}   # a segmented job's segment tasks (cancelled with it)

    def submit(job: Job, attempt: int) -> None:
        if len(job.segments) > 1:
            segs = [remote["segment"].options(num_cpus=threads).remote(*job.args, s, e, attempt, threads, counter)
                    for s, e in job.segments]
            ref = remote["merge"].options(num_cpus=threads).remote(*job.args, job.segments, attempt, threads, *segs)
            helpers[ref] = segs
        else:
            ref = task.options(num_cpus=threads).remote(*job.args, attempt, threads, counter)
        running[ref] = (job, attempt)

    def load() -> int:
        return sum(job.weight for job, _ in running.values())

    def collect(ref, job: Job, attempt: int) -> dict | None:
        try:
            res = ray.get(ref)
        except ray.exceptions.TaskCancelledError:
            res = {"take": job.name, "status": "interrupted", "error": "cancelled", "retry": False}
        except ray.exceptions.RayError as exc:  # the worker died (killed, out of memory) or Ray failed
            msg = " ".join(str(exc).split())
            res = {"take": job.name, "status": "failed", "error": f"worker failed: {msg[:300]}", "retry": True}
        res["attempt"] = attempt
        job.attempts.append(res)
        if res["status"] == "failed" and res.get("retry") and attempt <= RETRIES:
            return None
        on_result(job, res)
        return res

    last = 0.0
    try:
        while queue or running:
            while queue and (not running or load() + queue[-1][0].weight <= workers):
                submit(*queue.pop())
            ready, _ = ray.wait(list(running), num_returns=1, timeout=poll)
            for ref in ready:
                job, attempt = running.pop(ref)
                helpers.pop(ref, None)
                if collect(ref, job, attempt) is None:
                    queue.append((job, attempt + 1))   # next in line
            if on_frames is not None and time.monotonic() - last >= poll:
                on_frames(ray.get(counter.snapshot.remote()))
                last = time.monotonic()
        if on_frames is not None:
            on_frames(ray.get(counter.snapshot.remote()))
    except KeyboardInterrupt:
        for ref in running:
            for r in [ref, *helpers.get(ref, [])]:
                ray.cancel(r)
        deadline = time.monotonic() + 60
        while running and time.monotonic() < deadline:
            ready, _ = ray.wait(list(running), num_returns=len(running), timeout=1.0)
            for ref in ready:
                job, attempt = running.pop(ref)
                res = collect(ref, job, attempt)
                if res is None:   # would have been retried: report it failed as it stands
                    on_result(job, job.attempts[-1])
        for job, attempt in list(running.values()):
            on_result(job, {"take": job.name, "status": "interrupted", "error": "still running when interrupted",
                            "attempt": attempt})
        raise
    finally:
        ray.kill(counter)
