"""The Ray side of ``capture batch``: start or join Ray, run takes as tasks, retry once, count frames.

* :func:`connect` starts an **embedded** local Ray sized to ``workers x threads`` CPUs of this
  machine (always a new one, even when ``ray start`` runs here), or joins an existing cluster with
  ``address`` (``ray start --head`` on one machine, ``ray start --address ...`` on the others;
  ``auto``: ``RAY_ADDRESS`` or the cluster ``ray start`` started here). Joining finds the token of
  a token-authenticated cluster as Ray's CLI does (:func:`find_token`) and probes the cluster first
  (:func:`probe_cluster`): a failure is one line naming the address, the token or version skew, and
  Ray's own messages go to a log file. When the calling process already has Ray initialised (a
  script or a test), that Ray is used as it is.
* The workers run with :func:`worker_env` (a job-wide ``runtime_env``): at this process's niceness
  rather than Ray's 15, and with thread pools of ``threads`` threads that do not spin.
* Every take is one task asking for ``threads`` CPUs; the task checks the take's storage and pins its
  threads (:func:`capture.batch.take.guarded`). A take split into segments
  (:mod:`capture.batch.segments`) is one task per segment plus a merge task that Ray starts when
  they are done. At most ``workers`` tasks are in flight.
* Ray's own task retries are off (``max_retries=0``): a take whose task failed with an unexpected
  error, or whose worker process or node died, is submitted once more by :func:`run_tasks` (Ray places
  it on a node that is alive; it resumes from what its run folder kept); a take that failed on its
  input (:class:`~capture.io.errors.CaptureError`, or a path its node cannot reach) is not (the message
  says what to fix).
* Fitted frames flow from the tasks to a tiny counter actor (0 CPUs, on the driver's node) that the
  driver polls for the shoot-wide progress.

On a cluster every machine needs this package installed and must see the shoot's paths (videos,
actors, cameras, the output folder) at the same place: a shared file system.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sys
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
    address: str | None          # as given (--address); the GCS address joined is ``gcs``
    nodes: int
    cpus: float
    started: bool                # this command started or joined Ray (and shuts it down / leaves)
    gcs: str | None = None
    auth: str | None = None      # "token" when this driver authenticates with a token


def worker_env(threads: int) -> dict[str, str]:
    """Environment of the Ray workers that run takes (a job-wide ``runtime_env``).

    * ``RAY_worker_niceness``: Ray starts its workers at niceness 15, so any ordinary (niceness 0) job
      the kernel schedules with them (the same session's autogroup, or all jobs where autogroups are
      off) takes the CPU from them (a niceness-15 thread weighs 36 against 1024). The workers run at
      this driver's own niceness instead (``nice capture batch ...`` still makes them yield), or at
      ``RAY_worker_niceness`` when the driver's environment sets it (15: Ray's default).
    * OpenMP, MKL and OpenBLAS pools of ``threads`` threads that sleep rather than spin when idle.
    """
    n = str(max(1, int(threads)))
    nice = os.environ.get("RAY_worker_niceness") or str(os.nice(0))
    return {"RAY_worker_niceness": nice, "OMP_NUM_THREADS": n, "MKL_NUM_THREADS": n,
            "OPENBLAS_NUM_THREADS": n, "OMP_WAIT_POLICY": "PASSIVE", "KMP_BLOCKTIME": "0"}


@contextlib.contextmanager
def _quiet_stderr(path: Path):
    """Send what Ray's C++ core writes to stderr (fd 2) while joining to ``path`` (the log flood of a
    failed join: one warning per retry)."""
    sys.stderr.flush()
    saved = os.dup(2)
    with open(path, "ab") as fh:
        os.dup2(fh.fileno(), 2)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, 2)
            os.close(saved)


def find_token() -> str | None:
    """Turn on token authentication as Ray's CLI does (``ray start``, ``ray.init(address="auto")``):
    when ``RAY_AUTH_MODE`` is not set and a token exists (``RAY_AUTH_TOKEN``, the file named by
    ``RAY_AUTH_TOKEN_PATH``, or ``~/.ray/auth_token``). Returns where the token comes from, or None.

    ``ray.init`` with an explicit address does not do this (Ray >= 2.52 turns token authentication on
    by default in ``ray start --head`` when a token exists), so a driver without ``RAY_AUTH_MODE=token``
    in its environment could not join such a cluster.
    """
    mode = os.environ.get("RAY_AUTH_MODE")
    if mode is not None and mode.lower() != "token":
        return None
    if os.environ.get("RAY_AUTH_TOKEN"):
        source = "RAY_AUTH_TOKEN"
    elif os.environ.get("RAY_AUTH_TOKEN_PATH"):
        source = os.environ["RAY_AUTH_TOKEN_PATH"]
    elif (Path.home() / ".ray" / "auth_token").is_file():
        source = str(Path.home() / ".ray" / "auth_token")
    else:
        return None
    if mode is None:
        try:   # Ray's own switch (sets RAY_AUTH_MODE=token and refreshes its config), quietly
            from ray._private.authentication.authentication_token_setup import (
                maybe_enable_token_auth_if_token_available,
            )

            logging.getLogger("ray._private.authentication.authentication_token_setup").setLevel(logging.ERROR)
            if not maybe_enable_token_auth_if_token_available(warn_if_disabled=False):
                return None
        except ImportError:  # pragma: no cover - a Ray before token authentication
            return None
    return source


def _join_error(address: str, gcs: str | None, why: str, check: str) -> CaptureError:
    where = f"--address {address}" + (f" ({gcs})" if gcs and gcs != address else "")
    return CaptureError(f"cannot join the Ray cluster at {where}: {why}; {check}")


_TOKEN_HELP = ("check the token: put the cluster's token (`ray get-auth-token` on the head node prints it) in "
               "~/.ray/auth_token, or name its file in RAY_AUTH_TOKEN_PATH, or set RAY_AUTH_TOKEN")


def probe_cluster(address: str, token: str | None, log: Path) -> str:
    """Check that a Ray cluster answers at ``address`` and accepts this driver, before ``ray.init``;
    returns the GCS address (host:port). Raises a one-line :class:`CaptureError` naming what to check:
    the address (nothing answers), the token (refused or missing), or the versions (driver and
    cluster run different Ray or Python releases)."""
    import socket

    import ray
    from ray._private import services

    try:
        gcs = services.canonicalize_bootstrap_address(address)
    except (ValueError, ConnectionError) as exc:
        raise _join_error(address, None, " ".join(str(exc).split()), "check the address (host:port of the "
                          "head node, as `ray start --head` prints it)") from None
    if gcs is None:
        raise _join_error(address, None, "no running Ray cluster found on this machine (RAY_ADDRESS is not set)",
                          "start one with `ray start --head`, or give the head node's host:port")
    host, _, port = gcs.rpartition(":")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=5).close()
    except (OSError, ValueError) as exc:
        raise _join_error(address, gcs, f"nothing answers there ({exc.strerror or exc})",
                          "check the address (the head node's host:port, as `ray start --head` prints it; "
                          "`ray status` on the head shows it) and that the head node runs") from None
    from ray._raylet import GcsClient

    try:
        with _quiet_stderr(log):
            client = GcsClient(address=gcs)
            meta = json.loads(client.internal_kv_get(b"CLUSTER_METADATA", namespace=b"cluster", timeout=10) or b"{}")
    except ray.exceptions.AuthenticationError:
        why = ("the cluster refused this driver's token" + (f" (from {token})" if token else "") if token
               else "the cluster requires a token and none was found")
        raise _join_error(address, gcs, why, _TOKEN_HELP) from None
    except Exception as exc:  # noqa: BLE001 - RpcError, timeouts: not a Ray head, or one too busy to answer
        msg = " ".join(str(exc).split())[:200]
        raise _join_error(address, gcs, f"no answer from Ray's GCS ({msg})",
                          "check that the address is the head node's Ray port (default 6379) and that "
                          "driver and cluster run the same Ray version") from None
    ours = (ray.__version__, ".".join(map(str, sys.version_info[:2])))
    theirs = (meta.get("ray_version"), ".".join(str(meta.get("python_version", "")).split(".")[:2]))
    if meta and ours != theirs:
        raise _join_error(address, gcs, f"version skew: the cluster runs Ray {theirs[0]} on Python {theirs[1]}, "
                          f"this driver Ray {ours[0]} on Python {ours[1]}",
                          "install the cluster's Ray and Python versions here (or start the cluster with ours)")
    return gcs


def connect(address: str | None, workers: int, threads: int) -> RayInfo:
    """Start the embedded local Ray (``address`` None) or join the cluster at ``address``.

    ``address`` is a head node's ``host:port`` or ``auto`` (``RAY_ADDRESS``, else the cluster that
    ``ray start`` started on this machine). The token of a token-authenticated cluster is found as
    Ray's CLI finds it (:func:`find_token`); the cluster is probed first (:func:`probe_cluster`) so a
    failure to join is one line naming what to check, and Ray's messages go to a log file.
    """
    try:
        import ray
    except ImportError:  # pragma: no cover - a dependency
        raise CaptureError("capture batch needs Ray: pip install 'ray>=2.40,<3'") from None
    env = worker_env(threads)
    gcs = token = None
    if ray.is_initialized():
        mode, started = "existing", False
    elif address:
        import tempfile

        log = Path(tempfile.gettempdir()) / f"capture_batch_ray_join_{os.getpid()}.log"
        logging.getLogger("ray").setLevel(logging.ERROR)   # as ray.init(logging_level=ERROR) will: no warnings
        token = find_token()
        # A Ray Client address (ray://) goes to ray.init as it is: its server is not a GCS to probe.
        try:
            gcs = address if address.startswith("ray://") else probe_cluster(address, token, log)
        except CaptureError:
            log.unlink(missing_ok=True)   # the one line says what to check
            raise
        try:
            with _quiet_stderr(log):
                ray.init(address=gcs, log_to_driver=False, logging_level=logging.ERROR,
                         runtime_env={"env_vars": env})
        except Exception as exc:  # noqa: BLE001 - ConnectionError, RuntimeError (versions), auth ...
            msg = " ".join(str(exc).split())[:300]
            check = _TOKEN_HELP if "auth" in msg.lower() or "token" in msg.lower() else (
                "check the address, the token and that driver and cluster run the same Ray and Python versions")
            raise _join_error(address, gcs, f"{msg} (Ray's messages: {log})", check) from None
        log.unlink(missing_ok=True)
        mode, started = "cluster", True
    else:
        root = str(Path(__file__).resolve().parents[2])   # workers import capture even without an install
        path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
        # address="local": a new Ray even when RAY_ADDRESS is set or `ray start` runs on this machine.
        ray.init(address="local", num_cpus=workers * threads, include_dashboard=False, log_to_driver=False,
                 logging_level=logging.ERROR, runtime_env={"env_vars": {**env, "PYTHONPATH": path}})
        mode, started = "embedded", True
    res = ray.cluster_resources()
    nodes = sum(1 for n in ray.nodes() if n.get("Alive"))
    auth = "token" if os.environ.get("RAY_AUTH_MODE", "").lower() == "token" else None
    return RayInfo(mode, address, nodes, float(res.get("CPU", 0.0)), started, gcs, auth)


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
    # The counter lives on the driver's node: a worker node that dies must not take the progress with it.
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    here = NodeAffinitySchedulingStrategy(ray.get_runtime_context().get_node_id(), soft=True)
    counter = remote["counter"].options(scheduling_strategy=here).remote()
    frames: dict[str, int] = {}

    def report_frames() -> None:
        try:
            frames.update(ray.get(counter.snapshot.remote(), timeout=10))
        except ray.exceptions.RayError:
            pass  # the progress only: keep the last counts
        on_frames(dict(frames))
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
                report_frames()
                last = time.monotonic()
        if on_frames is not None:
            report_frames()
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
        with contextlib.suppress(Exception):
            ray.kill(counter)
