"""Detector spec version 2: the same detector in every tensor layout gives the format-1 landmarks;
anchor face detectors (BlazeFace style) decode, suppress and map back; layout errors are one line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from capture.detector import Detector
from capture.detector import synthetic as S
from capture.detector.crop import Crop, frame_to_input
from capture.detector.decode import anchor_counts, heatmap_peaks, make_anchors, nms
from capture.detector.finder import OnnxFaceFinder
from capture.detector.spec import AnchorSpec, parse_face_finder_spec
from capture.io.errors import CaptureError
from tests.test_detector_crop import _blobs

CENTRES = np.array([[150.3, 120.8], [190.6, 140.2], [165.1, 165.7]])
COLOURS = [(0, 0, 255), (0, 255, 0), (255, 0, 0)]


def _frames():
    # the face moves and turns a little over five frames (the track and the aligned crop follow it)
    out = []
    for t in range(5):
        a = np.radians(4.0 * t)
        rot = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        c = (CENTRES - CENTRES.mean(0)) @ rot.T + CENTRES.mean(0) + [2.7 * t, -1.9 * t]
        out.append(_blobs(288, 360, c, COLOURS))
    return out


def _v1(tmp_path, confidence=None):
    spec = S.detector_spec(size=(96, 96), first_frame="full_frame", margin=0.6, align={"left": 0, "right": 1},
                           presence={"name": "face_score", "threshold": 0.2},
                           confidence=None if confidence is None else {"name": "confidence", "kind": "probability"})
    model = S.centroid_model(size=(96, 96), confidence=confidence)
    return model, spec, Detector.load(S.save_detector(model, spec, tmp_path / "v1", "centroid"))


@pytest.mark.parametrize("layout", S.LAYOUTS_V2)
def test_every_layout_gives_the_format1_landmarks(tmp_path, layout):
    confidence = 0.8 if layout == "xyz_4d_corner" else None
    model, spec, det1 = _v1(tmp_path, confidence)
    m2, spec2 = S.relayout(model, spec, layout)
    det2 = Detector.load(S.save_detector(m2, spec2, tmp_path / "v2", "centroid"))
    assert det2.spec.raw["version"] == 2
    frames = _frames()
    r1 = det1.detect(frames)
    # on the same crops the decoded landmarks agree to 1e-4 px (float32 rounding of the relayout nodes)
    crops = [Crop(*a.crop) for a in r1]
    r2 = det2.run_crops(frames, crops, list(range(len(frames))))
    for a, b in zip(r1, r2):
        assert a.face_found and b.face_found
        np.testing.assert_allclose(b.points, a.points, rtol=0, atol=1e-4)
    # tracked, the crops follow their own landmarks; cv2.warpAffine samples at 1/32 px steps, so a
    # 1e-5 px change of a crop may move a sample by 1/32 px: the tracks agree to well below that
    t2 = det2.detect(frames)
    for a, b in zip(r1, t2):
        assert b.face_found
        np.testing.assert_allclose(b.points, a.points, rtol=0, atol=5e-3)
        np.testing.assert_allclose(b.crop, a.crop, rtol=0, atol=5e-3)
    for a, b in zip(r1, r2):
        assert b.presence == pytest.approx(1 / (1 + np.exp(-S.presence_logit(a.presence))), abs=1e-6)
    if layout == "xyz_4d_corner":
        for a, b in zip(r1, r2):
            np.testing.assert_allclose(b.confidence, a.confidence, atol=1e-6)
            crop = Crop(*b.crop)
            q = frame_to_input(a.points, crop, (96, 96))   # the v1 crop px of each landmark
            np.testing.assert_allclose(b.depth, S.depth_of(q) * crop.size / 96, atol=1e-4)
    if layout == "planar_flat_xyz_signed":
        crop = Crop(*r2[0].crop)
        np.testing.assert_allclose(r2[0].depth, S.depth_of(frame_to_input(r1[0].points, crop, (96, 96)))
                                   * crop.size / 96, atol=1e-4)
    if layout.startswith("heatmap"):
        # the heatmap peak is the confidence: a Gaussian of the sub-cell offset, 0.89..1
        for b in r2:
            assert b.confidence is not None and np.all((b.confidence > 0.85) & (b.confidence <= 1.0))


def test_heatmap_decoding_is_exact_for_gaussians_and_matches_a_plain_reference():
    rng = np.random.default_rng(3)
    h, w, sigma = 20, 24, 1.7
    true = rng.uniform([2, 2], [w - 3, h - 3], size=(2, 4, 2))
    ys, xs = np.mgrid[0:h, 0:w]
    hm = np.exp(-((xs - true[..., :1, None]) ** 2 + (ys - true[..., 1:, None]) ** 2) / (2 * sigma ** 2))
    uv, peak = heatmap_peaks(hm, "gaussian")
    np.testing.assert_allclose(uv, true, atol=1e-9)
    # plain reference for the parabola decode: one landmark at a time, loops
    uv_p, _ = heatmap_peaks(hm, "parabola")
    for i in range(2):
        for l in range(4):
            m = hm[i, l]
            y, x = np.unravel_index(np.argmax(m), m.shape)
            fx = x + 0.5 * (m[y, x - 1] - m[y, x + 1]) / (m[y, x - 1] - 2 * m[y, x] + m[y, x + 1])
            fy = y + 0.5 * (m[y - 1, x] - m[y + 1, x]) / (m[y - 1, x] - 2 * m[y, x] + m[y + 1, x])
            np.testing.assert_allclose(uv_p[i, l], [fx, fy], atol=1e-12)
            assert peak[i, l] == m.max()
    uv_n, _ = heatmap_peaks(hm, "none")
    assert np.all(uv_n == np.round(uv_n))


def test_mediapipe_face_mesh_layout_is_described(tmp_path):
    """(1, 192, 192, 3) NHWC input, (1, 1, 1, 1404) xyz landmarks (corner pixels), (1, 1, 1, 1) logit."""
    rng = np.random.default_rng(0)
    pts = rng.uniform(20, 170, size=(468, 2))
    model = S.constant_model(pts, size=(192, 192), layout="NHWC", batch=1, presence=0.9)
    spec = S.detector_spec(name="face_mesh", count=468, size=(192, 192), layout="NHWC", first_frame="full_frame",
                           presence={"name": "face_score", "threshold": 0.5})
    m2, spec2 = S.relayout(model, spec, "xyz_4d_corner")
    assert spec2["outputs"]["landmarks"] == {"name": "lm_out", "frame": "crop_corner_pixels",
                                             "components": "xyz", "order": "interleaved"}
    det = Detector.load(S.save_detector(m2, spec2, tmp_path, "face_mesh"))
    shapes = {o.name: o.shape for o in det.session.get_outputs()}
    assert shapes == {"lm_out": [1, 1, 1, 1404], "presence_out": [1, 1, 1, 1]}
    crop = Crop(200.0, 150.0, 384.0, 0.0)
    r = det.run_crops([np.zeros((300, 400, 3), np.uint8)], [crop], [0])[0]
    # crop px p -> frame px: 2 frame px per input px, input centre 95.5 at the crop centre
    np.testing.assert_allclose(r.points, (pts - 95.5) * 2.0 + [200.0, 150.0], atol=1e-3)
    assert r.face_found and r.presence == pytest.approx(1 / (1 + np.exp(-4.0)), abs=1e-6)


def test_layout_errors_are_one_line(tmp_path):
    model, spec, _ = _v1(tmp_path)
    m2, spec2 = S.relayout(model, spec, "xyz_4d_corner")
    bad = json.loads(json.dumps(spec2))
    bad["outputs"]["landmarks"]["components"] = "xy"
    with pytest.raises(CaptureError) as e:
        Detector.load(S.save_detector(m2, bad, tmp_path / "a", "d"))
    msg = str(e.value)
    assert "\n" not in msg and "xy interleaved (6 values per crop)" in msg and "(N, 1, 1, 9)" in msg
    bad = json.loads(json.dumps(spec2))
    bad["outputs"]["landmarks"]["order"] = "diagonal"
    with pytest.raises(CaptureError, match="outputs.landmarks.order is \"diagonal\""):
        Detector.load(S.save_detector(m2, bad, tmp_path / "b", "d"))
    bad = json.loads(json.dumps(spec2))
    bad["version"] = 1
    with pytest.raises(CaptureError, match="unknown key 'outputs.landmarks.components'"):
        Detector.load(S.save_detector(m2, bad, tmp_path / "c", "d"))
    bad = json.loads(json.dumps(spec2))
    bad["outputs"]["presence"]["threshold"] = 2.0
    with pytest.raises(CaptureError, match=r"outputs.presence.threshold is 2.0; expected a number in \[0.0, 1.0\]"):
        Detector.load(S.save_detector(m2, bad, tmp_path / "e", "d"))
    mh, spech = S.relayout(model, spec, "heatmap")
    bad = json.loads(json.dumps(spech))
    bad["landmarks"]["count"] = 5
    bad["crop"]["align"] = None
    with pytest.raises(CaptureError) as e:
        Detector.load(S.save_detector(mh, bad, tmp_path / "f", "d"))
    assert "landmarks.count is 5 and outputs.landmarks is a heatmap (LHW)" in str(e.value)
    assert "(N, 5, H, W)" in str(e.value) and "(N, 3, 24, 24)" in str(e.value)


# ----------------------------------------------------------------------------------------------
# anchor face detectors

BLAZE = {"strides": [8, 16, 16, 16], "per_cell": 2, "offset": 0.5}


def test_blazeface_anchor_layout_matches_mediapipe():
    a = make_anchors((128, 128), AnchorSpec(strides=(8, 16, 16, 16), per_cell=(2, 2, 2, 2)))
    assert a.shape == (896, 4)
    # MediaPipe's SsdAnchorsCalculator: 16x16 cells x 2 at stride 8, then 8x8 cells x 6 (three stride-16 layers)
    for i, (row, col) in enumerate([(0, 0), (3, 7), (15, 15)]):
        for k in range(2):
            np.testing.assert_allclose(a[(row * 16 + col) * 2 + k], [(col + 0.5) / 16, (row + 0.5) / 16, 1, 1])
    for row, col in [(0, 0), (5, 2), (7, 7)]:
        for k in range(6):
            np.testing.assert_allclose(a[512 + (row * 8 + col) * 6 + k], [(col + 0.5) / 8, (row + 0.5) / 8, 1, 1])
    same = make_anchors((128, 128), AnchorSpec(strides=(8, 16), per_cell=(2, 6)))
    np.testing.assert_array_equal(a, same)
    assert anchor_counts((128, 128), AnchorSpec(strides=(8, 16, 16, 16), per_cell=(2, 2, 2, 2))) == [512, 384]


def _blaze_finder(tmp_path, raw, logits, nms_mode="weighted", per_cell=2):
    model = S.box_model(raw, logits.reshape(-1, 1), size=(128, 128), layout="NHWC", batch=1,
                        names=("regressors", "classificators"))
    spec = {"format": "capture-face-detector", "version": 2,
            "input": {"name": "image", "layout": "NHWC", "size": [128, 128], "color": "RGB", "dtype": "float32",
                      "scale": 1 / 127.5, "mean": 1.0, "std": 1.0},
            "anchors": {**BLAZE, "per_cell": per_cell},
            "outputs": {"boxes": {"name": "regressors", "encoding": "anchor_linear", "scale": 128},
                        "scores": {"name": "classificators", "kind": "logit", "threshold": 0.5}},
            "nms": {"iou": 0.3, "mode": nms_mode}}
    import onnx

    onnx.save(model, str(tmp_path / "blaze.onnx"))
    (tmp_path / "blaze.json").write_text(json.dumps(spec))
    return OnnxFaceFinder(tmp_path / "blaze.onnx")


def test_blazeface_finder_decodes_anchors_logits_and_nms(tmp_path):
    anchors = make_anchors((128, 128), AnchorSpec(strides=(8, 16), per_cell=(2, 6)))
    raw = np.zeros((896, 16), np.float32)
    logits = np.full(896, -8.0, np.float32)
    # face: unit box centre (0.45, 0.55), size 0.30 x 0.36, from stride-16 anchor at cell (4, 3)
    i = 512 + (4 * 8 + 3) * 6
    target = np.array([0.45, 0.55, 0.30, 0.36])
    raw[i, :4] = [(target[0] - anchors[i, 0]) * 128, (target[1] - anchors[i, 1]) * 128, target[2] * 128,
                  target[3] * 128]
    logits[i] = 3.0
    # a second, weaker detection of the same face, shifted by 0.02: suppressed (hard) or blended (weighted)
    j = i + 1
    raw[j, :4] = raw[i, :4] + [0.02 * 128, 0, 0, 0]
    logits[j] = 1.0
    # a separate weak face far away (kept after NMS, ranked second)
    m = (2 * 16 + 13) * 2
    raw[m, 2:4] = [0.1 * 128, 0.1 * 128]
    logits[m] = 0.5
    frame = np.zeros((240, 320, 3), np.uint8)
    # letterbox: 320 px -> 128 px, so 2.5 frame px per input px, input centre 63.5 at frame (159.5, 119.5)
    to_frame = lambda u, v: (159.5 + (u * 128 - 0.5 - 63.5) * 2.5, 119.5 + (v * 128 - 0.5 - 63.5) * 2.5)

    hard = _blaze_finder(tmp_path, raw, logits, "hard").find_all(frame)
    assert len(hard) == 2
    (box, score) = hard[0]
    x0, y0 = to_frame(target[0] - target[2] / 2, target[1] - target[3] / 2)
    x1, y1 = to_frame(target[0] + target[2] / 2, target[1] + target[3] / 2)
    np.testing.assert_allclose(box, [x0, y0, x1, y1], atol=1e-3)
    assert score == pytest.approx(1 / (1 + np.exp(-3.0)), abs=1e-6)
    s1, s2 = 1 / (1 + np.exp(-3.0)), 1 / (1 + np.exp(-1.0))
    weighted = _blaze_finder(tmp_path, raw, logits, "weighted").find_all(frame)
    shift = 0.02 * s2 / (s1 + s2)
    x0w, _ = to_frame(target[0] + shift - target[2] / 2, 0)
    assert len(weighted) == 2 and weighted[0][0][0] == pytest.approx(x0w, abs=1e-3)
    # find() takes the best face
    assert _blaze_finder(tmp_path, raw, logits, "hard").find(frame) == pytest.approx(box)


def test_anchor_count_mismatch_is_one_line(tmp_path):
    with pytest.raises(CaptureError) as e:
        _blaze_finder(tmp_path, np.zeros((896, 16)), np.zeros(896), per_cell=3)
    msg = str(e.value)
    assert "\n" not in msg
    assert "make 1344 anchors" in msg and "'regressors' should be (N, 1344, D) but it is (1, 896, 16)" in msg


SCRFD_STRIDES = [8, 16, 32]


def _scrfd_finder(tmp_path, boxes, scores, batched=False, names=None):
    """A finder on a model with SCRFD's outputs (score_8, score_16, score_32, bbox_8, ..., kps_8, ...) and the
    spec a user writes for it: anchors at the cell corners (offset 0), 2 per cell of the stride's side,
    distances in strides, probabilities, hard NMS; input RGB (x - 127.5) / 128 as InsightFace feeds it."""
    import onnx

    onnx.save(S.layered_box_model(boxes, scores, SCRFD_STRIDES, size=(128, 128), batched=batched),
              str(tmp_path / "scrfd.onnx"))
    spec = {"format": "capture-face-detector", "version": 2,
            "input": {"name": "image", "layout": "NCHW", "size": [128, 128], "color": "RGB", "dtype": "float32",
                      "mean": 127.5, "std": 128.0},
            "anchors": {"strides": SCRFD_STRIDES, "sizes": [[s, s] for s in SCRFD_STRIDES], "offset": 0.0},
            "outputs": {"boxes": {"name": names or [f"bbox_{s}" for s in SCRFD_STRIDES], "encoding": "anchor_distance"},
                        "scores": {"name": [f"score_{s}" for s in SCRFD_STRIDES], "kind": "probability",
                                   "threshold": 0.5}},
            "nms": {"iou": 0.4, "mode": "hard"}}
    (tmp_path / "scrfd.json").write_text(json.dumps(spec))
    return OnnxFaceFinder(tmp_path / "scrfd.onnx")


def _scrfd_reference(boxes, scores, threshold=0.5):
    """InsightFace's SCRFD decoding (``scrfd.py``: anchor centres ``np.mgrid[:h, :w][::-1] * stride``, each
    repeated per anchor, ``distance2bbox(centres, bbox_pred * stride)``), boxes in input px, best first."""
    out = []
    for s, b, sc in zip(SCRFD_STRIDES, boxes, scores):
        h = w = 128 // s
        centres = (np.stack(np.mgrid[:h, :w][::-1], axis=-1).astype(np.float32) * s).reshape(-1, 2)
        centres = np.stack([centres] * 2, axis=1).reshape(-1, 2)
        d = np.asarray(b) * s
        xyxy = np.stack([centres[:, 0] - d[:, 0], centres[:, 1] - d[:, 1], centres[:, 0] + d[:, 2],
                         centres[:, 1] + d[:, 3]], axis=-1)
        keep = np.asarray(sc).reshape(-1) >= threshold
        out += list(zip(xyxy[keep], np.asarray(sc).reshape(-1)[keep]))
    return sorted(out, key=lambda t: -t[1])


@pytest.mark.parametrize("batched", [False, True])
def test_scrfd_finder_decodes_per_stride_outputs_as_insightface_does(tmp_path, batched):
    """Two faces, one on a stride-16 anchor and one on a stride-32 anchor; everything else scores 0.01. The
    boxes are InsightFace's own decoding of the same outputs, in frame px: the frame is the input's size, so
    only the outer-edge convention moves them (an edge at input u sits at u - 0.5)."""
    counts = [(128 // s) ** 2 * 2 for s in SCRFD_STRIDES]
    boxes = [np.full((k, 4), 0.5, np.float32) for k in counts]
    scores = [np.full((k, 1), 0.01, np.float32) for k in counts]
    a = (3 * 8 + 5) * 2 + 1                  # stride 16: row 3, column 5, second anchor
    boxes[1][a] = [2.0, 1.5, 1.0, 2.5]
    scores[1][a] = 0.9
    b = (1 * 4 + 2) * 2                      # stride 32: row 1, column 2, first anchor
    boxes[2][b] = [0.5, 0.75, 0.5, 0.25]
    scores[2][b] = 0.6
    found = _scrfd_finder(tmp_path, boxes, scores, batched).find_all(np.zeros((128, 128, 3), np.uint8))
    ref = _scrfd_reference(boxes, scores)
    assert len(found) == len(ref) == 2
    for (box, score), (rbox, rscore) in zip(found, ref):
        np.testing.assert_allclose(box, rbox - 0.5, atol=1e-4)
        assert score == pytest.approx(float(rscore), abs=1e-6)
    np.testing.assert_allclose(ref[0][0], [80 - 32, 48 - 24, 80 + 16, 48 + 40])     # written out once


def test_scrfd_spec_and_model_mismatches_are_one_line(tmp_path):
    counts = [(128 // s) ** 2 * 2 for s in SCRFD_STRIDES]
    boxes = [np.zeros((k, 4), np.float32) for k in counts]
    scores = [np.zeros((k, 1), np.float32) for k in counts]
    with pytest.raises(CaptureError) as e:
        _scrfd_finder(tmp_path, boxes, scores, names=["bbox_8", "bbox_16"])
    assert "\n" not in str(e.value)
    assert "outputs.boxes.name is [\"bbox_8\", \"bbox_16\"]; expected a list of 3 output names" in str(e.value)
    with pytest.raises(CaptureError) as e:       # scores as one output beside boxes as a list
        parse_face_finder_spec({"format": "capture-face-detector", "version": 2,
                                "input": {"name": "image", "layout": "NCHW", "size": [128, 128], "color": "RGB",
                                          "dtype": "float32"},
                                "anchors": {"strides": [8], "per_cell": 2, "offset": 0.0},
                                "outputs": {"boxes": {"name": ["bbox_8"], "encoding": "anchor_distance"},
                                            "scores": {"name": "score_8", "kind": "probability", "threshold": 0.5}}})
    assert "outputs.scores.name is \"score_8\"; expected a list of 1 output names" in str(e.value)
    with pytest.raises(CaptureError) as e:       # the model made for another input size: 64 rows at stride 32
        _scrfd_finder(tmp_path, boxes[:2] + [np.zeros((64, 4))], scores[:2] + [np.zeros((64, 1))])
    msg = str(e.value)
    assert "\n" not in msg and "anchor layer 2 (stride 32, 2/cell) on a 128x128 input makes 32 anchors" in msg
    assert "'bbox_32'" in msg and "(64, 4)" in msg


def test_nms_hard_is_opencv_and_weighted_blends():
    boxes = np.array([[0, 0, 10, 10], [1, 0, 11, 10], [20, 20, 30, 30]], float)
    scores = np.array([0.9, 0.8, 0.7])
    b, s = nms(boxes, scores, 0.5, "hard")
    np.testing.assert_array_equal(b, boxes[[0, 2]])
    b, s = nms(boxes, scores, 0.5, "weighted")
    np.testing.assert_allclose(b[0], (0.9 * boxes[0] + 0.8 * boxes[1]) / 1.7)
    np.testing.assert_allclose(b[1], boxes[2])


def test_the_documented_corner_to_corner_example():
    """docs/detector_spec.md 'Which frame?': W = 192, crop 480 px at (640, 360), model value 96.0."""
    from capture.detector.crop import input_to_frame, output_to_input_px

    crop = Crop(640.0, 360.0, 480.0, 0.0)
    x = lambda m, frame: input_to_frame(output_to_input_px(np.array([[m, 95.5]]), frame, (192, 192)), crop,
                                        (192, 192))[0, 0]
    assert x(96.0, "crop_corner_pixels") == pytest.approx(640.0, abs=1e-9)
    assert x(96.0 / 192, "crop_unit") == pytest.approx(640.0, abs=1e-9)
    assert x(96.0, "crop_pixels") == pytest.approx(641.25, abs=1e-9)
    assert x(0.0, "crop_corner_pixels") == pytest.approx(400.0, abs=1e-9)
