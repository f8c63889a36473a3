"""The streamed fit in a process of its own (``capture.fit.process``): the same fits as in this process,
bit for bit; its errors reach the parent with their type; a stopped or abandoned fit ends its process."""

from __future__ import annotations

import sys
import threading

import numpy as np
import pytest

from tests.tiny_actor import synth_tiny_take, train_tiny_actor

N_FRAMES = 10


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    import torch

    from calib.camera_io import read_camera
    from capture.actor.package import load_actor
    from capture.detector import embedded_points, read_embedding

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("fitproc")
    actor_dir = train_tiny_actor(root, iterations=60)
    take_dir = synth_tiny_take(actor_dir, root / "take", frames=N_FRAMES, landmarks=100)
    actor = load_actor(str(actor_dir))
    tp = embedded_points(read_embedding(actor.path, "synthetic_dense_100", actor.template), actor.template)
    with np.load(take_dir / "truth_landmarks.npz") as z:
        pts = z["points_2d"].astype(np.float64) + np.random.default_rng(1).normal(0, 0.3, (N_FRAMES, 100, 2))
    found = np.ones(N_FRAMES, bool)
    found[3] = False
    rows = [(pts[j], np.ones(100), bool(found[j])) for j in range(N_FRAMES)]
    yield actor, tp, read_camera(take_dir / "camera.json"), rows, take_dir
    torch.set_num_threads(threads)


def _run(worker, rows):
    """Feed in a thread, as the pipelines do; returns the fits with the rows read when each came."""
    feeder = threading.Thread(target=worker.feed, args=(iter(rows),), daemon=True)
    feeder.start()
    try:
        return list(worker.results())
    finally:
        feeder.join(30)
        worker.close()


@pytest.mark.parametrize("in_process", [True, False], ids=["process", "thread"])
def test_the_worker_gives_the_fits_of_this_process(take, in_process):
    """Forked or threaded, the worker runs fit_take_stream on the rows it is sent: the same numbers, bit
    for bit, in frame order, and rows_read counts the rows the fit had read (a window of 4 frames cannot be
    solved before its frames arrived)."""
    from capture.fit.process import FitWorker
    from capture.fit.stream import fit_take_stream
    from capture.fit.take import WindowedFit

    actor, tp, cam, rows, _ = take
    how = WindowedFit("default", window=4, overlap=1)
    ref = list(fit_take_stream(actor, iter(rows), tp, cam, how))
    worker = FitWorker(actor, tp, cam, how, in_process=in_process)
    got = _run(worker, rows)
    assert worker.in_process is in_process
    assert [int(f.frame) for f, _ in got] == [int(f.frame) for f in ref] == list(range(N_FRAMES))
    for (a, n_read), b in zip(got, ref):
        assert n_read >= min(N_FRAMES, int(a.frame) + 1)
        assert a.status == b.status
        for k in ("head_R", "head_t", "jaw_R", "jaw_t", "code", "coefficients_landmarks", "vertices", "landmarks_fit"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=f"frame {a.frame} {k}")
    assert worker.timings["busy_s"] > 0 and worker.timings["windows_solved"] >= 3
    if in_process:
        assert not worker._proc.is_alive()


@pytest.mark.parametrize("in_process", [True, False], ids=["process", "thread"])
def test_back_pressure_bounds_the_rows_waiting_and_never_stalls_the_fit(take, in_process):
    """With max_backlog the feed waits while that many rows were sent and not read, so a slow consumer of the
    fits (the export of a long take) does not let every row of the take pile up in the fit's inbox. A fit
    that reads rows without giving fits (frames without a face: no window can be solved before a pose
    exists beyond it) says how many it has read, so a gap longer than the backlog does not stall it; the
    fits are the same, bit for bit."""
    import time

    from capture.fit.process import FitWorker
    from capture.fit.stream import fit_take_stream
    from capture.fit.take import WindowedFit

    actor, tp, cam, rows, _ = take
    rows = [(p, w, f and not 2 <= j < 9) for j, (p, w, f) in enumerate(rows * 3)]   # a gap of 7 frames
    how = WindowedFit("default", window=3, overlap=1)
    ref = list(fit_take_stream(actor, iter(rows), tp, cam, how))
    worker = FitWorker(actor, tp, cam, how, in_process=in_process)
    backlog = []
    send = worker._send

    def counted(item):
        if not isinstance(item, str):            # a row (not the end of the take)
            backlog.append(worker.rows_sent - worker.rows_read)
        send(item)

    worker._send = counted
    stalled = threading.Event()                   # a stalled fit ends the test (FitStopped) instead of hanging it
    timer = threading.Timer(120, stalled.set)
    timer.start()
    feeder = threading.Thread(target=worker.feed, args=(iter(rows), stalled, 2), daemon=True)
    feeder.start()
    got = []
    try:
        for ff, _ in worker.results(stalled):
            got.append(ff)
            time.sleep(0.02)                      # a slow export
    finally:
        timer.cancel()
        feeder.join(30)
        worker.close()
    assert not feeder.is_alive()
    assert len(backlog) == len(rows) and max(backlog) == 2       # waited: never more than 2 unread
    assert [int(f.frame) for f in got] == list(range(len(rows)))
    for a, b in zip(got, ref):
        assert a.status == b.status
        np.testing.assert_array_equal(a.vertices, b.vertices, err_msg=f"frame {a.frame}")


def test_an_error_of_the_fit_reaches_the_parent_with_its_type(take):
    """No frame has a face: the fit process fails (no head pose anywhere) and the parent raises that error,
    with its type, its message and, as a note for the log, where in the fit process it happened."""
    from capture.fit.process import FitWorker
    from capture.fit.take import WindowedFit

    actor, tp, cam, rows, _ = take
    faceless = [(p, w, False) for p, w, _ in rows]
    worker = FitWorker(actor, tp, cam, WindowedFit("default", window=4, overlap=1), in_process=True)
    with pytest.raises(ValueError, match="PnP failed everywhere") as caught:
        _run(worker, faceless)
    assert not worker._proc.is_alive()
    note = "".join(getattr(caught.value, "__notes__", []))
    assert "in the fit process" in note and "capture/fit/stream.py" in note     # the child's traceback, for logs


def test_a_bad_row_fails_in_the_feed_and_stops_the_fit(take):
    """A row of 50 landmarks where the actor has 100: feed (which cleans the rows and runs the PnP) raises
    at that row, and the fit process stops."""
    from capture.fit.process import FitStopped, FitWorker
    from capture.fit.take import WindowedFit

    actor, tp, cam, rows, _ = take
    bad = rows[:2] + [(rows[2][0][:50], rows[2][1][:50], True)] + rows[3:]
    worker = FitWorker(actor, tp, cam, WindowedFit("default", window=4, overlap=1), in_process=True)
    with pytest.raises(ValueError, match=r"frame 2: landmarks should be \(100, 2\)"):
        worker.feed(iter(bad))
    with pytest.raises(FitStopped):
        list(worker.results())
    worker.close(timeout=30)
    assert not worker._proc.is_alive()


def test_a_failing_feed_stops_the_fit_process(take):
    """The parent's rows fail (as the plausibility check does): feed raises that error, the fit process is
    told to stop and ends, and the results end with FitStopped, not a wrong take."""
    from capture.fit.process import FitStopped, FitWorker
    from capture.fit.take import WindowedFit

    actor, tp, cam, rows, _ = take

    def failing():
        yield from rows[:5]
        raise KeyError("no face")

    worker = FitWorker(actor, tp, cam, WindowedFit("default", window=4, overlap=1), in_process=True)
    errors = []

    def feed():
        try:
            worker.feed(failing())
        except KeyError as exc:
            errors.append(exc)

    t = threading.Thread(target=feed, daemon=True)
    t.start()
    got = []
    with pytest.raises(FitStopped):
        for ff, _ in worker.results():
            got.append(int(ff.frame))
    t.join(10)
    worker.close(timeout=30)
    assert errors and not worker._proc.is_alive()
    assert got == sorted(got) and len(got) < N_FRAMES


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="niceness is per thread on Linux only")
@pytest.mark.parametrize("in_process", [True, False], ids=["process", "thread"])
def test_a_nice_fit_yields_the_cpu_in_every_thread_of_its_own_and_only_there(take, in_process):
    """``nice``: every thread of the fit (its process's, or the fit thread and the thread reading its rows)
    runs at the caller's niceness + ``nice``, read back from the kernel by thread id; the caller's threads
    keep theirs; the fits are the same."""
    import os

    from capture.fit.process import FitWorker
    from capture.fit.take import WindowedFit
    from capture.io.priority import BACKGROUND_NICE

    mine = os.getpriority(os.PRIO_PROCESS, threading.get_native_id())
    if mine + BACKGROUND_NICE > 19:
        pytest.skip(f"the tests run at niceness {mine}: no room left to lower a thread by {BACKGROUND_NICE}")
    actor, tp, cam, rows, _ = take
    how = WindowedFit("default", window=4, overlap=1)
    plain = _run(FitWorker(actor, tp, cam, how, in_process=in_process), rows)
    worker = FitWorker(actor, tp, cam, how, in_process=in_process, nice=BACKGROUND_NICE)
    worker.wait_ready()                 # its reading thread has started
    if in_process:
        tids = [int(t) for t in os.listdir(f"/proc/{worker._proc.pid}/task")]
    else:
        tids = [t.native_id for t in threading.enumerate() if t.name in ("capture-fit", "capture-fit-rows")]
    assert len(tids) >= 2
    assert {os.getpriority(os.PRIO_PROCESS, t) for t in tids} == {mine + BACKGROUND_NICE}
    assert os.getpriority(os.PRIO_PROCESS, threading.get_native_id()) == mine
    assert os.getpriority(os.PRIO_PROCESS, os.getpid()) == mine
    got = _run(worker, rows)
    assert len(got) == len(plain) == N_FRAMES
    for (a, _), (b, _) in zip(got, plain):
        np.testing.assert_array_equal(a.vertices, b.vertices)


def test_the_fit_process_ends_when_its_parent_is_gone(take):
    """The parent's end of the pipe closes without the end of the take (the parent was killed): the child
    reads the end of the pipe and exits instead of waiting for ever."""
    from capture.fit.process import FitWorker
    from capture.fit.take import WindowedFit

    actor, tp, cam, rows, _ = take
    worker = FitWorker(actor, tp, cam, WindowedFit("default", window=4, overlap=1), in_process=True)
    worker._rows.send(rows[0])
    worker._rows.close()               # what the kernel does to a killed parent's descriptors
    worker._proc.join(30)
    assert not worker._proc.is_alive() and worker._proc.exitcode == 0


def test_a_prestarted_process_takes_the_next_forked_worker_and_gives_the_same_fits(take):
    """prestart() forks the fit process ahead; the next worker that forks takes it instead (a threaded one leaves
    it), sends it the take and gets the fits of this process, bit for bit; then it ends like any worker's."""
    from capture.fit import process as P
    from capture.fit.stream import fit_take_stream
    from capture.fit.take import WindowedFit

    actor, tp, cam, rows, _ = take
    how = WindowedFit("default", window=4, overlap=1)
    ref = list(fit_take_stream(actor, iter(rows), tp, cam, how))
    assert P.prestart() and not P.prestart()           # one at a time
    proc = P._PRESTARTED[0][0]
    threaded = P.FitWorker(actor, tp, cam, how, in_process=False)
    assert not threaded.prestarted and P._PRESTARTED
    threaded.close(timeout=30)
    worker = P.FitWorker(actor, tp, cam, how, in_process=True)
    assert worker.prestarted and worker._proc is proc and not P._PRESTARTED
    got = _run(worker, rows)
    assert [int(f.frame) for f, _ in got] == [int(f.frame) for f in ref]
    for (a, _), b in zip(got, ref):
        for k in ("head_R", "head_t", "jaw_R", "jaw_t", "code", "coefficients_landmarks", "vertices", "landmarks_fit"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=f"frame {a.frame} {k}")
    assert not proc.is_alive() and proc.exitcode == 0


def test_a_prestarted_process_no_worker_took_ends(take):
    """Released (a run whose fit was cached, or that failed before it), or its parent gone, a prestarted fit
    process exits instead of waiting for ever."""
    from capture.fit import process as P

    assert P.prestart()
    proc = P._PRESTARTED[0][0]
    P.release_prestarted()
    assert not proc.is_alive() and proc.exitcode == 0 and not P._PRESTARTED
    assert P.prestart()
    proc, rows, out, ready = P._PRESTARTED.pop()
    rows.close()                       # what the kernel does to a killed parent's descriptors
    proc.join(30)
    assert not proc.is_alive() and proc.exitcode == 0
    out.close()
    ready.close()


def test_a_parent_that_exits_without_releasing_its_prestarted_process_does_not_hang():
    """A prestarted process takes SIGTERM until it has a take, so multiprocessing ends it at the parent's exit
    (it would wait for it for ever otherwise)."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    code = ("import os\nfrom capture.fit.process import _PRESTARTED, prestart\n"
            "assert prestart()\nprint(_PRESTARTED[0][0].pid, flush=True)\n")
    r = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    pid = int(r.stdout.split()[-1])
    assert not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text().split()[2]


def test_a_take_that_does_not_pickle_ends_the_prestarted_process_and_forks_afresh(take):
    """The prestarted process gets its take pickled; where that fails, the worker ends it and forks as before
    (which pickles nothing), with the same fits."""
    import copy

    from capture.fit import process as P
    from capture.fit.stream import fit_take_stream
    from capture.fit.take import WindowedFit

    actor, tp, cam, rows, _ = take
    how = WindowedFit("default", window=4, overlap=1)
    ref = list(fit_take_stream(actor, iter(rows), tp, cam, how))
    assert P.prestart()
    proc = P._PRESTARTED[0][0]
    unpicklable = copy.copy(actor)
    unpicklable.callback = lambda: None          # a lambda does not pickle
    worker = P.FitWorker(unpicklable, tp, cam, how, in_process=True)
    assert not worker.prestarted and not P._PRESTARTED and not proc.is_alive()
    got = _run(worker, rows)
    assert [int(f.frame) for f, _ in got] == [int(f.frame) for f in ref]
    for (a, _), b in zip(got, ref):
        np.testing.assert_array_equal(a.vertices, b.vertices, err_msg=f"frame {a.frame}")


def test_a_stop_event_ends_the_results_and_close_ends_the_process(take):
    from capture.fit.process import FitStopped, FitWorker
    from capture.fit.take import WindowedFit

    actor, tp, cam, _, _ = take
    worker = FitWorker(actor, tp, cam, WindowedFit("default", window=4, overlap=1), in_process=True)
    stop = threading.Event()
    stop.set()
    with pytest.raises(FitStopped):
        next(worker.results(stop))
    worker.close(timeout=30)
    assert not worker._proc.is_alive()


def test_capture_run_loads_neither_torch_nor_trimesh_outside_its_fit_process(take, tmp_path):
    """The parent of ``capture run`` checks the actor (safetensors' numpy reader, plyfile), decodes, detects,
    exports and reports; only the forked fit process builds the networks. Were torch imported in the
    parent, every run would start 2 s later. Nor may a BLAS library load there after the run limited the pools to
    one thread (scipy's own would). The run must still be whole: meshes, report and rig."""
    import base64
    import json
    import os
    import re
    import subprocess
    import sys
    from pathlib import Path

    actor, _, _, _, take_dir = take
    out = tmp_path / "run"
    code = (
        "import builtins, os, sys\n"
        "parent = os.getpid(); seen = []\n"
        "real = builtins.__import__\n"
        "def spy(name, *a, **k):\n"
        "    if os.getpid() == parent and name.split('.')[0] in ('torch', 'trimesh') and name not in seen:\n"
        "        seen.append(name)\n"
        "    return real(name, *a, **k)\n"
        "builtins.__import__ = spy\n"
        "from capture.cli import main\n"
        "code = main(sys.argv[1:])\n"
        "print('PARENT_IMPORTED=' + ','.join(seen))\n"
        "from threadpoolctl import threadpool_info\n"
        "print('BLAS_AT_END=' + repr([i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas']))\n"
        "sys.exit(code)\n")
    root = Path(__file__).resolve().parents[1]
    r = subprocess.run([sys.executable, "-c", code, "run", str(take_dir / "take.mp4"), "--actor", str(actor.path),
                        "--camera", str(take_dir / "camera.json"), "--out", str(out), "--formats", "npz,obj",
                        "--no-progress"], cwd=root, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(root)}, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "PARENT_IMPORTED=\n" in r.stdout, r.stdout
    report = json.loads((out / "report.json").read_text())
    # no BLAS library loaded after the run limited its pools (scipy brings its own): each would spin its own
    # threads, and a rerun in the same process would record changed settings
    blas = eval(r.stdout.split("BLAS_AT_END=")[1].splitlines()[0])
    assert blas == [1] * len(report["settings"]["thread_pools"]["blas"]), (blas, report["settings"]["thread_pools"])
    fit = next(s for s in report["stages"] if s["stage"] == "fit")
    assert fit["fit_process"] is True and report["frames"]["fitted"] == N_FRAMES
    assert fit["fit_process_prestarted"] is True      # forked first, it imported torch while the run started
    assert len(list((out / "meshes").glob("*.obj"))) == N_FRAMES
    svgs = re.findall(r"src='data:image/svg\+xml;base64,([^']+)'", (out / "report.html").read_text())
    assert any(b"jawOpen" in base64.b64decode(b) for b in svgs)    # the rig the fit process handed back


def test_the_pnp_model_comes_before_the_networks_are_evaluated_and_wait_ready_waits_for_both(take):
    """The parent can pose the first rows while the fit evaluates the actor at every template vertex; capture
    live's wait_ready returns only once that is done (no frame dropped for it)."""
    import copy

    from capture.fit.process import FitWorker
    from capture.fit.take import WindowedFit

    actor, tp, cam, rows, _ = take
    gate, entered = threading.Event(), threading.Event()
    slow = copy.copy(actor)

    def at_template():
        entered.set()
        assert gate.wait(30)
        return actor.at_template()

    slow.at_template = at_template
    worker = FitWorker(slow, tp, cam, WindowedFit("default", window=4, overlap=1), in_process=False)
    try:
        box = {}
        waiter = threading.Thread(target=lambda: box.setdefault("model", worker._wait_model_points()), daemon=True)
        waiter.start()
        waiter.join(20)
        assert "model" in box, "the PnP model did not come while the networks were being evaluated"
        model = box["model"]
        assert entered.wait(30) and not gate.is_set()
        assert model.shape == (len(tp), 3) and np.isfinite(model).all()
        ready = threading.Thread(target=worker.wait_ready, daemon=True)
        ready.start()
        ready.join(0.5)
        assert ready.is_alive()                         # still evaluating: not ready
        gate.set()
        ready.join(30)
        assert not ready.is_alive()
        got = _run(worker, rows)
        assert [int(f.frame) for f, _ in got] == list(range(N_FRAMES))
    finally:
        gate.set()
        worker.close()


#: OpenCV's pool busy on 2 threads (as in a calibration), then idle long enough for its workers to wait on their
#: condition variables
_OPENCV_BUSY_THEN_IDLE = """
import sys, time
import numpy as np, cv2
cv2.setNumThreads(2)
a = np.random.default_rng(0).random((1500, 1500), dtype=np.float32)
for _ in range(3):
    cv2.GaussianBlur(a, (0, 0), 3)
time.sleep(1.5)
"""

#: then a forked child that sets and uses the pool (as the prestarted fit process does: limit_native_pools)
_FORK_AFTER_OPENCV = _OPENCV_BUSY_THEN_IDLE + """
import multiprocessing as mp
from capture.io.threads import opencv_pool_stopped
def child():
    cv2.setNumThreads(1)
    cv2.GaussianBlur(a, (0, 0), 3)
p = mp.get_context("fork").Process(target=child, daemon=True)
if sys.argv[1] == "stopped":
    with opencv_pool_stopped():
        p.start()
else:
    p.start()
p.join(20)
print("CHILD", p.exitcode, "THREADS", cv2.getNumThreads(), flush=True)
if p.is_alive():
    p.kill()
"""

#: then ``capture run`` in the same process, through the library
_RUN_AFTER_OPENCV = _OPENCV_BUSY_THEN_IDLE + "from capture.cli import main\nsys.exit(main(sys.argv[1:]))\n"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the fit forks only on Linux")
def test_a_child_forked_with_opencvs_pool_stopped_can_use_opencv():
    """OpenCV's pthreads pool is not fork-safe: a child forked while the pool's workers wait on their condition
    variables hangs in its first ``cv2.setNumThreads`` (the control, which shows the test can fail). Forked inside
    :func:`opencv_pool_stopped`, the child sets and uses the pool, and the parent gets its 2 threads back."""
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = {}
    for mode in ("bare", "stopped"):
        r = subprocess.run([sys.executable, "-c", _FORK_AFTER_OPENCV, mode], cwd=root, capture_output=True,
                           text=True, timeout=120)
        assert r.returncode == 0, r.stderr[-2000:]
        out[mode] = r.stdout.split()
    assert out["bare"][:2] == ["CHILD", "None"], out       # still waiting after 20 s: the hang
    assert out["stopped"] == ["CHILD", "0", "THREADS", "2"], out


#: torch's OpenMP pool run on 2 threads (as training an actor does), then idle; then ``capture run`` in the same
#: process, through the library
_RUN_AFTER_TORCH = """
import sys, time
import torch
from capture.cli import main
torch.set_num_threads(2)
a = torch.randn(800, 800)
for _ in range(5):
    (a @ a).sin().sum()
time.sleep(1.5)
sys.exit(main(sys.argv[1:]))
"""


def _run_in_a_script(code: str, take, out, *extra: str) -> dict:
    """``capture run`` of the module's take (npz only, 5 iterations) in a fresh Python that runs ``code``, which
    ends in ``sys.exit(main(sys.argv[1:]))``; asserts it succeeded and returns its report."""
    import json
    import subprocess
    from pathlib import Path

    actor, _, _, _, take_dir = take
    r = subprocess.run([sys.executable, "-c", code, "run", str(take_dir / "take.mp4"), "--actor", str(actor.path),
                        "--camera", str(take_dir / "camera.json"), "--out", str(out), "--formats", "npz",
                        "--iterations", "5", "--no-progress", *extra],
                       cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    report = json.loads((out / "report.json").read_text())
    assert report["frames"]["fitted"] == N_FRAMES
    return report


def _fit_stage(report: dict) -> dict:
    return next(s for s in report["stages"] if s["stage"] == "fit")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the fit forks only on Linux")
def test_capture_run_in_a_process_that_already_ran_opencv(take, tmp_path):
    """A pipeline script that calibrates (OpenCV on its pool) and then runs a take through the library in the same
    process: the prestarted fit process set OpenCV's pool it had inherited and waited for ever. The run must
    finish, with the fit in its prestarted process."""
    fit = _fit_stage(_run_in_a_script(_RUN_AFTER_OPENCV, take, tmp_path / "run"))
    assert fit["fit_process_prestarted"] is True


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the fit forks only on Linux")
@pytest.mark.parametrize("threads", [1, 2])
def test_capture_run_in_a_process_that_already_ran_torch_on_two_threads(take, tmp_path, threads):
    """A script that trains an actor (torch's OpenMP pool on 2 threads) and then runs a take in the same process:
    a forked fit on 2 threads waited for ever in its first parallel region. With ``--threads 2`` the fit runs in a
    thread, and the run says why; with 1 it still forks (one thread does not touch the pool)."""
    fit = _fit_stage(_run_in_a_script(_RUN_AFTER_TORCH, take, tmp_path / "run", "--threads", str(threads)))
    if threads == 1:
        assert fit["fit_process"] is True and fit["fit_thread_reason"] is None
    else:
        assert fit["fit_process"] is False
        assert fit["fit_thread_reason"] == "torch is loaded in this process and the fit has 2 threads"
