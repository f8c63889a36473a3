"""The synthetic detector reads landmarks from decoded video frames (ONNX through onnxruntime).

Crops are computed from the truth (square, margin from the spec) as the generic runtime would from
its tracking. Measured on the tiny actor at 640x360 (see the assertions for the figures).
"""

from __future__ import annotations

import json

import numpy as np
import onnxruntime as ort
import pytest

from capture.cli import main
from capture.synth.detector_onnx import square_crop
from capture.synth.video import read_frames
from capture.io.video import VideoReader
from tests.test_synth_take import train_tiny_actor


@pytest.fixture(scope="module")
def actor(tmp_path_factory):
    return train_tiny_actor(tmp_path_factory.mktemp("det"))


def _session(out):
    report = json.loads((out / "truth.json").read_text())
    spec = json.loads((out / report["detector"]["spec"]).read_text())
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    sess = ort.InferenceSession(str(out / report["detector"]["onnx"]), so)
    assert [i.name for i in sess.get_inputs()] == [spec["input"]["name"]]
    assert [o.name for o in sess.get_outputs()] == [spec["outputs"][k]["name"] for k in ("landmarks", "confidence", "presence")]
    return sess, spec


def _run(sess, spec, frame, points, visible):
    """Landmarks (L, 2) in frame pixels, confidence (L,), presence of one frame."""
    crop, M = square_crop(frame, (*points[visible].min(0), *points[visible].max(0)), spec["crop"]["margin"],
                          spec["input"]["size"][0])
    pts, c, score = sess.run(None, {"image": crop.transpose(2, 0, 1)[None].astype(np.float32)})
    assert pts.shape == (1, spec["landmarks"]["count"], 2)
    return (pts[0] - M[:, 2]) / M[0, 0], c[0], float(score[0])


def _facing_cosine(out, j):
    """(L,) cosine between each landmark's triangle normal and the ray to the camera, frame j."""
    mesh, lms = np.load(out / "truth_meshes.npz"), np.load(out / "truth_landmarks.npz")
    tri = mesh["vertices"][j][mesh["faces"][lms["face_index"]]].astype(np.float64)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    p = lms["points_3d"][j].astype(np.float64)
    return -(n * p).sum(1) / (np.linalg.norm(n, axis=1) * np.linalg.norm(p, axis=1))


def _detect(out):
    sess, spec = _session(out)
    S = spec["input"]["size"][0]
    lms = np.load(out / "truth_landmarks.npz")
    errs, conf, vis, cos = [], [], [], []
    # the runtime decodes through OpenCV: its frames must be the very pixels PyAV decodes (no chroma loss)
    with VideoReader(out / "take.mp4") as reader:
        cv_frames = [f for _, f in reader.frames()]
    for j, frame in enumerate(read_frames(out / "take.mp4")):
        np.testing.assert_array_equal(cv_frames[j][..., ::-1], frame)
        p, v = lms["points_2d"][j], lms["visible"][j]
        est, c, score = _run(sess, spec, frame, p, v)
        assert score >= spec["outputs"]["presence"]["threshold"]
        errs.append(np.linalg.norm(est - p, axis=1))
        conf.append(c)
        vis.append(v)
        cos.append(_facing_cosine(out, j))
    empty = sess.run(None, {"image": np.zeros((1, 3, S, S), np.float32)})
    assert empty[2][0] < spec["outputs"]["presence"]["threshold"]  # no face, no presence
    return np.concatenate(errs), np.concatenate(conf), np.concatenate(vis), np.concatenate(cos)


@pytest.mark.parametrize("preset", ["frontal", "yaw30"])
def test_detector_accuracy_on_decoded_video(actor, tmp_path, preset):
    out = tmp_path / preset
    assert main(["synth", "--actor", str(actor), "--out", str(out), "--frames", "2", "--size", "640x360",
                 "--preset", preset, "--landmarks", "300", "--no-progress"]) == 0
    e, c, v, cos = _detect(out)
    confident = v & (c > 0.5)
    rms = float(np.sqrt((e[confident] ** 2).mean()))
    facing = v & (cos > 0.35)
    print(f"{preset}: median {np.median(e[v]):.3f} px, RMS confident-visible {rms:.3f} px, p99 "
          f"{np.percentile(e[confident], 99):.3f} px ({confident.sum()}/{v.sum()} confident; facing "
          f"{(confident & facing).sum()}/{facing.sum()}), occluded confident {(c[~v] > 0.5).sum()}/{(~v).sum()}")
    # Measured (2 frames, 300 landmarks): frontal median 0.114, RMS 0.125, p99 0.385 px, 373/454 confident,
    # 300/300 facing (cosine > 0.35) confident; yaw30 median 0.112, RMS 0.168, p99 0.631 px, 341/420
    # confident, 301/321 facing. Flagged landmarks are seen at grazing angles or lie next to an occluding
    # contour (the nose at yaw30), by design; occluded ones 0/146 and 0/180 confident.
    assert np.median(e[v]) < 0.2
    assert rms <= 0.5  # the goal of issue 4 (was 0.58 / 0.55 before the robust fit and the dither)
    assert confident.sum() > 0.7 * v.sum()
    assert (confident & facing).sum() > 0.9 * facing.sum()  # landmarks facing the camera are kept
    assert (~v).sum() > 50 and (c[~v] > 0.5).mean() < 0.02  # occluded landmarks are flagged (measured 0)


def test_occluder_flags_hidden_landmarks(actor, tmp_path):
    """A patch of another part of the face pasted over the mouth (an occluder with code-like colours):
    landmarks under it get low confidence, the others stay accurate."""
    out = tmp_path / "occ"
    assert main(["synth", "--actor", str(actor), "--out", str(out), "--frames", "1", "--size", "640x360",
                 "--preset", "frontal", "--landmarks", "300", "--no-progress"]) == 0
    sess, spec = _session(out)
    lms = np.load(out / "truth_landmarks.npz")
    p, v = lms["points_2d"][0], lms["visible"][0]
    frame = next(read_frames(out / "take.mp4")).copy()
    x0, x1 = np.percentile(p[v, 0], [25, 75])
    y0 = np.percentile(p[v, 1], 60)                      # image y down: the lower face
    h = 0.3 * (p[v, 1].max() - p[v, 1].min())
    box = np.array([x0, y0, x1, y0 + h]).round().astype(int)
    src = box - np.array([0, 1, 0, 1]) * int(round(1.8 * h))   # from higher up the face (forehead, eyes)
    frame[box[1]:box[3], box[0]:box[2]] = frame[src[1]:src[3], src[0]:src[2]]
    est, c, _ = _run(sess, spec, frame, p, v)
    margin = 3.0
    hidden = v & (p[:, 0] > box[0] + margin) & (p[:, 0] < box[2] - 1 - margin) & (p[:, 1] > box[1] + margin) \
        & (p[:, 1] < box[3] - 1 - margin)
    def within(b, pad):
        return (p[:, 0] > b[0] - pad) & (p[:, 0] < b[2] + pad) & (p[:, 1] > b[1] - pad) & (p[:, 1] < b[3] + pad)

    away = v & ~within(box, 12) & ~within(src, 12)     # neither under the patch nor where it comes from
    assert hidden.sum() > 10
    print(f"occluder: {hidden.sum()} hidden, confident {(c[hidden] > 0.5).sum()}; away RMS "
          f"{np.sqrt((np.linalg.norm(est - p, axis=1)[away & (c > 0.5)] ** 2).mean()):.3f} px")
    assert (c[hidden] > 0.5).mean() < 0.05
    e = np.linalg.norm(est - p, axis=1)[away & (c > 0.5)]
    assert np.sqrt((e ** 2).mean()) <= 0.5
