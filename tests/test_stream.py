"""Streaming: the frame-by-frame fit equals the whole-take fit bit for bit; ``capture live`` keeps its lag and
equals the offline run of the same frames; the fast OBJ text equals Python's formatting; USD points written in
bulk read back as written."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import pytest

from tests.tiny_actor import synth_tiny_take, train_tiny_actor

N_FRAMES = 12


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    root = tmp_path_factory.mktemp("stream")
    actor = train_tiny_actor(root, iterations=60)
    out = synth_tiny_take(actor, root / "take", frames=N_FRAMES, landmarks=100)
    yield root, actor, out
    torch.set_num_threads(threads)


def test_streamed_fit_equals_the_whole_take_fit(take):
    """fit_take_stream reads one frame at a time and solves each window as soon as it can; on the same
    landmarks it must give exactly fit_take's numbers (same windows, initial poses, warm starts, blends),
    also with frames without a face inside the take and at its end (pose interpolation and holding)."""
    from calib.camera_io import read_camera
    from capture.actor.package import load_actor
    from capture.detector import embedded_points, read_embedding
    from capture.fit.stream import fit_take_stream
    from capture.fit.take import TakeLandmarks, WindowedFit, fit_take

    _, actor_dir, take_dir = take
    actor = load_actor(str(actor_dir))
    emb = read_embedding(actor.path, "synthetic_dense_100", actor.template)
    tp = embedded_points(emb, actor.template)
    with np.load(take_dir / "truth_landmarks.npz") as z:
        pts = z["points_2d"].astype(np.float64)
    pts = pts + np.random.default_rng(0).normal(0, 0.3, pts.shape)
    w = np.ones(pts.shape[:2])
    found = np.ones(len(pts), bool)
    found[[4, 5, N_FRAMES - 1]] = False          # a gap inside and a last frame without a face
    cam = read_camera(take_dir / "camera.json")
    how = WindowedFit("default", window=5, overlap=2)
    ref = list(fit_take(actor, TakeLandmarks(pts, w, found, tp), cam, how))
    got = list(fit_take_stream(actor, ((pts[j], w[j], found[j]) for j in range(len(pts))), tp, cam, how))
    assert [f.frame for f in got] == [f.frame for f in ref] == list(range(N_FRAMES))
    for a, b in zip(got, ref):
        assert a.status == b.status
        for k in ("head_R", "head_t", "jaw_R", "jaw_t", "code", "coefficients_landmarks", "vertices", "landmarks_fit"):
            np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=f"frame {a.frame} {k}")
    assert [f.status for f in got][4:6] == ["bridged", "bridged"]


def test_a_causal_stream_that_ends_on_a_window_border_without_overlap(take):
    """capture live with --lag 1 has windows of 2 frames and no overlap: a take whose frames fill its last
    window exactly gave "no frames to fit" (the window after it was empty). Every frame must be fitted."""
    from calib.camera_io import read_camera
    from capture.actor.package import load_actor
    from capture.detector import embedded_points, read_embedding
    from capture.fit.stream import fit_take_stream
    from capture.fit.take import WindowedFit

    _, actor_dir, take_dir = take
    actor = load_actor(str(actor_dir))
    tp = embedded_points(read_embedding(actor.path, "synthetic_dense_100", actor.template), actor.template)
    with np.load(take_dir / "truth_landmarks.npz") as z:
        pts = z["points_2d"].astype(np.float64)
    cam = read_camera(take_dir / "camera.json")
    for window in (2, 3, 4):                      # 12 frames: every one ends on a border
        got = list(fit_take_stream(actor, ((pts[j], np.ones(len(tp)), True) for j in range(N_FRAMES)), tp, cam,
                                   WindowedFit("default", window=window, overlap=0), causal=True))
        assert [f.frame for f in got] == list(range(N_FRAMES))
        assert all(f.status == "fitted" and np.isfinite(f.vertices).all() for f in got)


def test_live_keeps_its_lag_and_equals_the_offline_run_of_the_same_frames(take, tmp_path):
    """The take played at its frame rate: every frame is final at most --lag frames after it arrived (JSON
    line per frame over UDP, and live.json); frames are dropped rather than queued when the pipeline is busy,
    and each one is counted. The offline run of the frames live kept (no clock, nothing dropped) gives the
    same numbers exactly: timing only decides which frames are processed, never what they give (one thread
    per stage, the same deterministic float operations in the same order)."""
    from capture.run.live import LiveConfig, run_live

    root, actor, take_dir = take
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.05)
    lag = 3
    cfg = LiveConfig(source=str(take_dir / "take.mp4"), actor=str(actor), camera=take_dir / "camera.json",
                     out=tmp_path / "live", lag=lag, fps=8.0, json_to=f"udp://127.0.0.1:{sock.getsockname()[1]}",
                     iterations=10)
    live = run_live(cfg)
    lines = []
    while True:
        try:
            lines.append(json.loads(sock.recv(1 << 16)))
        except socket.timeout:
            break
    sock.close()
    fr = live["frames"]
    assert fr["received"] == N_FRAMES and fr["processed"] + fr["dropped"] == N_FRAMES and fr["processed"] >= 2
    assert [m["frame"] for m in lines] == fr["processed_frames"]           # one line per frame, in order
    assert all(0 <= m["lag_frames"] <= lag for m in lines) and live["lag"]["max_frames"] <= lag
    assert set(lines[0]["expressions"]) == {"jawOpen", "smile", "browUp"}
    assert all(m["t_final_s"] >= m["t_source_s"] for m in lines)
    pools = live["settings"]["thread_pools"]          # recorded as set (capture.io.threads)
    assert pools["blas"] and all(b["threads"] == 1 for b in pools["blas"]) and pools["usd"] == cfg.threads

    off = run_live(replace(cfg, realtime=False, only_frames=tuple(fr["processed_frames"]), json_to="none",
                           out=tmp_path / "offline"))
    assert off["frames"]["dropped"] == 0 and off["frames"]["processed_frames"] == fr["processed_frames"]
    with np.load(tmp_path / "live" / "params.npz") as a, np.load(tmp_path / "offline" / "params.npz") as b:
        assert a["frame_index"].tolist() == fr["processed_frames"]
        for k in ("head_R", "head_t_mm", "jaw_R", "jaw_t_mm", "codes", "coefficients_landmarks", "status"):
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    m = lines[-1]
    with np.load(tmp_path / "live" / "params.npz") as a:
        np.testing.assert_allclose(m["head_t_mm"], a["head_t_mm"][-1], atol=1e-6)   # the line is the take's frame


class _SlowReads:
    """A file source whose ``read`` takes ``seconds`` (a slow decoder or a starved thread); ``grab`` does not."""

    def __init__(self, path: str, seconds: float):
        import cv2

        self.cap, self.seconds = cv2.VideoCapture(path), seconds

    def read(self):
        import time

        time.sleep(self.seconds)
        return self.cap.read()

    def grab(self):
        return self.cap.grab()

    def release(self):
        self.cap.release()


def _check_counts(live: dict, lag: int) -> None:
    fr = live["frames"]
    assert fr["processed"] + fr["dropped"] == fr["received"] == N_FRAMES
    assert fr["dropped"] == sum(fr["dropped_why"].values())
    assert len(fr["processed_frames"]) == fr["processed"] and live["lag"]["max_frames"] <= lag
    assert live["fps_sustained"] == pytest.approx(fr["processed"] / live["source_seconds"])


def test_live_skips_a_files_frames_it_reads_too_late(take, tmp_path, monkeypatch):
    """A file plays as a camera delivers it: when reading a frame takes 2.4 frame periods, the frames whose
    time has passed by the next read are skipped and counted as late, instead of every frame being read
    later and later (before, none was dropped and the take lagged further behind the source at each
    frame). Frame i is read at about i / fps, so about every other frame is late."""
    import capture.run.live as live_mod
    from capture.run.live import LiveConfig, run_live

    _, actor, take_dir = take
    fps = 20.0
    real_open = live_mod.open_source

    def slow_source(source):
        cap, is_file, _, label = real_open(source)
        cap.release()
        return _SlowReads(source, 2.4 / fps), is_file, fps, label

    monkeypatch.setattr(live_mod, "open_source", slow_source)
    cfg = LiveConfig(source=str(take_dir / "take.mp4"), actor=str(actor), camera=take_dir / "camera.json",
                     out=tmp_path / "live", lag=3, json_to="none", iterations=10, queue_frames=N_FRAMES)
    live = run_live(cfg)
    _check_counts(live, 3)
    assert live["frames"]["dropped_why"]["late"] >= 3
    assert live["source_seconds"] == pytest.approx(N_FRAMES / fps)
    with np.load(tmp_path / "live" / "params.npz") as a:
        assert a["frame_index"].tolist() == live["frames"]["processed_frames"]


def test_live_drops_frames_while_the_fit_is_two_windows_behind(take, tmp_path, monkeypatch):
    """The fit process takes rows as they come; when its results come back slowly (here 0.6 s per frame after
    the first, at a source of 8 frames/s), the capture drops the frames that would wait beyond two windows
    (counted as fit_busy) instead of queueing them in the fit process without bound (before, none was
    dropped for it and the latency grew with every frame)."""
    import time

    from capture.fit.process import FitWorker
    from capture.run.live import LiveConfig, run_live

    _, actor, take_dir = take
    real_results = FitWorker.results

    def slow_results(self, stop=None):
        for k, item in enumerate(real_results(self, stop)):
            if k:
                time.sleep(0.6)
            yield item

    monkeypatch.setattr(FitWorker, "results", slow_results)
    lag = 1                                   # windows of 2 frames: at most 2 * 2 + 1 admitted rows ahead
    cfg = LiveConfig(source=str(take_dir / "take.mp4"), actor=str(actor), camera=take_dir / "camera.json",
                     out=tmp_path / "live", lag=lag, fps=8.0, json_to="none", iterations=10, queue_frames=1)
    live = run_live(cfg)
    _check_counts(live, lag)
    assert live["frames"]["dropped_why"]["fit_busy"] >= 1


def test_obj_vertex_text_is_pythons_formatting():
    """format_fixed4 must give the bytes of "v %.4f %.4f %.4f" exactly: random values over many magnitudes,
    values on rounding ties (x.xxxx5), negative zero and small negatives, non-finite and huge values."""
    from capture.export.mesh_files import format_fixed4

    rng = np.random.default_rng(1)
    rows = [rng.normal(0, s, (400, 3)) for s in (1e-5, 1e-3, 1.0, 150.0, 1e5)]
    x = np.concatenate(rows + [np.round(rows[2], 4), np.round(rows[3], 5) + 5e-5,
                               [[0.00005, -0.00005, -0.0], [0.00015, 1.23445, -9.99995], [np.nan, np.inf, -np.inf],
                                [1e20, -3e6, 2 ** 31 / 1e4]]])
    for v in (x, x.astype(np.float32).astype(np.float64)):
        ref = (("v %.4f %.4f %.4f\n" * len(v)) % tuple(v.ravel())).encode()
        assert format_fixed4(v, b"v ", b" ", b"\n") == ref


@dataclass
class _Fit:
    frame: int
    vertices: np.ndarray | None
    status: str = "fitted"


def test_usd_points_written_in_bulk_read_back(tmp_path):
    """Blocks of frames authored at once (usd_save_every 4, 10 frames, one skipped) read back per time code
    as diag(1,-1,-1) @ p_cam, with extents, and the mesh invisible on the skipped frame only."""
    pytest.importorskip("pxr")
    from pxr import Usd, UsdGeom

    from capture.export import ExportContext, ExportOptions, open_exporters

    rng = np.random.default_rng(2)
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    verts = [rng.normal(0, 50, (4, 3)).astype(np.float32) + [0, 0, 500] for _ in range(10)]
    ctx = ExportContext(faces=faces, fps=30, image_size=(64, 48), camera=None,
                        options=ExportOptions(usd_save_every=4))
    with open_exporters(["usd"], tmp_path, ctx) as w:
        for j, v in enumerate(verts):
            w.write(_Fit(j + 100, None if j == 6 else v, "skipped" if j == 6 else "fitted"))
    stage = Usd.Stage.Open(str(tmp_path / "take.usdc"))
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Take/Face"))
    assert mesh.GetPointsAttr().GetTimeSamples() == [float(j + 100) for j in range(10) if j != 6]
    for j, v in enumerate(verts):
        if j == 6:
            assert mesh.GetVisibilityAttr().Get(106) == UsdGeom.Tokens.invisible
            continue
        p = np.asarray(mesh.GetPointsAttr().Get(j + 100))
        np.testing.assert_array_equal(p, (v.astype(np.float64) * [1, -1, -1]).astype(np.float32))
        np.testing.assert_array_equal(np.asarray(mesh.GetExtentAttr().Get(j + 100)), [p.min(0), p.max(0)])
        assert mesh.GetVisibilityAttr().Get(j + 100) == UsdGeom.Tokens.inherited


def test_the_command_line_loads_without_heavy_imports():
    """capture --help (and the start of every command) must not import torch, pxr, av, ray or trimesh:
    they take seconds; each command imports what it needs when it runs."""
    code = ("import sys, capture.cli; from capture.cli import main; "
            "heavy = sorted(m for m in ('torch', 'pxr', 'av', 'ray', 'trimesh', 'scipy', 'onnxruntime') "
            "if m in sys.modules); print(','.join(heavy))")
    root = Path(__file__).resolve().parents[1]
    r = subprocess.run([sys.executable, "-c", code], cwd=root, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(root)})
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == ""


@pytest.mark.parametrize("lanes", [1, 2, 3, 4, 8])
def test_detection_groups_ramp_up_and_down(lanes):
    """Every segment once, in order, at most ``lanes`` side by side; the fit gets two segments first (its
    first window and the head poses after it) and one last (little left to fit when detection ends); the
    middle groups are full."""
    from capture.run.stream import ramped_groups

    for n in range(0, 41):
        groups = ramped_groups(list(range(100, 100 + n)), lanes)
        sizes = [len(g) for g in groups]
        assert sum(groups, []) == list(range(100, 100 + n))
        assert all(1 <= k <= lanes for k in sizes)
        if n >= 3:
            assert sizes[0] == min(2, lanes) and sizes[-1] == 1
        if n >= 4 * lanes:
            assert lanes in sizes and sizes.count(lanes) >= n // lanes - 3


def test_the_frame_pool_holds_the_largest_group_and_a_frame_per_lane():
    """The decoder fills the next group while the detector gives this one back a frame per lane at each step:
    the cap is the largest group (or, for one segment decoded by pieces, the piece) plus a frame per lane,
    never a second segment (each buffer is memory touched for the first time)."""
    from capture.run.stream import DetectPlan, pool_frames

    seg = {s: 32 for s in range(0, 320, 32)}
    seg[288] = 20                                             # the take's last, short segment
    plan = DetectPlan(sorted(seg), seg, {}, [[0, 32], [64, 96, 128], [160, 192, 224], [256], [288]], [], None, None)
    assert pool_frames(plan) == 96 + 3
    plan.piece = 10                                           # 1080p: single segments go by pieces of 10 frames
    assert pool_frames(plan) == 96 + 3
    plan.groups = [[0], [32], [64]]
    assert pool_frames(plan) == 10 + 1
    plan.groups = []                                          # everything cached
    assert pool_frames(plan) == 1 + 1


@pytest.mark.parametrize("sigma", [0.0, 1.0, 2.5])
def test_window_poses_from_the_frames_around_them_equal_the_whole_takes(sigma):
    """A window's initial poses are computed from the raw poses around it (so that a window costs the same
    however long the take), not from the whole take so far: they must equal the poses of the whole take
    (interpolated over frames without a pose, smoothed) bit for bit, with gaps at the start, inside and at
    the end, a single good frame between long gaps, and head turns past 180 degrees (quaternion signs)."""
    from capture.fit.init import PnPSettings, interpolate_poses, smooth_poses
    from capture.fit.stream import StreamLandmarkSource
    from models.quaternion import matrix_from_quat

    rng = np.random.default_rng(11)
    T = 400
    angle = np.cumsum(rng.normal(0.05, 0.04, T))          # turns past pi and on: the quaternions change sign
    axis = np.stack([np.sin(0.01 * np.arange(T)), np.ones(T), 0.3 * np.cos(0.02 * np.arange(T))], 1)
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    R_raw = matrix_from_quat(np.concatenate([axis * np.sin(angle / 2)[:, None], np.cos(angle / 2)[:, None]], 1))
    t_raw = np.cumsum(rng.normal(0, 1, (T, 3)), 0) + [0, 0, 600]
    ok = rng.uniform(size=T) > 0.2
    ok[:7] = False                      # no face at the start,
    ok[150:190] = False                 # a long gap,
    ok[170] = True                      # one frame in it,
    ok[-9:] = False                     # none at the end
    rows = [(np.zeros((3, 2)), np.ones(3), bool(k), (R_raw[j], t_raw[j]) if k else None) for j, k in enumerate(ok)]
    pnp = PnPSettings(smooth_sigma_frames=sigma)
    R_all, t_all = interpolate_poses(np.where(ok[:, None, None], R_raw, np.eye(3)), np.where(ok[:, None], t_raw, 0),
                                     ok)
    R_all, t_all = smooth_poses(R_all, t_all, sigma)
    src = StreamLandmarkSource(iter(rows), np.zeros((3, 3)), np.eye(3), np.zeros(5), pnp, None, None, None, "cpu",
                               n_landmarks=3)
    spans = []
    for s in range(0, T, 13):                     # windows of 17 frames, read as the take arrives
        e = min(s + 17, T)
        while not src._ready(e) and src._pull():
            pass
        R, t = src._poses(s, e)
        np.testing.assert_array_equal(R, R_all[s:e], err_msg=f"window {s}")
        np.testing.assert_array_equal(t, t_all[s:e], err_msg=f"window {s}")
        spans.append(src._pose_span(s, e))
    assert max(hi - lo for lo, hi in spans) < 120          # read around each window, not the whole take


def test_face_crops_are_cut_in_their_own_thread_and_the_buffers_come_back(monkeypatch):
    """The report's face crops, cut beside detection (capture.run.stream.FaceCrops): each offered frame's crop is
    the one FaceCrop.of cuts from it, its buffer goes back to the pool once cut, a frame never offered has none,
    the export waits for a crop being cut, and a stopped run does not leave it waiting."""
    import threading
    import time

    from capture.export import report_html as rh
    from capture.io.video import FramePool
    from capture.run.stream import FaceCrops, Pipeline, StageClock, _Stopped

    rng = np.random.default_rng(3)
    images = {i: rng.integers(0, 255, (480, 640, 3), dtype=np.uint8) for i in (3, 4, 5)}
    points = {i: rng.uniform([200, 150], [420, 380], (68, 2)) for i in images}
    expected = {i: rh.FaceCrop.of(images[i], points[i]) for i in images}
    gate = threading.Event()
    cut = rh.FaceCrop.of

    def slow_of(image, pts):          # frame 5 is cut only when the gate opens
        if image is images[5]:
            gate.wait(5)
        return cut(image, pts)

    monkeypatch.setattr(rh.FaceCrop, "of", staticmethod(slow_of))
    line = Pipeline()
    pool = FramePool(cap=3, stop=line.stop)
    crops = FaceCrops(line, pool, 3)
    line.start("crop", crops.run, StageClock())
    for i in images:
        crops.offer(i, images[i], points[i])
    crops.close()
    for i in (3, 4):
        got = crops.take(i)
        assert got.box == expected[i].box and got.jpeg == expected[i].jpeg
    assert crops.take(7) is None                                   # never offered
    taken = []
    waiter = threading.Thread(target=lambda: taken.append(crops.take(5)))
    waiter.start()
    time.sleep(0.3)
    assert not taken and len(pool) == 2                            # 5 is being cut: the export waits
    gate.set()
    waiter.join(5)
    assert taken[0].jpeg == expected[5].jpeg
    line.close()
    line.check()
    assert len(pool) == 3 and {id(b) for b in pool._free} == {id(im) for im in images.values()}

    line2 = Pipeline()                                             # stopped while a crop is pending
    stuck = FaceCrops(line2, FramePool(cap=1, stop=line2.stop), 1)
    stuck.offer(9, images[3], points[3])                           # no crop thread runs: it stays pending
    threading.Timer(0.2, line2.stop.set).start()
    with pytest.raises(_Stopped):
        stuck.take(9)
