"""``capture synth`` end to end on the tiny actor: files, truth consistency, motion presets, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from calib.camera_io import read_camera
from capture.cli import main
from capture.synth.motion import PRESETS, generate_motion
from capture.synth.video import read_frames
from tests.tiny_actor import write_tiny_actor_inputs


def train_tiny_actor(root: Path) -> Path:
    shapes, skull, jaw = write_tiny_actor_inputs(root)
    actor = root / "actors" / "tiny"
    rc = main(["actor", "train", str(actor), "--shapes", str(shapes), "--skull", str(skull), "--jaw", str(jaw),
               "--iterations", "100", "--width", "64", "--no-progress"])
    assert rc == 0
    return actor


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    root = tmp_path_factory.mktemp("synth")
    actor = train_tiny_actor(root)
    out = root / "take"
    rc = main(["synth", "--actor", str(actor), "--out", str(out), "--frames", "6", "--size", "320x240",
               "--preset", "talk", "--landmarks", "200", "--distortion", "-0.1,0.02,0,0,0", "--obj", "--look",
               "--no-progress"])
    assert rc == 0
    return actor, out


def test_files_and_truth(take):
    actor, out = take
    report = json.loads((out / "truth.json").read_text())
    assert report["settings"]["size"] == [320, 240] and report["seed"] == 0
    name = report["detector"]["name"]
    for f in ("take.mp4", "camera.json", "truth_meshes.npz", "truth_params.npz", "truth_landmarks.npz",
              f"detector/{name}.onnx", f"detector/{name}.json", "meshes/frame_000005.obj"):
        assert (out / f).is_file(), f
    frames = list(read_frames(out / "take.mp4"))
    assert len(frames) == 6 and frames[0].shape == (240, 320, 3)
    cap = cv2.VideoCapture(str(out / "take.mp4"))  # the lossless default is readable by OpenCV too
    ok, bgr = cap.read()
    assert ok and np.abs(bgr[..., ::-1].astype(int) - frames[0]).max() <= 1
    cam = read_camera(out / "camera.json")
    assert cam.image_size == (320, 240) and cam.dist[0] == pytest.approx(-0.1)
    meshes = np.load(out / "truth_meshes.npz")
    params = np.load(out / "truth_params.npz")
    lms = np.load(out / "truth_landmarks.npz")
    T, V = meshes["vertices"].shape[:2]
    assert T == 6 and meshes["faces"].max() < V
    assert params["coefficients"].shape == (6, 3) and params["head_R"].shape == (6, 3, 3)
    np.testing.assert_allclose(params["head_R"] @ params["head_R"].transpose(0, 2, 1), np.broadcast_to(np.eye(3), (6, 3, 3)), atol=1e-5)
    assert lms["points_2d"].shape == (6, 200, 2) and lms["visible"].dtype == bool and lms["visible"].mean() > 0.5
    # Landmarks are their (triangle, barycentric) points of the truth mesh, projected with OpenCV.
    f, b = meshes["faces"][lms["face_index"]], lms["barycentric"]
    p3 = np.einsum("lk,lkc->lc", b, meshes["vertices"][2][f]).astype(np.float64)
    uv, _ = cv2.projectPoints(p3[:, None], np.zeros(3), np.zeros(3), cam.K, cam.dist)
    np.testing.assert_allclose(uv[:, 0], lms["points_2d"][2], atol=1e-3)
    # Each visible landmark shows its own colour in the decoded frame.
    code = report["colour_code"]
    lo, hi = np.array(code["box_min_mm"]), np.array(code["box_max_mm"])
    tmpl = np.load(out / "truth_landmarks.npz")  # template points from the embedding
    emb = json.loads((actor / "landmarks" / f"{name}.json").read_text())
    assert emb["count"] == 200 and emb["face_index"] == tmpl["face_index"].tolist()
    assert lo.shape == hi.shape == (3,)
    # --look: the same frames shaded for people, covering the same pixels as the coded video
    look = list(read_frames(out / "take_look.mp4"))
    assert len(look) == 6 and report["look_video"]["file"] == "take_look.mp4"
    face = frames[0].max(-1) >= 16
    lf = look[0][face].astype(int)
    assert face.mean() > 0.05 and (lf[:, 0] >= lf[:, 2]).mean() > 0.99  # skin tone: red over blue
    bg = np.abs(look[0][~face].astype(int) - 40)                      # dark background, lossy H.264
    assert np.median(bg) <= 1 and np.percentile(bg, 99) <= 10          # (ringing at the silhouette)


def test_params_reproduce_meshes(take):
    """Head-frame meshes = head_R^T (v - head_t); the head frame is the template frame (near the template)."""
    actor, out = take
    import trimesh

    meshes, params = np.load(out / "truth_meshes.npz"), np.load(out / "truth_params.npz")
    head = np.einsum("tji,tpj->tpi", params["head_R"], meshes["vertices"] - params["head_t"][:, None])
    template = trimesh.load(actor / "template.ply", process=False)
    assert np.abs(head - template.vertices[None]).mean() < 10.0


def test_motion_presets():
    names = ["jawOpen", "smile", "browUp", "eyeBlink_L", "eyeBlink_R"]
    turns = generate_motion(PRESETS["turns"], 250, 25.0, names, seed=1)
    assert 15 < np.abs(turns.yaw_deg).max() <= 30.0 + 1e-9 and np.abs(turns.pitch_deg).max() <= 20.0 + 1e-9
    assert np.abs(np.diff(turns.yaw_deg)).max() < 5.0  # smooth: under 5 degrees per frame
    frontal = generate_motion(PRESETS["frontal"], 100, 25.0, names, seed=1)
    assert not frontal.yaw_deg.any() and not frontal.pitch_deg.any()
    assert frontal.jaw_open.max() > 0.1 and frontal.jaw_shape == 0
    assert frontal.coefficients[:, 3:].max() > 0.5  # blinks happen in 4 s
    yaw = generate_motion(PRESETS["yaw30"], 10, 25.0, names, seed=1)
    np.testing.assert_allclose(yaw.yaw_deg, 30.0)
    a = generate_motion(PRESETS["talk"], 60, 25.0, names, seed=3)
    b = generate_motion(PRESETS["talk"], 60, 25.0, names, seed=3)
    np.testing.assert_array_equal(a.coefficients, b.coefficients)


@pytest.mark.parametrize("args,msg", [
    (["--size", "big"], "--size"),
    (["--distortion", "0.1,x"], "--distortion"),
    (["--preset", "dance"], "unknown preset"),
])
def test_bad_input_is_one_line(take, tmp_path, capsys, args, msg):
    actor, _ = take
    rc = main(["synth", "--actor", str(actor), "--out", str(tmp_path / "o"), "--no-progress", *args])
    err = capsys.readouterr().err
    assert rc == 2 and msg in err and err.count("\n") == 1


def test_unknown_actor_and_existing_out(take, tmp_path, capsys):
    actor, out = take
    assert main(["synth", "--actor", str(tmp_path / "nobody"), "--out", str(tmp_path / "o"), "--no-progress"]) == 2
    assert "unknown actor" in capsys.readouterr().err
    assert main(["synth", "--actor", str(actor), "--out", str(out), "--no-progress"]) == 2
    assert "--overwrite" in capsys.readouterr().err
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "keep.txt").write_text("x")
    assert main(["synth", "--actor", str(actor), "--out", str(tmp_path / "other"), "--overwrite", "--no-progress"]) == 2
    assert "refusing" in capsys.readouterr().err and (tmp_path / "other" / "keep.txt").exists()


def test_bundled_actor_is_not_written(tmp_path, monkeypatch, capsys):
    """``--actor demo`` (the bundled actor, read-only) puts the take's landmark embedding into the user's copy of
    the actor, which then shadows the bundled one for ``capture run --actor demo``; the package is left as shipped."""
    from capture.actor.package import bundled_actor, resolve_actor

    monkeypatch.setenv("CAPTURE_ACTORS", str(tmp_path / "actors"))
    bundled = bundled_actor("demo")
    before = sorted(p.relative_to(bundled) for p in bundled.rglob("*"))
    out = tmp_path / "take"
    assert main(["synth", "--actor", "demo", "--out", str(out), "--frames", "2", "--size", "160x120",
                 "--landmarks", "50", "--no-progress"]) == 0
    said = capsys.readouterr().out
    assert sorted(p.relative_to(bundled) for p in bundled.rglob("*")) == before
    report = json.loads((out / "truth.json").read_text())
    copy = tmp_path / "actors" / "demo"
    emb = copy / "landmarks" / f"{report['detector']['name']}.json"
    assert emb.is_file() and report["detector"]["embedding"] == str(emb)
    assert "bundled (read-only)" in said and str(copy) in said
    assert resolve_actor("demo") == copy
