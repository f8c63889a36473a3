"""Runtime: presence, confidence/sigma, query detectors, fixed batch sizes, ONNX face finder, tracking."""

from __future__ import annotations

import json

import numpy as np
import pytest

from capture.detector import Detector, TrackOptions, TrackState
from capture.detector import synthetic as S
from capture.detector.crop import Crop, input_to_frame
from capture.detector.finder import OnnxFaceFinder
from capture.io.errors import CaptureError
from tests.test_detector_crop import _blobs

SIZE = (64, 64)
PTS = np.array([[10.0, 20.0], [40.0, 30.0], [32.0, 50.0]])


def _centroid_detector(tmp_path, **kw):
    spec = S.detector_spec(size=(96, 96), first_frame="full_frame", margin=0.6,
                           presence={"name": "face_score", "threshold": 0.2}, **kw)
    return Detector.load(S.save_detector(S.centroid_model(size=(96, 96)), spec, tmp_path, "centroid"))


def test_no_face_frames_are_recorded_not_fitted(tmp_path):
    det = _centroid_detector(tmp_path)
    centres = np.array([[150.3, 120.8], [190.6, 140.2], [165.1, 165.7]])
    face = _blobs(288, 360, centres, [(0, 0, 255), (0, 255, 0), (255, 0, 0)])
    empty = np.zeros_like(face)
    res = det.detect([face, empty, face, face])
    assert [r.face_found for r in res] == [True, False, True, True]
    assert np.isnan(res[1].points).all() and res[1].presence == pytest.approx(0.0)
    np.testing.assert_allclose(res[2].points, centres, atol=0.05)
    # after the lost frame the track restarts from the finder (full frame letterbox), then refines
    assert res[2].crop != res[1].crop


def test_state_carries_the_track_between_calls(tmp_path):
    det = _centroid_detector(tmp_path)
    centres = np.array([[150.3, 120.8], [190.6, 140.2], [165.1, 165.7]])
    frames = [_blobs(288, 360, centres + 3 * t, [(0, 0, 255), (0, 255, 0), (255, 0, 0)]) for t in range(4)]
    whole = det.detect(frames)
    st = TrackState()
    parts = det.detect(frames[:2], st) + det.detect(frames[2:], st, frame_indices=[2, 3])
    for a, b in zip(whole, parts):
        np.testing.assert_array_equal(a.points, b.points)
        assert a.crop == b.crop
    for t, r in enumerate(whole):
        np.testing.assert_allclose(r.points, centres + 3 * t, atol=0.05)


def test_sigma_confidence_converted_and_kept_in_frame_px(tmp_path):
    sig = np.array([1.28, 0.0, 12.8])  # input px; 1.28 = 2 % of 64 -> weight 0.5
    spec = S.detector_spec(confidence={"name": "confidence", "kind": "sigma_px"})
    det = Detector.load(S.save_detector(S.constant_model(PTS, confidence=sig), spec, tmp_path))
    r = det.run_crops([np.zeros((300, 400, 3), np.uint8)], [Crop(200.0, 150.0, 128.0, 10.0)], [0])[0]
    np.testing.assert_allclose(r.sigma_px, sig * 2.0, rtol=1e-6)
    np.testing.assert_allclose(r.confidence, [0.5, 1.0, 1 / 101], rtol=1e-5)
    assert r.presence is None and r.face_found


def test_low_confidence_landmarks_do_not_steer_the_crop(tmp_path):
    pts = np.array([[10.0, 10.0], [50.0, 10.0], [30.0, 50.0], [63.0, 63.0]])
    spec = S.detector_spec(count=4, confidence={"name": "confidence", "kind": "probability"},
                           first_frame="full_frame")
    det = Detector.load(S.save_detector(S.constant_model(pts, confidence=[0.9, 0.9, 0.9, 0.1]), spec, tmp_path))
    det.options = TrackOptions(refine=False, smooth_centre=1.0, smooth_size=1.0)
    frame = np.zeros((200, 200, 3), np.uint8)
    res = det.detect([frame, frame])
    r0 = res[0]
    good = r0.points[:3]
    lo, hi = good.min(0) - 0.5, good.max(0) + 0.5
    assert res[1].crop[0] == pytest.approx((lo[0] + hi[0]) / 2)
    assert res[1].crop[2] == pytest.approx(max(hi - lo) * 1.5)


def test_query_detector(tmp_path):
    q = np.array([[5.0, 7.0, 100.0], [50.25, 12.5, -3.0], [31.5, 60.0, 0.0]], np.float32)
    spec = S.detector_spec(kind="query", query={"name": "points"})
    det = Detector.load(S.save_detector(S.query_model(3), spec, tmp_path))
    crop = Crop(200.0, 150.0, 123.0, 25.0)
    r = det.run_crops([np.zeros((300, 400, 3), np.uint8)], [crop], [0], query_points=q)[0]
    np.testing.assert_allclose(r.points, input_to_frame(q[:, :2], crop, SIZE), atol=1e-4)
    with pytest.raises(CaptureError, match="needs the actor's template points"):
        det.run_crops([np.zeros((300, 400, 3), np.uint8)], [crop], [0])
    with pytest.raises(CaptureError, match=r"takes 3 template points \(L, 3\)"):
        det.run_crops([np.zeros((300, 400, 3), np.uint8)], [crop], [0], query_points=q[:2])


def test_query_detector_in_half_precision(tmp_path):
    """A query model exported in float16 takes the template points in float16: they reach it rounded to
    float16 (the nearest of 2^-11 relative: 0.03 px at 60 px) and come back as the float32 twin's do."""
    q = np.array([[5.0, 7.0, 100.0], [50.25, 12.5, -3.0], [31.5, 60.1, 0.0]], np.float32)
    spec = S.detector_spec(kind="query", query={"name": "points"}, dtype="float16")
    det = Detector.load(S.save_detector(S.query_model(3, dtype="float16"), spec, tmp_path))
    crop = Crop(200.0, 150.0, 64.0, 0.0)
    r = det.run_crops([np.zeros((300, 400, 3), np.uint8)], [crop], [0], query_points=q)[0]
    np.testing.assert_allclose(r.points, input_to_frame(q[:, :2].astype(np.float16).astype(np.float64), crop, SIZE),
                               atol=1e-5)
    assert np.abs(r.points - input_to_frame(q[:, :2], crop, SIZE)).max() > 1e-3     # 60.1 is not a float16


@pytest.mark.parametrize("batch", [1, 4])
def test_fixed_batch_models(tmp_path, batch):
    spec = S.detector_spec(first_frame="full_frame", track=False)
    det = Detector.load(S.save_detector(S.constant_model(PTS, batch=batch), spec, tmp_path))
    assert det.fixed_batch == batch and det.batch_size == batch
    frames = [np.full((100, 120, 3), i, np.uint8) for i in range(6)]
    res = det.detect(frames)
    assert [r.frame_index for r in res] == list(range(6))
    assert det.model_calls == (6 if batch == 1 else 2)
    np.testing.assert_allclose(res[5].points, input_to_frame(PTS, Crop(*res[5].crop), SIZE), atol=1e-4)


def test_onnx_face_finder(tmp_path):
    boxes = np.array([[0.25, 0.25, 0.75, 0.75], [0.0, 0.0, 0.1, 0.1]])
    fspec = {"format": "capture-face-detector", "version": 1,
             "input": {"name": "image", "layout": "NCHW", "size": [128, 96], "color": "RGB", "dtype": "float32",
                       "scale": 1 / 255},
             "outputs": {"boxes": {"name": "boxes", "format": "xyxy", "frame": "crop_unit"},
                         "scores": {"name": "scores", "threshold": 0.5}}}
    S.save_detector(S.box_model(boxes, [0.9, 0.3]), fspec, tmp_path, "faces")
    finder = OnnxFaceFinder(tmp_path / "faces.onnx")
    frame = np.zeros((288, 360, 3), np.uint8)
    # letterbox: crop size 384 centred at (179.5, 143.5), 3 frame px per input px (hand computed)
    assert finder.find(frame) == pytest.approx((83.5, 71.5, 275.5, 215.5))
    # used from a detector spec by a relative path
    spec = S.detector_spec(first_frame="faces.onnx", track=False, margin=0.0)
    det = Detector.load(S.save_detector(S.constant_model(PTS), spec, tmp_path))
    r = det.detect([frame])[0]
    assert r.crop == pytest.approx((179.5, 143.5, 192.0, 0.0))
    # no box above the threshold: no face, model not run
    S.save_detector(S.box_model(boxes, [0.4, 0.3]), fspec, tmp_path, "faces")
    det = Detector.load(tmp_path / "detector.onnx")
    r = det.detect([frame])[0]
    assert not r.face_found and det.model_calls == 0 and np.isnan(r.points).all()
    fspec["outputs"]["scores"]["name"] = "score"
    (tmp_path / "faces.json").write_text(json.dumps(fspec))
    with pytest.raises(CaptureError, match="outputs.scores.name is 'score'"):
        Detector.load(tmp_path / "detector.onnx")


def test_detect_rejects_bad_frames(tmp_path):
    det = Detector.load(S.save_detector(S.constant_model(PTS), S.detector_spec(), tmp_path))
    with pytest.raises(CaptureError, match="BGR uint8"):
        det.detect([np.zeros((10, 10), np.float32)])
