"""One take of a ``capture batch``: its settings key, whether it is already done, and running it.

This module knows nothing of Ray: :func:`process_take` is what a Ray task calls on a worker (and what
a test can call directly). It first checks that this machine can read the take's inputs and write
its output folder (:func:`check_storage`), then runs :func:`capture.run.take.run_take` (the stages,
caches and report of ``capture run``) with the worker's threads pinned (:func:`pin_threads`), appends
what happened to the take's log ``OUT/batch_take.log`` and returns a plain-data result (with the
machine, Ray node and niceness it ran on); it never raises for a bad take.

A take is *done* when its run folder's ``batch_take.json`` (written by the batch driver) says so for
the same key and ``run.json`` / ``report.json`` agree. The key hashes the take's settings and
fingerprints of its inputs' contents (the video, the camera and detector files, the actor's weights
and landmark embeddings; not their paths), so a changed setting or input runs the take again (whose
stages then redo only what the change affects).
"""

from __future__ import annotations

import contextlib
import os
import platform
import socket
import time
import traceback
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable

from capture.io.atomic import write_json
from capture.io.errors import CaptureError, Interrupted
from capture.run.inputs import RunConfig
from capture.run.store import RUN_JSON, digest, file_sha256, read_json

TAKE_JSON = "batch_take.json"
TAKE_LOG = "batch_take.log"
TAKE_FORMAT = "capture-batch-take"
#: Settings of a take left out of its key: those that do not change its outputs, and the input paths
#: (their contents are fingerprinted instead, so a moved or copied shoot folder is still done).
_NOT_KEYED = ("out", "overwrite", "progress", "threads", "video", "camera", "detector", "actor")


def _sha(path: Path | None) -> str | None:
    """The file's sha256; None for no file; a marker naming a file that cannot be read (never "done")."""
    try:
        return None if path is None else file_sha256(path)
    except OSError:
        return f"unreadable: {path}"


def take_key(cfg: RunConfig, segments: list | None = None) -> str:
    """sha256 over the take's output-relevant settings, its segments (when split) and its input
    fingerprints (cheap: the video's identity reads 2 MiB; the other inputs are small files or the
    actor's weights)."""
    from capture.actor.package import WEIGHTS, resolve_actor
    from capture.run.inputs import default_detector
    from capture.io.video import video_identity

    settings = {k: v for k, v in cfg.to_dict().items() if k not in _NOT_KEYED}
    try:
        video = video_identity(cfg.video)
    except OSError:
        video = f"unreadable: {cfg.video}"
    try:
        det = Path(cfg.detector) if cfg.detector is not None else default_detector(Path(cfg.video))
    except CaptureError:
        det = None
    actor = resolve_actor(str(cfg.actor))
    fingerprints = {
        "video": video, "camera": _sha(cfg.camera), "actor_weights": _sha(actor / WEIGHTS),
        "detector_onnx": _sha(det), "detector_spec": _sha(None if det is None else det.with_suffix(".json")),
        "embeddings": {p.name: _sha(p) for p in sorted((actor / "landmarks").glob("*.json"))},
    }
    key = {"settings": settings, "fingerprints": fingerprints}
    if segments:
        key["segments"] = [list(map(int, se)) for se in segments]
    return digest(key)


def done_result(cfg: RunConfig, key: str) -> dict | None:
    """The stored result of a take that is done with ``key`` (None: it must run)."""
    out = Path(cfg.out)
    state = read_json(out / TAKE_JSON)
    run = read_json(out / RUN_JSON)
    if (state is None or state.get("format") != TAKE_FORMAT or state.get("key") != key
            or state.get("status") != "done" or run is None or run.get("status") != "done"
            or not (out / "report.json").is_file()):
        return None
    return state.get("result")


def write_take_state(cfg: RunConfig, name: str, key: str, status: str, result: dict, attempts: list[dict],
                     shoot: Path) -> Path:
    """``OUT/batch_take.json``: the take's key, final status, result row and attempts (written by the driver)."""
    return write_json(Path(cfg.out) / TAKE_JSON, {
        "format": TAKE_FORMAT, "version": 1, "take": name, "shoot": str(shoot), "key": key, "status": status,
        "result": result, "attempts": attempts})


def result_from_report(report: dict) -> dict:
    """The summary-table fields of a ``capture run`` report."""
    from capture.run.report import unexplained_frames

    fr, err = report["frames"], report["error"]
    return {"frames_requested": fr["requested"], "frames_fitted": fr["fitted"], "frames_skipped": fr["skipped"],
            "reprojection_mean_px": err.get("mean"), "reprojection_median_px": err.get("median"),
            "reprojection_max_px": err.get("max"), "worst_frame": err.get("worst_frame"),
            "frames_unexplained": unexplained_frames(report.get("unexplained")),
            "camera_is_default": bool(report.get("camera", {}).get("is_default")),
            "stages": {s["stage"]: s["status"] for s in report.get("stages", [])}}


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


class _Throttle:
    """Forward ``(label, n)`` progress to ``sink(frames)`` for the fit stage, at most every ``period`` s."""

    def __init__(self, sink: Callable[[int], None] | None, period: float = 0.5):
        self.sink, self.period, self.pending, self.last = sink, period, 0, time.monotonic()

    def __call__(self, label: str, n: int) -> None:
        if self.sink is None or label != "fit":
            return
        self.pending += n
        if time.monotonic() - self.last >= self.period:
            self.flush()

    def flush(self) -> None:
        if self.sink is not None and self.pending:
            self.sink(self.pending)
            self.pending = 0
        self.last = time.monotonic()


def process_take(cfg: RunConfig, name: str, attempt: int, threads: int,
                 on_frames: Callable[[int], None] | None = None) -> dict:
    """Run one take like ``capture run``; returns ``{"status": "done" | "failed" | "interrupted", ...}``.

    See :func:`guarded` for threads, logging and failures; the result carries the summary fields of
    the take's report (:func:`result_from_report`).
    """
    from capture.run.take import run_take

    return guarded(cfg, name, attempt, threads, lambda c: result_from_report(run_take(c)), on_frames)


def node_name() -> str:
    """This process's machine and Ray node (the first 8 hex digits of its id) for logs and errors."""
    host = socket.gethostname()
    try:
        import ray

        if ray.is_initialized():
            return f"{host} (Ray node {ray.get_runtime_context().get_node_id()[:8]})"
    except Exception:  # noqa: BLE001, S110 - only a label
        pass
    return host


def check_storage(cfg: RunConfig) -> str | None:
    """None when this machine can read the take's inputs and write its output folder, else what it cannot
    (the path and the reason), checked before any work: on a cluster every node must see the shoot's
    files at the same paths (a shared file system).

    Reads the first byte of the video, the camera and detector files (when given) and the actor's
    ``actor.json``; creates the output folder and writes and removes a small file in it.
    """
    from capture.actor.package import ACTOR_JSON, actor_dir

    inputs = [("video", Path(cfg.video)), ("camera file", cfg.camera), ("detector", cfg.detector),
              ("actor", actor_dir(str(cfg.actor)) / ACTOR_JSON)]
    for what, path in inputs:
        if path is None:
            continue
        try:
            with open(path, "rb") as fh:
                fh.read(1)
        except OSError as exc:
            return f"cannot read the {what} {path} ({exc.strerror or exc})"
    out = Path(cfg.out)
    probe = out / f".capture_write_check.{socket.gethostname()}.{os.getpid()}"
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe.write_bytes(b"ok")
        probe.unlink()
    except OSError as exc:
        return f"cannot write the output folder {out} ({exc.strerror or exc})"
    return None


_PINNED: dict[str, int] = {}


def pin_threads(threads: int) -> None:
    """Pin this worker process's thread pools to ``threads`` (once per process and value): torch's
    intra-op threads (and one inter-op thread), OpenCV's and USD's (:func:`capture.io.threads.
    limit_native_pools`). The detector's onnxruntime session gets ``threads`` intra-op threads that do
    not spin (:func:`capture.detector.session.open_session`);
    OpenMP's idle policy is set in the worker's environment (:func:`capture.batch.cluster.worker_env`).
    """
    import torch

    from capture.io.threads import limit_native_pools

    if _PINNED.get("threads") == threads:
        return
    if "interop" not in _PINNED:
        with contextlib.suppress(RuntimeError):   # only before the first parallel work of the process
            torch.set_num_interop_threads(1)
        _PINNED["interop"] = 1
    torch.set_num_threads(int(threads))
    limit_native_pools(threads)
    _PINNED["threads"] = threads


def guarded(cfg: RunConfig, name: str, attempt: int, threads: int, work: Callable[[RunConfig], dict],
            on_frames: Callable[[int], None] | None = None, what: str = "take") -> dict:
    """``work(cfg)`` on a worker, with its threads pinned, logged to ``OUT/batch_take.log``; never raises.

    First :func:`check_storage`: a take whose inputs this node cannot read or whose output folder it
    cannot write fails at once (``retry: False``) with one line naming the path and the node.
    ``threads`` pins torch, OpenCV and the detector's onnxruntime (through ``cfg.threads``)
    (:func:`pin_threads`). ``on_frames(n)`` is called as the fit stage advances. Input problems
    (:class:`CaptureError`) come back as ``failed`` with ``retry: False`` (running again cannot help),
    anything else as ``failed`` with ``retry: True`` and the traceback in the log.
    """
    import dataclasses

    from capture.run.progress import progress_listener

    # a take is a task with a budget of `threads` CPUs: its fit and report stay in the take's process
    cfg = dataclasses.replace(cfg, threads=int(threads), progress=False, side_processes=False)
    out = Path(cfg.out)
    t0, c0 = time.perf_counter(), time.process_time()
    node = node_name()
    base = {"take": name, "attempt": attempt, "host": socket.gethostname(), "node": node, "pid": os.getpid(),
            "threads": threads, "niceness": os.nice(0), "started": _now()}
    problem = check_storage(cfg)
    if problem is not None:
        return {**base, "status": "failed", "retry": False, "seconds": time.perf_counter() - t0, "cpu_seconds": 0.0,
                "error": f"{problem} on node {node}; every Ray node must see the shoot's inputs and output "
                         f"folder at the same paths (shared storage)"}
    log_path = out / TAKE_LOG
    pin_threads(int(threads))
    throttle = _Throttle(on_frames)
    with open(log_path, "a", encoding="utf-8") as log:
        log.write(f"--- {base['started']} {what} {name} attempt {attempt} on {node} (pid {base['pid']}, "
                  f"{threads} thread(s), niceness {base['niceness']}, python {platform.python_version()})\n")
        log.write(f"settings: {cfg.to_dict()}\n")
        log.flush()
        try:
            with contextlib.redirect_stdout(log), contextlib.redirect_stderr(log), progress_listener(throttle):
                res = {**base, "status": "done", **work(cfg)}
        except Interrupted as exc:
            res = {**base, "status": "interrupted", "error": str(exc), "retry": False}
        except CaptureError as exc:
            res = {**base, "status": "failed", "error": str(exc), "retry": False}
        except KeyboardInterrupt:
            res = {**base, "status": "interrupted", "error": "interrupted; finished work is kept", "retry": False}
        except Exception as exc:  # a bug or a resource problem: keep the traceback, retry once
            log.write(traceback.format_exc())
            res = {**base, "status": "failed", "error": f"{type(exc).__name__}: {' '.join(str(exc).split())}",
                   "retry": True}
        finally:
            throttle.flush()
        res["seconds"] = time.perf_counter() - t0
        res["cpu_seconds"] = time.process_time() - c0   # this worker process's CPU time (all its threads)
        log.write(f"{_now()} {what} {name} {res['status']} in {res['seconds']:.1f} s"
                  + (f": {res['error']}" if res.get("error") else "") + "\n")
    return res
