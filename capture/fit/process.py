"""The streamed take fit in a process of its own, so that it has a core to itself.

:func:`capture.fit.stream.fit_take_stream` is Python-heavy (many small torch ops per step); in a thread
of ``capture run``'s pipeline it ran 1.5x slower than alone (the GIL, and the run's fixed mmap threshold:
:mod:`capture.io.heap`). :class:`FitWorker` runs it in a child process instead, fed one row of
landmarks at a time through a pipe, with the same results (the child runs the same code on the same
numbers; its window cache is the same folder). The per-frame PnP of the head poses runs in the parent
(:meth:`FitWorker.feed`), beside decoding and detection: the same calls in the same order.

The child is forked, so it starts at once with the parent's loaded actor (nothing is pickled but the
rows, the fits, the PnP model and, at the end, the actor's rig). The parent's actor may not have built
its networks (:class:`capture.actor.package.Actor` makes them on first use): then the child imports
torch and builds them while the parent decodes and detects, and the parent never needs torch. Fork it
before the parent starts other threads (a lock held by another thread at the fork would stay held in
the child; OpenCV's pool is stopped around the fork, :func:`capture.io.threads.opencv_pool_stopped`). Off Linux
(no fork on Windows; macOS' system libraries are not fork-safe), with ``in_process=False``, or for a fit of more
than one thread in a process that loaded torch (:func:`torch_forbids_fork`), the same code runs in a thread,
through the same pipes.

A command can fork the fit process before its own start-up (:func:`prestart`, ``capture run``): it imports torch
and the fit (about 1 s) while the command loads its inputs on the other core, then waits for its take, which the
next worker sends it (the actor and the settings, pickled: about 4 MB, a few ms) instead of forking. That is
the one case where the actor is pickled; a take that does not pickle ends the prestarted process, and the worker
forks as above. On the 11 GRID clips (75 frames of 360x288) a whole run took 2.60 s instead of 2.82 by the means,
shorter in 20 of 22 pairs (``BENCHMARKS.md``, streaming pipeline, twentieth round).

Protocol::

    parent -> child   (a prestarted process only) ("take", the actor, the settings ...) or NO_TAKE first; then
                      (points (L, 2), weights (L,), face_found, PnP head pose or None) per frame, then
                      END (or ABORT)
    child -> parent   on the ready pipe, the PnP model points (the actor at the landmarks), then BUILT
                      once the networks are evaluated at every template vertex; on its own pipe,
                      ("fit", FrameFit, rows read so far) per frame (without vertices where it has a mesh_map:
                      the parent makes them from ("basis", the actor's features (K, V) float32), sent once
                      before the first such fit), ("read", rows read so far) when it
                      waits for rows, then ("end", timings, the actor's FaceRig, which the parent
                      adopts), ("error", exception) or ("aborted",)

Back-pressure: :meth:`FitWorker.feed` waits while more than its ``max_backlog`` rows were sent and not yet
read by the fit (as the fit last said), so that when the fit (or the export after it) is slower than
detection the rows do not pile up in the child's inbox for the rest of the take. It cannot stall the fit:
a fit that waits for rows says how many it has read first, over a long stretch without a face too (where
it reads rows without giving fits until a pose exists beyond its window).

Signals: the child ignores SIGINT and SIGTERM, which the parent handles (Ctrl-C reaches the whole process
group): the parent then sends ABORT and the child stops after the window it is solving (that window is
cached). If the parent dies, the child reads the end of its pipe and exits.
"""

from __future__ import annotations

import multiprocessing
import queue
import signal
import sys
import threading
import time
import traceback
from typing import Iterable, Iterator

from capture.io.threads import opencv_pool_stopped
from models.mesh_map import map_vertices

END = "end"
ABORT = "abort"
NO_TAKE = "no take"    # to a prestarted fit process that no worker took: exit
BUILT = "built"        # on the ready pipe after the PnP model: the actor's networks are evaluated
JOIN_S = 600.0         # how long :meth:`FitWorker.close` waits for the window being solved
TRIM_EVERY_FRAMES = 2400  # the fit process gives its free heap back this often (capture.io.heap.release_free_heap)


class FitStopped(Exception):
    """:meth:`FitWorker.results` was stopped from outside (its ``stop`` event)."""


class _Aborted(Exception):
    pass


def _child_main(rows_conn, out_conn, ready_conn, parent_ends, actor, template_points, camera, how, causal, threads,
                in_thread, nice=0) -> None:
    """The fit, reading rows from ``rows_conn`` and sending fits to ``out_conn``."""
    if nice:                           # before its reading thread starts, which inherits it (capture.io.priority)
        from capture.io.priority import background_thread

        background_thread(nice)
    if not in_thread:
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        for c in parent_ends:          # forked copies: the parent's ends must close only in the parent
            c.close()
        from capture.io.heap import COMPUTE, set_malloc_thresholds

        set_malloc_thresholds(*COMPUTE)   # not the run's: its 1 MiB mmap threshold slows the fit 1.4x
    from capture.io.heap import release_free_heap
    import torch

    from capture.fit.stream import fit_take_stream, pnp_model_points
    from capture.fit.take import query_template
    from models.fit_state import mesh_basis

    torch.set_num_threads(max(1, int(threads)))      # once, for this stage

    read = [0]
    inbox: queue.Queue = queue.Queue()

    def receive():
        """Drain the pipe as rows come, so that the parent never waits on a full pipe: it computes the next
        rows' PnP while this process solves a window."""
        while True:
            try:
                item = rows_conn.recv()
            except (EOFError, OSError):    # the parent is gone
                inbox.put(ABORT)
                return
            inbox.put(item)
            if isinstance(item, str):
                return

    threading.Thread(target=receive, name="capture-fit-rows", daemon=True).start()

    reported = [0]

    def rows():
        while True:
            if inbox.empty() and read[0] != reported[0]:   # about to wait for rows: say how many were read,
                out_conn.send(("read", read[0]))             # so that the parent's back-pressure lets more come
                reported[0] = read[0]
            item = inbox.get()
            if isinstance(item, str):
                if item == END:
                    return
                raise _Aborted
            read[0] += 1
            yield item

    timings: dict = {}
    try:
        # the PnP model first (the actor at the landmarks only): the parent poses the first rows while the
        # networks are evaluated at every template vertex (~0.6 s on one core), then says so (wait_ready)
        ready_conn.send(pnp_model_points(actor, template_points, how.device))
        if hasattr(actor, "at_template"):
            actor.at_template()
        ready_conn.send(BUILT)
        busy, t_last = 0.0, time.perf_counter()
        basis_sent = False
        for k, ff in enumerate(fit_take_stream(actor, rows(), template_points, camera, how, causal=causal,
                                               timings=timings, vertices=False)):
            now = time.perf_counter()
            busy += now - t_last
            if ff.mesh_map is not None and not basis_sent:
                # fits go without their vertices where they are a map of the actor's features (FrameFit.mesh_map):
                # the parent makes them from this basis (results), under 1 KB a frame on the pipe instead of 113 KB
                out_conn.send(("basis", mesh_basis(query_template(actor, how.device))))
                basis_sent = True
            out_conn.send(("fit", ff, read[0]))
            reported[0] = read[0]
            if not in_thread and k % TRIM_EVERY_FRAMES == TRIM_EVERY_FRAMES - 1:
                release_free_heap()      # flat in the take's length (capture.io.heap)
            t_last = time.perf_counter()
        busy += time.perf_counter() - t_last
        timings["busy_s"] = max(0.0, busy - timings.get("wait_s", 0.0))
        if not in_thread:
            import resource

            timings["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
        out_conn.send(("end", timings, actor.face_rig() if hasattr(actor, "face_rig") else None))
    except _Aborted:
        try:
            out_conn.send(("aborted",))
        except (OSError, ValueError):
            pass
    except BaseException as exc:  # handed to the parent, which raises it
        from capture.io.errors import CaptureError

        if not isinstance(exc, CaptureError) and hasattr(exc, "add_note"):   # where it failed, for the log
            exc.add_note(f"in the fit process:\n{traceback.format_exc()}")
        try:
            out_conn.send(("error", exc))
        except Exception:            # not picklable, or the parent is gone
            try:
                out_conn.send(("error", RuntimeError(f"the fit failed: {type(exc).__name__}: {exc}\n"
                                                     f"{traceback.format_exc()}")))
            except (OSError, ValueError):
                pass
    finally:
        if not in_thread:
            out_conn.close()
            ready_conn.close()


#: the fit process forked ahead by :func:`prestart` and not yet taken: (process, rows, out, ready) pipe ends
_PRESTARTED: list[tuple] = []
#: what a prestarted process imports while it waits: what :func:`_child_main` needs
PRESTART_IMPORTS = ("torch", "capture.fit.stream", "capture.fit.take", "models.fit_state")


def torch_forbids_fork(threads: int) -> bool:
    """Whether a forked fit of ``threads`` torch threads could hang: torch is loaded here, and so its OpenMP pool
    may have run with several threads (a script that trained an actor, then runs a take). A forked child of such
    a process that runs torch on more than one thread waits for ever in its first parallel region (GNU OpenMP is
    not fork-safe); on one thread it does not use the pool. ``capture`` commands never load torch outside the fit
    process, so this holds only for library callers, whose fit then runs in a thread (a prestarted process is then
    not taken: it forked from the same process)."""
    return int(threads) > 1 and "torch" in sys.modules


def prestart() -> bool:
    """Fork the fit process now, before the caller's own imports and threads (where :meth:`FitWorker.forks`): it
    imports torch and the fit while the caller starts, then waits for the next :class:`FitWorker` that forks, which
    takes it instead of forking. :func:`release_prestarted` ends it if none does. True when forked."""
    if _PRESTARTED or not FitWorker.forks(None):
        return False
    ctx = multiprocessing.get_context("fork")
    child_ends, parent_ends = _fit_pipes(ctx)
    proc = ctx.Process(target=_prestarted_main, args=(*child_ends, parent_ends), name="capture-fit", daemon=True)
    with opencv_pool_stopped():      # the child sets OpenCV's pool (limit_native_pools): it must inherit none
        proc.start()
    for c in child_ends:
        c.close()
    _PRESTARTED.append((proc, *parent_ends))
    return True


def _fit_pipes(ctx) -> tuple[tuple, tuple]:
    """The three one-way pipes between a run and its fit: ``((rows, out, ready) ends of the fit, the same of the
    run)``. The run sends rows and reads fits and the PnP model (once the networks are built)."""
    rows_child, rows = ctx.Pipe(duplex=False)      # (receive end, send end)
    out, out_child = ctx.Pipe(duplex=False)
    ready, ready_child = ctx.Pipe(duplex=False)
    return (rows_child, out_child, ready_child), (rows, out, ready)


def release_prestarted(timeout: float = 10.0) -> None:
    """End the prestarted fit process that no worker took (nothing to do when there is none)."""
    import pickle

    while _PRESTARTED:
        proc, rows, out, ready = _PRESTARTED.pop()
        try:
            rows.send_bytes(pickle.dumps(NO_TAKE))
        except Exception:        # gone already, or its pipe closed: the join below sees to it
            pass
        for c in (rows, out, ready):
            c.close()
        proc.join(timeout)
        if proc.is_alive():
            proc.kill()
            proc.join()


def _take_prestarted(take: tuple) -> tuple | None:
    """The prestarted process's ``(process, rows, out, ready, the take pickled)``, taken off the list; None where
    there is none, it has died, or the take does not pickle (it is then ended, and the worker forks afresh)."""
    if not _PRESTARTED:
        return None
    from multiprocessing.reduction import ForkingPickler     # as Connection.send

    proc = _PRESTARTED[-1][0]
    try:
        payload = bytes(ForkingPickler.dumps(take)) if proc.is_alive() else None
    except Exception:            # e.g. an actor holding something that does not pickle
        payload = None
    if payload is None:
        release_prestarted()
        return None
    return (*_PRESTARTED.pop(), payload)


def _prestarted_main(rows_conn, out_conn, ready_conn, parent_ends) -> None:
    """A prestarted fit process: the imports, then the take the parent sends (or none). Ctrl-C is the parent's to
    handle; SIGTERM ends it until it has a take (so that a parent which exits without releasing it can end it:
    multiprocessing terminates its daemonic children at exit), then _child_main ignores it too."""
    import importlib

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for c in parent_ends:
        c.close()
    got: list[bytes] = []

    def read_take():
        """The take's message, read as soon as it comes: the parent's send of its ~4 MB must not wait for the
        imports (a pipe holds 64 KB), or its stages would start that much later."""
        try:
            got.append(rows_conn.recv_bytes())
        except (EOFError, OSError):                  # the parent is gone
            pass

    reader = threading.Thread(target=read_take, name="capture-fit-take", daemon=True)
    reader.start()
    for name in PRESTART_IMPORTS:
        importlib.import_module(name)
    from capture.io.threads import limit_native_pools

    limit_native_pools(1)        # forked before the parent set its pools: OpenCV's and the BLAS libraries' as there
    reader.join()
    if not got:
        return
    from multiprocessing.reduction import ForkingPickler     # what Connection.send pickled it with

    msg = ForkingPickler.loads(got[0])
    if isinstance(msg, tuple) and msg and msg[0] == "take":
        _child_main(rows_conn, out_conn, ready_conn, (), *msg[1:])


class FitWorker:
    """:func:`capture.fit.stream.fit_take_stream` in a child process (or a thread), fed row by row.

    Use::

        worker = FitWorker(actor, template_points, camera, how)   # forks here: before other threads start
        # in one thread:   worker.feed(rows, stop)                 # rows: (points, weights, face_found)
        # in another:      for ff, rows_read in worker.results(stop): ...
        worker.close()                                            # always (also after an error)

    ``rows_read`` is how many rows the fit had read when it gave ``ff`` (the live lag). After the take,
    :attr:`timings` holds the fit's timings (``query_s``, ``pnp_s``, ``solve_s``, ``busy_s`` ...).

    ``nice``: niceness added to the fit's threads (Linux; :func:`capture.io.priority.background_thread`):
    ``capture run`` gives the CPU to decoding and detection first, and the fit fills what they leave from
    its queue of rows; ``capture live`` keeps 0 (its lag).
    """

    @staticmethod
    def forks(in_process: bool | None = None, threads: int = 1) -> bool:
        """Whether a worker made with ``in_process`` and ``threads`` runs the fit in a forked process (else in a
        thread, which starts in the constructor: load C extensions such as pxr before it, see capture.run.stream).

        By default it forks on Linux (macOS' system libraries are not fork-safe), except for a fit of more than
        one thread in a process that has loaded torch (:func:`torch_forbids_fork`)."""
        return FitWorker.thread_reason_for(in_process, threads) is None

    @staticmethod
    def thread_reason_for(in_process: bool | None = None, threads: int = 1) -> str | None:
        """Why a worker made with ``in_process`` and ``threads`` runs the fit in a thread (for the run's record);
        None where it forks (:meth:`forks`)."""
        if in_process is not None:
            return None if in_process else "asked for"
        if not (sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()):
            return "no fork on this platform"
        if torch_forbids_fork(threads):
            return f"torch is loaded in this process and the fit has {threads} threads"
        return None

    def __init__(self, actor, template_points, camera, how, causal: bool = False, threads: int = 1,
                 in_process: bool | None = None, nice: int = 0):
        from capture.fit.init import PnPSettings

        #: why the fit runs in a thread (for the run's record), None in a process
        self.thread_reason = self.thread_reason_for(in_process, threads)
        self.in_process = self.thread_reason is None
        self.actor = actor
        take = ("take", actor, template_points, camera, how, causal, threads, False, nice)
        taken = _take_prestarted(take) if self.in_process else None
        self.prestarted = taken is not None     # a process forked by prestart() took the fit
        ctx = multiprocessing.get_context("fork") if self.in_process else multiprocessing
        if taken is None:
            ((self._rows_child, self._out_child, self._ready_child),
             (self._rows, self._out, self._ready)) = _fit_pipes(ctx)
        else:
            self._proc, self._rows, self._out, self._ready, payload = taken
        self.timings: dict = {}
        self._n_landmarks, self._camera = len(template_points), camera
        self._pnp_settings = PnPSettings()     # fit_take_stream's default
        self._ready_lock = threading.Lock()
        self._model_points = None
        self._built = False
        self._basis = None      # the actor's features (models.fit_state.mesh_basis), sent before the first fit
        self._pnp_s = 0.0
        self._send_lock = threading.Lock()
        self._sent_end = False
        self.rows_sent = 0
        self.rows_read = 0      # as the fit last said (with a fit, or when it waits for rows)
        self._progress = threading.Condition()
        if taken is not None:      # forked before: it imported torch meanwhile, and now gets its take
            self._rows.send_bytes(payload)
            return
        args = (self._rows_child, self._out_child, self._ready_child, (self._rows, self._out, self._ready), actor,
                template_points, camera, how, causal, threads, not self.in_process, nice)
        if self.in_process:
            self._proc = ctx.Process(target=_child_main, args=args, name="capture-fit", daemon=True)
            with opencv_pool_stopped():
                self._proc.start()
            for c in (self._rows_child, self._out_child, self._ready_child):
                c.close()
        else:
            self._proc = threading.Thread(target=_child_main, args=args, name="capture-fit", daemon=True)
            self._proc.start()

    def _send(self, item) -> None:
        with self._send_lock:
            if not self._sent_end:
                self._rows.send(item)
                if isinstance(item, str):
                    self._sent_end = True
                else:
                    self.rows_sent += 1

    def _heard(self, rows_read: int) -> None:
        with self._progress:
            self.rows_read = max(self.rows_read, int(rows_read))
            self._progress.notify_all()

    def _wait_backlog(self, max_backlog: int, stop: threading.Event | None) -> None:
        """Wait while more than ``max_backlog`` rows were sent and not read (see the module docstring)."""
        with self._progress:
            while self.rows_sent - self.rows_read > max_backlog:
                if stop is not None and stop.is_set():
                    raise FitStopped
                if not self._alive():       # results() says why
                    return
                self._progress.wait(0.1)

    def feed(self, rows: Iterable, stop: threading.Event | None = None, max_backlog: int | None = None) -> None:
        """Send every row of ``rows``, then the end of the take; an error in ``rows`` aborts the fit (and is
        raised here). ``max_backlog``: wait before a row while more than that many were sent and not yet read
        by the fit (back-pressure; the consumer of :meth:`results` must go on reading them meanwhile).

        Each row goes with its head pose by PnP (:class:`capture.fit.init.PnPChain`, the fit's own, run
        here: it is a quarter of the fit's time, and this process has time beside decoding and detection).
        Its 3D model, the actor's neutral at the landmarks, comes from the fit once it has built the
        networks; rows wait for it in ``rows``' queue.
        """
        from capture.fit.init import PnPChain, clean_row

        chain = None
        try:
            for j, (points, weights, found) in enumerate(rows):
                if chain is None:
                    chain = PnPChain(self._wait_model_points(stop), self._camera.K, self._camera.dist,
                                     self._pnp_settings)
                p, w = clean_row(points, weights, found, self._n_landmarks, j)
                if max_backlog is not None:
                    self._wait_backlog(max_backlog, stop)
                self._send((p, w, bool(found), chain.next(p, w)))
                self._pnp_s = chain.seconds
        except BaseException:
            self.abort()
            raise
        self._send(END)

    def _wait_model_points(self, stop: threading.Event | None = None):
        """The PnP model the fit sends once it has built the actor's networks (waits for it)."""
        with self._ready_lock:
            while self._model_points is None:
                if self._ready.poll(0.1):
                    try:
                        self._model_points = self._ready.recv()
                    except EOFError:        # it failed before: results() raises its error
                        raise FitStopped("the fit process ended before it was ready") from None
                elif stop is not None and stop.is_set():
                    raise FitStopped
                elif not self._alive() and not self._ready.poll(0):
                    raise FitStopped("the fit ended before it was ready")
            return self._model_points

    def abort(self) -> None:
        """Tell the fit to stop after the window it is solving."""
        try:
            self._send(ABORT)
        except (OSError, ValueError):
            pass

    def results(self, stop: threading.Event | None = None, make_vertices: bool = True) -> Iterator[tuple]:
        """Yield ``(FrameFit, rows_read)`` in frame order until the take ends; raises the fit's error,
        or :class:`FitStopped` once ``stop`` is set. A fit sent with its mesh map and without its vertices gets
        them here (:func:`models.mesh_map.map_vertices` of :attr:`basis`), unless ``make_vertices`` is False."""
        while True:
            while not self._out.poll(0.1):
                if stop is not None and stop.is_set():
                    raise FitStopped
                if not self._alive():
                    if self._out.poll(0):
                        break
                    raise RuntimeError(f"the fit process ended unexpectedly (exit code {self._exitcode()}); "
                                       f"if the machine ran out of memory, fit fewer frames at a time "
                                       f"(--frames) or close other programs")
            try:
                msg = self._out.recv()
            except EOFError:
                raise RuntimeError(f"the fit process ended unexpectedly (exit code {self._exitcode()})") from None
            if msg[0] == "read":
                self._heard(msg[1])
            elif msg[0] == "fit":
                self._heard(msg[2])
                ff = msg[1]
                if make_vertices and ff.vertices is None and ff.mesh_map is not None:
                    ff.vertices = map_vertices(ff.mesh_map, self._basis)
                yield ff, msg[2]
            elif msg[0] == "basis":
                self._basis = msg[1]
            elif msg[0] == "end":
                self.timings = {**msg[1], "pnp_s": self._pnp_s}
                if msg[2] is not None and self.in_process:   # the parent's actor need not evaluate its networks
                    self.actor.set_face_rig(msg[2])
                return
            elif msg[0] == "aborted":
                raise FitStopped("the fit was stopped (its rows ended without the end of the take)")
            else:
                raise msg[1]

    @property
    def basis(self):
        """The actor's features that the fits' mesh maps map (``(K, V)`` float32), once the fit sent them
        (before its first fit with a map); None before that or for fits without maps."""
        return self._basis

    def wait_ready(self) -> None:
        """Wait until the fit has built the actor's networks and evaluated them at the template (``capture
        live``: before the source plays, so that no frame is dropped while torch is imported); raises the
        fit's error."""
        try:
            self._wait_model_points()
            with self._ready_lock:
                while not self._built:
                    if self._ready.poll(0.1):
                        self._built = self._ready.recv() == BUILT
                    elif not self._alive() and not self._ready.poll(0):
                        raise FitStopped("the fit ended before it was ready")
        except (FitStopped, EOFError):
            if self._out.poll(5.0):
                msg = self._out.recv()
                if msg[0] == "error":
                    raise msg[1] from None
            raise RuntimeError(f"the fit process ended before it was ready (exit code {self._exitcode()})") from None

    def _alive(self) -> bool:
        return self._proc.is_alive()

    def _exitcode(self):
        return getattr(self._proc, "exitcode", None)

    def close(self, timeout: float = JOIN_S) -> None:
        """Stop the fit (after the window it is solving) and wait for it; kill it after ``timeout`` s."""
        self.abort()
        t_end = time.monotonic() + timeout
        while self._alive() and time.monotonic() < t_end:
            try:
                while self._out.poll(0.05):   # drain: a child blocked on a full pipe cannot finish
                    self._out.recv()
            except (EOFError, OSError):
                pass
            self._proc.join(0.05)
        if self.in_process:
            if self._proc.is_alive():
                self._proc.kill()
                self._proc.join()
            for c in (self._rows, self._out, self._ready):
                c.close()
