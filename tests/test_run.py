"""``capture run`` / ``capture fit3d`` end to end on the tiny actor and a tiny synthetic take.

Outputs open in their readers, a rerun redoes nothing, a run killed part-way resumes to the same
outputs, each bad input is one line and exit status 2 with nothing lost, a frame without a face is
reported as skipped with exit status 0.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import numpy as np
import pytest
import trimesh

from capture.cli import main
from capture.io.machine import machine
from capture.run.inputs import parse_frame_range, resolve_camera
from tests.tiny_actor import synth_tiny_take, train_tiny_actor

REPO = Path(__file__).resolve().parents[1]
FAST = ["--iterations", "20", "--window", "8", "--threads", "1", "--no-progress"]
N_FRAMES = 20


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    """A tiny actor (100 iterations, width 64) and a 20-frame 320x240 synthetic take of it."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the test machine's cores are shared: one thread wastes least
    root = tmp_path_factory.mktemp("run")
    actor = train_tiny_actor(root)
    out = synth_tiny_take(actor, root / "take", frames=N_FRAMES)
    yield root, actor, out
    torch.set_num_threads(threads)


def run_args(take_dir: Path, actor: Path, out: Path, *extra: str) -> list[str]:
    return ["run", str(take_dir / "take.mp4"), "--actor", str(actor), "--camera", str(take_dir / "camera.json"),
            "--out", str(out), *FAST, *extra]


@pytest.fixture(scope="module")
def full_run(take):
    root, actor, take_dir = take
    out = root / "run_full"
    import capture.run.stages as stages

    chunk, stages.FIT_CHUNK = stages.FIT_CHUNK, 8  # several stored chunks (the killed run below has one)
    try:
        assert main(run_args(take_dir, actor, out)) == 0
    finally:
        stages.FIT_CHUNK = chunk
    assert len(json.loads(next(out.glob("fit/*/done.json")).read_text())["chunks"]) == 3
    return out


def _stages(out: Path) -> dict:
    report = json.loads((out / "report.json").read_text())
    return {s["stage"]: s for s in report["stages"]}


def test_outputs_open_in_their_readers(take, full_run):
    _, actor, take_dir = take
    out = full_run
    V = len(trimesh.load(actor / "template.ply", process=False).vertices)
    meshes = sorted((out / "meshes").glob("frame_*.obj"))
    assert len(meshes) == N_FRAMES
    assert len(trimesh.load(meshes[3], process=False).vertices) == V
    with np.load(out / "params.npz", allow_pickle=False) as p:
        assert p["head_R"].shape == (N_FRAMES, 3, 3) and p["frame_index"].tolist() == list(range(N_FRAMES))
        assert {"head_t_mm", "jaw_R", "jaw_t_mm", "codes", "coefficients_landmarks", "status"} <= set(p.files)
    with np.load(out / "landmarks.npz", allow_pickle=False) as lm:
        assert lm["points"].shape == (N_FRAMES, 200, 2) and lm["confidence"].shape == (N_FRAMES, 200)
    assert (out / "overlay.mp4").stat().st_size > 0
    try:
        from pxr import Usd
    except ImportError:
        Usd = None
    if Usd is not None:
        usd = next(out.glob("take.usd*"))
        stage = Usd.Stage.Open(str(usd))
        mesh = next(p for p in stage.Traverse() if p.GetTypeName() == "Mesh")
        assert len(mesh.GetAttribute("points").GetTimeSamples()) == N_FRAMES
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == {"requested": N_FRAMES, "first": 0, "last": N_FRAMES - 1, "fitted": N_FRAMES,
                                "skipped": 0}
    rms = [r["reprojection_rms_px"] for r in report["per_frame"]]
    assert len(rms) == N_FRAMES and all(r is not None and 0 <= r < 50 for r in rms)
    assert report["camera"]["is_default"] is False and report["camera"]["source"].endswith("camera.json")
    assert {"python", "torch", "onnxruntime", "opencv", "capture"} <= set(report["versions"])
    assert report["machine"] == machine()
    assert report["settings"]["fit_settings"]["iterations"] == 20
    blas = report["settings"]["thread_pools"]["blas"]   # numpy's OpenBLAS at least, at one thread (capture.io.threads)
    assert blas and all(b["threads"] == 1 for b in blas)
    assert {s["stage"] for s in report["stages"]} == {"detect", "fit", "export"}
    assert json.loads((out / "run.json").read_text())["status"] == "done"
    # The fitted meshes are near the truth (a few mm for this tiny, briefly trained setup).
    truth = np.load(take_dir / "truth_meshes.npz")["vertices"]
    v = trimesh.load(meshes[10], process=False).vertices
    assert np.linalg.norm(v - truth[10], axis=1).mean() < 10.0


def test_rerun_does_nothing_and_a_changed_setting_redoes_what_it_affects(take, full_run, monkeypatch, capsys):
    _, actor, take_dir = take
    import capture.fit.take

    def no_fit(*a, **k):
        raise AssertionError("fit_take called on a rerun")

    monkeypatch.setattr(capture.fit.take, "fit_take", no_fit)
    before = {p: p.stat().st_mtime_ns for p in (full_run / "meshes").glob("*.obj")}
    assert main(run_args(take_dir, actor, full_run)) == 0
    st = _stages(full_run)
    assert [st[k]["status"] for k in ("detect", "fit", "export")] == ["skipped"] * 3
    assert st["detect"]["frames_detected"] == 0
    assert {p: p.stat().st_mtime_ns for p in (full_run / "meshes").glob("*.obj")} == before
    assert "20 fitted" in capsys.readouterr().out
    # Other formats: only the export is redone (the fit is still not called), from the fit cache, which holds
    # each frame's mesh as its map of the actor's features (no vertices): the same meshes as the streamed run's.
    fit_dir = next(full_run.glob("fit/*/done.json")).parent
    assert (fit_dir / "mesh_basis.npy").is_file()
    assert not any("vertices.npy" in zipfile.ZipFile(c).namelist() for c in fit_dir.glob("frames_*.npz"))
    streamed = trimesh.load(full_run / "meshes" / "frame_000003.obj", process=False).vertices
    assert main(run_args(take_dir, actor, full_run, "--formats", "ply,npz")) == 0
    st = _stages(full_run)
    assert st["fit"]["status"] == "skipped" and st["export"]["status"] == "done"
    assert len(list((full_run / "meshes").glob("*.ply"))) == N_FRAMES
    np.testing.assert_allclose(trimesh.load(full_run / "meshes" / "frame_000003.ply", process=False).vertices,
                               streamed, rtol=0, atol=1e-4)     # OBJ text: 4 decimals, rounding <= 5e-5 mm
    assert not list((full_run / "meshes").glob("*.obj"))  # the old export's files are replaced
    assert main(run_args(take_dir, actor, full_run)) == 0  # back to the default formats for later tests
    assert _stages(full_run)["fit"]["status"] == "skipped"


def test_killed_run_resumes_to_the_same_outputs(take, full_run):
    root, actor, take_dir = take
    out = root / "run_killed"
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    args = run_args(take_dir, actor, out)
    proc = subprocess.Popen([sys.executable, "-m", "capture.cli", *args], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.time() + 90
        while time.time() < deadline and proc.poll() is None:
            if list(out.glob("fit/*/windows/win_000000.npz")):
                break
            time.sleep(0.02)
        assert proc.poll() is None, "the run ended before it could be interrupted"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    # 130, or death by SIGINT, which a shell reports as the same 130. The second was seen in 2 of ~40 runs on
    # a loaded machine, after the run had handled the interrupt (its message printed, its work kept, no
    # traceback). It is CPython's: under `python -m` (as here), a KeyboardInterrupt that passed through code a
    # C extension ran with PyRun_String marks the run "interrupted" for good, and after sys.exit(130) the
    # interpreter ends itself by SIGINT (reproduced with ctypes' PyRun_StringFlags). The `capture` console
    # script runs as a file, where sys.exit(130) is final.
    assert proc.returncode in (130, -signal.SIGINT), err
    assert "run the same command to resume" in err.strip().splitlines()[-1]
    assert not (out / "report.json").exists() and not list(out.glob("fit/*/done.json"))
    assert main(args) == 0
    st = _stages(out)
    assert st["detect"]["status"] == "skipped"
    with np.load(out / "params.npz") as a, np.load(full_run / "params.npz") as b:
        for k in ("head_R", "head_t_mm", "jaw_R", "codes", "coefficients_landmarks"):
            np.testing.assert_allclose(a[k], b[k], atol=1e-5, err_msg=k)
    for name in ("frame_000000.obj", "frame_000019.obj"):
        va = trimesh.load(out / "meshes" / name, process=False).vertices
        vb = trimesh.load(full_run / "meshes" / name, process=False).vertices
        np.testing.assert_allclose(va, vb, atol=2e-4)


def _error(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("capture: error: ")
    return err[0]


def test_bad_input_is_one_line_and_exit_2(take, full_run, tmp_path, capsys, monkeypatch):
    _, actor, take_dir = take
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("CAPTURE_ACTORS", raising=False)
    video = take_dir / "take.mp4"
    cam = ["--camera", str(take_dir / "camera.json")]

    def run(*args):
        return main(["run", *[str(a) for a in args], *FAST])

    (tmp_path / "text.mp4").write_text("not a video")
    (tmp_path / "empty.mp4").write_bytes(b"")
    for bad in ("text.mp4", "empty.mp4", "missing.mp4"):
        assert run(tmp_path / bad, "--actor", actor, *cam) == 2
        assert "video" in _error(capsys)
    assert run(video, "--actor", "nosuch", *cam) == 2
    assert "unknown actor 'nosuch'" in _error(capsys)
    # A camera of another aspect ratio; a pure resize is accepted and reported.
    other = json.loads((take_dir / "camera.json").read_text())
    other["image_size"] = [640, 360]
    (tmp_path / "cam169.json").write_text(json.dumps(other))
    assert run(video, "--actor", actor, "--camera", tmp_path / "cam169.json") == 2
    assert "320x240" in _error(capsys)
    other["image_size"] = [640, 480]
    (tmp_path / "cam2x.json").write_text(json.dumps(other))
    rc = resolve_camera(tmp_path / "cam2x.json", 320, 240)
    assert rc.camera.image_size == (320, 240) and "resized" in rc.note
    assert resolve_camera(None, 320, 240).camera.is_default
    # Detector spec that does not match its model.
    det = next((take_dir / "detector").glob("*.onnx"))
    (tmp_path / "det").mkdir()
    shutil.copy(det, tmp_path / "det" / det.name)
    spec = json.loads(det.with_suffix(".json").read_text())
    spec["input"]["size"] = [128, 128]
    (tmp_path / "det" / det.with_suffix(".json").name).write_text(json.dumps(spec))
    assert run(video, "--actor", actor, *cam, "--detector", tmp_path / "det" / det.name) == 2
    assert "detector spec" in _error(capsys)
    # No detector beside a copied video.
    shutil.copy(video, tmp_path / "copy.mp4")
    assert run(tmp_path / "copy.mp4", "--actor", actor, *cam) == 2
    assert "--detector" in _error(capsys)
    # An actor without the detector's landmark embedding.
    bare = tmp_path / "bare_actor"
    shutil.copytree(actor, bare)
    shutil.rmtree(bare / "landmarks")
    assert run(video, "--actor", bare, *cam) == 2
    assert "landmark embedding" in (msg := _error(capsys)) and "make one" in msg
    for frames in ("abc", "5:100", "10:5", "1:2:3"):
        assert run(video, "--actor", actor, *cam, "--frames", frames) == 2
        assert "--frames" in _error(capsys)
    assert main(["run", str(video), "--actor", str(actor), "--formats", "obj,gif"]) == 2
    assert "gif" in _error(capsys)
    # An output folder that holds another take is refused; nothing in it is touched.
    held = tmp_path / "held"
    shutil.copytree(full_run, held, ignore=shutil.ignore_patterns("detections", "fit"))
    run_json = json.loads((held / "run.json").read_text())
    run_json["take_id"], run_json["take_label"] = "another", "other.mp4"
    (held / "run.json").write_text(json.dumps(run_json))
    files = sorted(p.relative_to(held) for p in held.rglob("*"))
    assert run(video, "--actor", actor, *cam, "--out", held) == 2
    assert "another take" in _error(capsys)
    assert sorted(p.relative_to(held) for p in held.rglob("*")) == files
    # --overwrite replaces that run (its meshes go, this take's outputs come).
    assert run(video, "--actor", actor, *cam, "--out", held, "--frames", "0:8", "--formats", "npz", "--overwrite") == 0
    capsys.readouterr()
    assert not (held / "meshes").exists() and json.loads((held / "run.json").read_text())["take_id"] != "another"
    with np.load(held / "params.npz") as p:
        assert p["frame_index"].tolist() == list(range(8))
    (tmp_path / "user").mkdir()
    (tmp_path / "user" / "notes.txt").write_text("mine")
    assert run(video, "--actor", actor, *cam, "--out", tmp_path / "user") == 2
    assert "not empty" in _error(capsys)


def test_frame_range_parsing():
    assert parse_frame_range(None, 10) == (0, 10)
    assert parse_frame_range("2:5", 10) == (2, 5)
    assert parse_frame_range("3:", 10) == (3, 10)
    assert parse_frame_range(":-2", 10) == (0, 8)


def test_frames_without_a_face_are_reported_skipped(take, tmp_path):
    from capture.synth.video import VideoWriter, read_frames

    root, actor, take_dir = take
    blank = tmp_path / "blank" / "take.mp4"
    blank.parent.mkdir()
    shutil.copytree(take_dir / "detector", blank.parent / "detector")
    frames = list(read_frames(take_dir / "take.mp4"))[:12]
    with VideoWriter(blank, (320, 240), 25.0) as w:
        for i, f in enumerate(frames):
            w.write(np.zeros_like(f) if i in (4, 5) else f)
    out = tmp_path / "out"
    assert main(["run", str(blank), "--actor", str(actor), "--camera", str(take_dir / "camera.json"),
                 "--out", str(out), "--formats", "obj,npz", *FAST]) == 0
    report = json.loads((out / "report.json").read_text())
    assert [s["frame"] for s in report["skipped_frames"]] == [4, 5]
    assert all("no face" in s["reason"] for s in report["skipped_frames"])
    assert report["frames"]["requested"] == 12 and report["frames"]["skipped"] == 2


def _png(b64: str) -> np.ndarray:
    import base64

    import cv2

    return cv2.imdecode(np.frombuffer(base64.b64decode(b64), np.uint8), cv2.IMREAD_COLOR).astype(np.float64)


@pytest.mark.parametrize("formats", ["npz", "npz,overlay"])
def test_the_stream_hands_the_report_its_worst_frames(take, tmp_path, monkeypatch, formats):
    """The streamed run decodes the video once and keeps what the report's thumbnails need as it exports
    (report_html.WorstFrameImages), so report.html decodes nothing after the take: with the overlay, the
    overlay's frames, each the video's frame (read here with OpenCV); without it, the face crops that
    detection cut (report_html.FaceCrop), each in the thumbnail's box, and the thumbnails drawn from them
    within 35 dB of those drawn from the video's frames (a JPEG of quality 95 alone is ~40 dB; a wrong
    crop, shift or colour order is < 20)."""
    import cv2

    import capture.export.report_html as rh
    import capture.io.video as video

    root, actor, take_dir = take
    seen = {}
    original = rh.thumbnails

    def spy(path, frames, fits, dets, renderer, *args, images=None, **kwargs):
        seen.update(frames=list(frames), images=dict(images or {}))
        seen["from_video"] = original(path, frames, fits, dets, renderer, *args, **kwargs)
        seen["usable"] = {i: img.box == rh.face_box(dets[i].points, *img.frame_size)
                          for i, img in seen["images"].items() if isinstance(img, rh.FaceCrop)}
        def no_decoding(self, *a, **k):
            raise AssertionError(f"the report decoded the video {a}")

        with pytest.MonkeyPatch.context() as m:
            m.setattr(video.VideoReader, "__init__", no_decoding)
            seen["thumbs"] = original(path, frames, fits, dets, renderer, *args, images=images, **kwargs)
        return seen["thumbs"]

    monkeypatch.setattr(rh, "thumbnails", spy)
    out = tmp_path / "out"
    assert main(run_args(take_dir, actor, out, "--formats", formats)) == 0
    assert seen["frames"] and sorted(seen["images"]) == sorted(seen["frames"])
    assert [i for i, _ in seen["thumbs"]] == [i for i, _ in seen["from_video"]] == seen["frames"]
    if "overlay" in formats:
        cap = cv2.VideoCapture(str(take_dir / "take.mp4"))
        for i in range(max(seen["frames"]) + 1):
            ok, img = cap.read()
            assert ok
            if i in seen["images"]:
                np.testing.assert_array_equal(seen["images"][i], img)
        cap.release()
    else:
        assert all(isinstance(v, rh.FaceCrop) for v in seen["images"].values())
        assert all(seen["usable"].values())
    for (_, a), (_, b) in zip(seen["thumbs"], seen["from_video"]):
        a, b = _png(a), _png(b)
        assert a.shape == b.shape
        assert 10 * np.log10(255.0 ** 2 / max(np.mean((a - b) ** 2), 1e-12)) > 35.0
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64") >= len(seen["frames"])


def test_the_stream_gives_the_report_its_series_and_rows_as_it_exports(take, tmp_path, monkeypatch):
    """The report reads nothing back from the fit after a streamed take. The stream hands the report's series to
    the figure process once every fit went to the exporters and before they finish their files (USD's last
    block, the NPZ archives), once; that series is the one the report builds after the take from the fit
    folder, the rows' errors and the track's detections (every field equal: the same errors and confidence
    statistics, summarised frame by frame as they came). The report's rows (errors, head depths) are those
    that summarise_fit and check_head_depths read from the fit folder, and the worst frames' fits that the
    thumbnails are drawn with those that fits_at reads. Its landmark residuals' section (the runs of frames the
    actor does not explain) is the one summarise_fit's residuals give."""
    import dataclasses

    import capture.export.report_figures as rf
    import capture.export.usd as usd
    import capture.run.stages as stages
    import capture.run.take as take_module
    from capture.actor.package import load_actor
    from capture.detector import LandmarkTrack
    from capture.export.report_html import take_series
    from capture.run.checks import check_head_depths
    from capture.run.report import frame_table
    import capture.export.report_html as rh
    from capture.run.stages import LANDMARKS, fits_at, iter_fits
    from capture.run.take import THUMBNAIL_FIELDS, Detection, skip_reasons, summarise_fit
    from capture.detector import embedded_points, read_embedding
    from capture.fit.unexplained import ResidualTally
    from capture.run.report import unexplained_section

    root, actor, take_dir = take
    events = []
    submit, close, read_back = rf.FigureProcess.submit, usd.UsdTakeWriter.close, stages.iter_fits
    monkeypatch.setattr(rf.FigureProcess, "submit", lambda self, s: (events.append(("submit", s)), submit(self, s))[1])
    prepare = rf.FigureProcess.prepare
    monkeypatch.setattr(rf.FigureProcess, "prepare", lambda self: (events.append(("prepare", None)), prepare(self))[1])
    monkeypatch.setattr(usd.UsdTakeWriter, "close", lambda self: (events.append(("close", None)), close(self))[1])
    spy = (lambda *a, **k: (events.append(("read", None)), read_back(*a, **k))[1])
    for module in (stages, take_module):
        monkeypatch.setattr(module, "iter_fits", spy)
    monkeypatch.setattr(stages, "fits_at", lambda *a, **k: events.append(("read", None)))
    thumbnails = rh.thumbnails
    monkeypatch.setattr(rh, "thumbnails", lambda video, frames, fits, *a, **k: (
        events.append(("thumbnails", (list(frames), fits))), thumbnails(video, frames, fits, *a, **k))[1])
    out = tmp_path / "out"
    assert main(run_args(take_dir, actor, out, "--formats", "npz,usd")) == 0
    for module in (stages, take_module):
        monkeypatch.setattr(module, "iter_fits", read_back)
    # the figure process imports matplotlib once detection is done, then draws while the files are written
    assert [e for e, _ in events] == ["prepare", "submit", "close", "thumbnails"]
    got = events[1][1]
    report = json.loads((out / "report.json").read_text())
    errors = {r["frame"]: r["reprojection_rms_px"] for r in report["per_frame"]}
    assert sum(e is not None for e in errors.values()) >= N_FRAMES - 1
    track = LandmarkTrack.load_npz(out / LANDMARKS)
    fit_dir = Path(next(s for s in report["stages"] if s["stage"] == "fit")["fit_dir"])
    fits = summarise_fit(fit_dir, track)
    rows, _ = frame_table(fits, "reprojection_rms_px", [f.error for f in fits], skip_reasons(track, "d"))
    assert check_head_depths(fit_dir, rows) is None
    for r, f in zip(rows, fits):
        r["reprojection_rms_all_px"] = f.error_all
    keys = ("frame", "status", "reprojection_rms_px", "reprojection_rms_all_px", "head_depth_mm")
    assert [{k: r.get(k) for k in keys} for r in report["per_frame"]] == [{k: r.get(k) for k in keys} for r in rows]
    assert sum("head_depth_mm" in r for r in rows) >= N_FRAMES - 1
    worst, kept = events[3][1]
    assert len(worst) == rh.WORST_FRAMES
    for i, f in fits_at(fit_dir, worst, THUMBNAIL_FIELDS).items():
        for k in THUMBNAIL_FIELDS:
            a, b = getattr(kept[i], k, None), getattr(f, k)
            if a is None or isinstance(a, str):
                assert a == b, (i, k)
            else:
                np.testing.assert_array_equal(a, b, err_msg=f"frame {i} {k}")
    dets = {int(i): Detection(track.points[j], None if track.confidence is None else track.confidence[j],
                              bool(track.face_found[j])) for j, i in enumerate(track.frame_index)}
    ref = take_series(iter_fits(fit_dir), report["video"]["fps"], load_actor(str(actor)).face_rig().names, errors,
                      "px", dets)
    assert np.isfinite(ref.conf_median).sum() >= N_FRAMES - 1
    for f in dataclasses.fields(ref):
        a, b = getattr(got, f.name), getattr(ref, f.name)
        if isinstance(b, np.ndarray):
            np.testing.assert_array_equal(a, b, err_msg=f.name)
        else:
            assert a == b, f.name
    # the residuals' tally that the stream kept gives the section that the fit folder gives
    a = load_actor(str(actor))
    points = embedded_points(read_embedding(a.path, report["detector"]["name"], a.template_arrays,
                                            track.points.shape[1]), a.template_arrays)
    tally = ResidualTally.on_template(a.template, points)
    summarise_fit(fit_dir, track, tally)
    assert report["unexplained"] == json.loads(json.dumps(unexplained_section(tally, report["video"]["fps"])[0]))
    assert report["unexplained"]["noise_px"] > 0
    assert sum(report["unexplained"]["regions"].values()) == track.points.shape[1]


def test_a_segment_detected_piece_by_piece_gives_the_same_landmarks(take, full_run, tmp_path, monkeypatch):
    """Frames too large for two segments in the stream's decode budget go through a segment a few frames at a
    time (capture.run.stream.DECODE_PIECE_BYTES), the detector's track carried from piece to piece: the same
    landmarks and crops, to the bit, as the run that detected the segment in one go."""
    import capture.run.stream as stream

    root, actor, take_dir = take
    pieces = []
    original = stream.decode_pieces

    def spy(indices, piece):
        pieces.extend(original(indices, piece))
        return pieces[-len(original(indices, piece)):]

    monkeypatch.setattr(stream, "DECODE_PIECE_BYTES", 3 * 320 * 240 * 3)     # 3 frames of the 320x240 take
    monkeypatch.setattr(stream, "decode_pieces", spy)
    out = tmp_path / "out"
    assert main(run_args(take_dir, actor, out, "--formats", "npz")) == 0
    assert [len(p) for p in pieces] == [3] * 6 + [2]                           # 20 frames, one segment
    with np.load(out / "landmarks.npz") as a, np.load(full_run / "landmarks.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_fit3d_on_truth_meshes(take, tmp_path):
    _, actor, take_dir = take
    z = np.load(take_dir / "truth_meshes.npz")
    folder = tmp_path / "scans"
    folder.mkdir()
    for i in range(6):
        trimesh.Trimesh(z["vertices"][i] / 10.0, z["faces"], process=False).export(folder / f"scan_{i:03d}.obj")
    out = tmp_path / "fit3d"
    assert main(["fit3d", str(folder), "--actor", str(actor), "--out", str(out), "--units", "cm",
                 "--formats", "obj,npz", *FAST]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["error"]["kind"] == "3D vertex error" and report["error"]["unit"] == "mm"
    assert report["frames"]["fitted"] == 6 and report["per_frame"][0]["mesh"] == "scan_000.obj"
    assert 0 <= report["error"]["mean"] < 10.0
    assert len(list((out / "meshes").glob("*.obj"))) == 6
    assert main(["fit3d", str(folder), "--actor", str(actor), "--out", str(out), "--units", "cm",
                 "--formats", "obj,npz", *FAST]) == 0
    assert {s["status"] for s in json.loads((out / "report.json").read_text())["stages"]} == {"skipped"}


def test_demo_flow_with_a_bundled_actor(take, tmp_path, monkeypatch, capsys):
    """``capture demo`` end to end, with the tiny actor standing in for the bundled demo actor."""
    import capture.demo as demo

    _, actor, _ = take
    monkeypatch.setattr(demo, "bundled_demo_actor", lambda: actor)
    cfg = demo.DemoConfig(out=tmp_path / "demo", frames=10, size="320x240", landmarks=200, fit_iterations=20,
                          window=8, progress=False)
    result = demo.run_demo(cfg)
    out = capsys.readouterr().out
    assert "bundled pretrained demo actor" in out and "mean 3D vertex error" in out
    assert 0 <= result["mean_3d_error_mm"] < 10.0 and result["mean_reprojection_px"] is not None
    assert (tmp_path / "demo" / "run" / "report.json").is_file()
    assert demo.run_demo(cfg)["mean_3d_error_mm"] == result["mean_3d_error_mm"]  # a rerun reuses everything
    assert "reusing" in capsys.readouterr().out
