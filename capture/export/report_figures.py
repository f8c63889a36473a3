"""The report's figures drawn in a process that imported matplotlib while the take was running.

Importing matplotlib and pyplot costs 0.5-0.8 s, and drawing the five figures of ``report.html``
another 0.5-0.7 s; in a run they came after the take, one after the other, beside the worst-frame
thumbnails. :class:`FigureProcess` starts one process when the run starts (:data:`START_METHOD`), which
imports matplotlib while the take is decoded, detected and fitted, and draws
:func:`capture.export.report_html.figures` of the take's series when asked, while the run's process
draws the thumbnails. With ``FigureProcess(prepare_later=True)`` the import waits for
:meth:`FigureProcess.prepare`: a streamed run calls it when detection ends, so that the import runs on the
core that the fit's and the export's last frames leave idle, not beside the run's own start-up and the fit
process's import of torch. The figures are the same bytes as drawn in the run's process (the same function
on the same series; ``svg.hashsalt`` fixes the SVG ids). If the process is gone or fails, they are drawn
in the run's process. It starts no thread in the run's process (the fit process is forked from it).
"""

from __future__ import annotations

import multiprocessing
import sys


#: Forked where that is safe (Linux: the run has started no thread yet, as for the fit process): the child
#: has the run's modules already and only imports matplotlib, 0.77 CPU-seconds in all against 0.92-1.04 for a
#: fresh interpreter on a 1,200-frame run (``BENCHMARKS.md``, streaming pipeline, sixteenth round); elsewhere
#: a fresh interpreter.
START_METHOD = "fork" if sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods() \
    else "spawn"


#: The message of :meth:`FigureProcess.prepare`: import matplotlib now.
PREPARE = "prepare"


def _import_pyplot() -> None:
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot  # noqa: F401


def _serve(conn, parent_end=None, prepare_later: bool = False) -> None:
    import os
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)   # Ctrl-C is the run's to handle; it closes this process
    run = os.getppid()
    if parent_end is not None:     # forked: the run's end of the pipe is the run's alone, or this process would
        parent_end.close()         # never read the end of it when the run is killed (and keep its folder locked)
    if not prepare_later:
        _import_pyplot()

    from capture.export.report_html import figures

    while True:
        try:
            # a run killed with -9 may leave the pipe open in its fit process (forked after this one, with a copy of
            # the run's end) until that one ends: the parent's going is watched too
            while not conn.poll(0.5):
                if os.getppid() != run:
                    _leave()
            series = conn.recv()
        except (EOFError, OSError):                # the run is done or gone
            series = None
        if series is None:
            _leave()
        if isinstance(series, str) and series == PREPARE:
            _import_pyplot()       # once: a second import is a dictionary lookup
            continue
        try:
            conn.send(("ok", figures(series)))
        except Exception as exc:  # handed to the run, which draws the figures itself
            conn.send(("error", f"{type(exc).__name__}: {exc}"))


def _leave() -> None:
    """End the process at once: it holds no file and nothing to save, and a normal interpreter exit with
    matplotlib loaded took 0.24 s, which the run spent waiting for it in :meth:`FigureProcess.close`."""
    import os
    import sys

    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError, AttributeError):
            pass
    os._exit(0)


class FigureProcess:
    """``FigureProcess()`` starts the process; :meth:`submit` a series, then :meth:`result`; :meth:`close` ends
    it (always call it). ``prepare_later``: the process imports matplotlib at :meth:`prepare` (or at the first
    :meth:`submit`), not at once. The methods may be called from different threads."""

    def __init__(self, prepare_later: bool = False):
        import threading

        ctx = multiprocessing.get_context(START_METHOD)
        self._conn, child = ctx.Pipe()
        args = (child, self._conn if START_METHOD == "fork" else None, prepare_later)
        self._proc = ctx.Process(target=_serve, args=args, name="capture-report-figures", daemon=True)
        from capture.io.threads import opencv_pool_stopped

        with opencv_pool_stopped():
            self._proc.start()
        child.close()
        self._series, self._sent = None, False
        self._send_lock = threading.Lock()

    def _send(self, obj) -> bool:
        with self._send_lock:
            try:
                self._conn.send(obj)
                return True
            except (OSError, ValueError):
                return False

    def prepare(self) -> None:
        """Let the process import matplotlib now (``prepare_later``; otherwise it did at the start)."""
        self._send(PREPARE)

    def submit(self, series) -> None:
        """Start drawing ``report_html.figures(series)`` in the process; :meth:`result` gives them."""
        self._series = series
        self._sent = self._send(series)

    def result(self) -> list[tuple[str, str]]:
        """The figures of the submitted series, drawn in the process (here, if it was not usable)."""
        from capture.export.report_html import figures

        try:
            if self._sent:
                while not self._conn.poll(0.2):
                    if not self._proc.is_alive():
                        raise EOFError
                status, figs = self._conn.recv()
                if status == "ok":
                    return figs
        except (EOFError, OSError, ValueError):
            pass
        return figures(self._series)

    def close(self) -> None:
        self._send(None)
        with self._send_lock:
            self._conn.close()
        self._proc.join(2.0)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join()

    def __enter__(self) -> FigureProcess:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
