"""Detector spec validation: each wrong field gives its own one-line error naming field, expected, found."""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from capture.detector import Detector
from capture.detector import synthetic as S
from capture.detector.crop import Crop
from capture.detector.spec import load_face_finder_spec, parse_detector_spec
from capture.io.errors import CaptureError

PTS = np.array([[10.0, 20.0], [40.0, 30.0], [32.0, 50.0]])


def _load(tmp_path, model, spec, stem="face"):
    onnx_path = S.save_detector(model, spec, tmp_path, stem)
    return Detector.load(onnx_path)


def _error(tmp_path, model, spec) -> str:
    with pytest.raises(CaptureError) as e:
        _load(tmp_path, model, spec)
    msg = str(e.value)
    assert "\n" not in msg
    return msg


def test_valid_spec_loads(tmp_path):
    det = _load(tmp_path, S.constant_model(PTS), S.detector_spec())
    assert det.name == "synthetic" and det.count == 3
    assert det.fixed_batch is None and det.batch_size == 4


def test_layout_mismatch_names_expected_and_found_shape(tmp_path):
    model = S.constant_model(PTS, size=(256, 256), layout="NHWC", batch=1)
    msg = _error(tmp_path, model, S.detector_spec(size=(256, 256), layout="NCHW"))
    assert msg == ("detector spec face.json: input.layout says NCHW, so the model input 'image' should be "
                   "(N, 3, 256, 256) but it is (1, 256, 256, 3)")


def test_size_mismatch(tmp_path):
    msg = _error(tmp_path, S.constant_model(PTS, size=(64, 64)), S.detector_spec(size=(128, 64)))
    assert "input.size is [128, 64]" in msg and "(N, 3, 64, 128)" in msg and "(N, 3, 64, 64)" in msg


def test_channel_count_vs_colour(tmp_path):
    msg = _error(tmp_path, S.constant_model(PTS, channels=3), S.detector_spec(color="GRAY"))
    assert "input.color is GRAY (1 channel)" in msg and "(N, 1, 64, 64)" in msg and "(N, 3, 64, 64)" in msg


def test_colour_value_not_allowed(tmp_path):
    spec = S.detector_spec()
    spec["input"]["color"] = "RGBA"
    msg = _error(tmp_path, S.constant_model(PTS), spec)
    assert "input.color is \"RGBA\"" in msg and "'RGB' or 'BGR' or 'GRAY'" in msg


def test_dtype_mismatch(tmp_path):
    msg = _error(tmp_path, S.constant_model(PTS, dtype="uint8"), S.detector_spec())
    assert msg == "detector spec face.json: input.dtype is float32 but the model input 'image' is uint8"


def test_uint8_model_loads_and_runs(tmp_path):
    det = _load(tmp_path, S.constant_model(PTS, dtype="uint8"), S.detector_spec(dtype="uint8"))
    r = det.run_crops([np.zeros((50, 60, 3), np.uint8)], [Crop(30.0, 25.0, 64.0, 0.0)], [0])
    np.testing.assert_allclose(r[0].points, PTS - 31.5 + [30.0, 25.0], atol=1e-5)
    spec = S.detector_spec(dtype="uint8")
    spec["input"]["scale"] = 0.5
    msg = _error(tmp_path, S.constant_model(PTS, dtype="uint8"), spec)
    assert "input.dtype is \"uint8\"; expected float32 or float16 when scale/mean/std are given" in msg


def _mean_shift_model(dtype: str):
    """Landmarks PTS + the mean of the normalised crop (N, 3, 64, 64) of ``dtype``, in float32: what the model
    returns depends on every input value, as a real network's does."""
    from onnx import TensorProto, helper, numpy_helper

    et = {"float32": TensorProto.FLOAT, "float16": TensorProto.FLOAT16}[dtype]
    nodes = [helper.make_node("Cast", ["image"], ["f"], to=TensorProto.FLOAT),
             helper.make_node("ReduceMean", ["f"], ["m"], axes=[1, 2, 3], keepdims=1),     # (N, 1, 1, 1)
             helper.make_node("Squeeze", ["m", "ax"], ["m3"]),                             # (N, 1, 1)
             helper.make_node("Add", ["m3", "pts"], ["landmarks"])]
    inits = [numpy_helper.from_array(np.array([3], np.int64), "ax"),
             numpy_helper.from_array(PTS[None].astype(np.float32), "pts")]
    graph = helper.make_graph(nodes, "mean_shift", [helper.make_tensor_value_info("image", et, ["N", 3, 64, 64])],
                              [helper.make_tensor_value_info("landmarks", TensorProto.FLOAT, ["N", 3, 2])], inits)
    m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 13)])
    m.ir_version = 8
    return m


def test_float16_model_loads_and_runs_like_its_float32_twin(tmp_path):
    """A model exported in half precision (float16 image input): the crop is normalised as for float32 and
    rounded once. Its landmarks equal the float32 twin's within float16 rounding of the input (a mean of
    values <= 1 rounded at 2^-11 relative: 5e-4 px), and they see the normalisation: a crop of value 200
    shifts them by 200 / 255 px."""
    frame = np.full((100, 120, 3), 200, np.uint8)
    crop = Crop(60.0, 50.0, 64.0, 0.0)                  # inside the frame: every crop pixel is 200
    got = {}
    for dtype in ("float32", "float16"):
        det = _load(tmp_path / dtype, _mean_shift_model(dtype), S.detector_spec(dtype=dtype))
        got[dtype] = det.run_crops([frame], [crop], [0])[0].points
    np.testing.assert_allclose(got["float16"], got["float32"], atol=5e-4)
    np.testing.assert_allclose(got["float16"], PTS - 31.5 + [60.0, 50.0] + 200 / 255, atol=5e-4)
    msg = _error(tmp_path / "mismatch", _mean_shift_model("float16"), S.detector_spec())
    assert msg == "detector spec face.json: input.dtype is float32 but the model input 'image' is float16"


def test_input_name_mismatch(tmp_path):
    spec = S.detector_spec()
    spec["input"]["name"] = "pixels"
    msg = _error(tmp_path, S.constant_model(PTS), spec)
    assert "input.name is 'pixels'" in msg and "its inputs: image" in msg


def test_output_name_mismatch(tmp_path):
    spec = S.detector_spec()
    spec["outputs"]["landmarks"]["name"] = "points2d"
    msg = _error(tmp_path, S.constant_model(PTS), spec)
    assert "outputs.landmarks.name is 'points2d'" in msg and "its outputs: landmarks" in msg


def test_landmark_count_mismatch(tmp_path):
    msg = _error(tmp_path, S.constant_model(PTS), S.detector_spec(count=68))
    assert "landmarks.count is 68" in msg and "(N, 68, 2)" in msg and "(N, 3, 2)" in msg


def test_flat_landmark_output(tmp_path):
    det = _load(tmp_path, S.constant_model(PTS, flat=True), S.detector_spec())
    r = det.run_crops([np.zeros((50, 60, 3), np.uint8)], [Crop(31.5, 31.5, 64.0, 0.0)], [0])[0]
    np.testing.assert_allclose(r.points, PTS, atol=1e-5)
    msg = _error(tmp_path, S.constant_model(PTS, flat=True), S.detector_spec(count=4))
    assert "landmarks.count is 4" in msg and "should be (N, 8)" in msg and "it is (N, 6)" in msg


def test_coordinate_frame_value(tmp_path):
    msg = _error(tmp_path, S.constant_model(PTS), S.detector_spec(frame="normalized"))
    assert "outputs.landmarks.frame is \"normalized\"" in msg and "'crop_unit'" in msg


def test_unknown_key_top_level_and_nested(tmp_path):
    spec = S.detector_spec()
    spec["colour"] = "RGB"
    msg = _error(tmp_path, S.constant_model(PTS), spec)
    assert "unknown key 'colour'" in msg
    spec = S.detector_spec()
    spec["crop"]["margins"] = 0.2
    msg = _error(tmp_path, S.constant_model(PTS), spec)
    assert "unknown key 'crop.margins'" in msg and "margin" in msg


def test_types_and_ranges(tmp_path):
    cases = [
        (("crop", "margin"), "0.2", "crop.margin is \"0.2\"; expected a number"),
        (("crop", "margin"), -1, "crop.margin is -1; expected a number in [0.0, 5.0]"),
        (("crop", "track"), 1, "crop.track is 1; expected true or false"),
        (("input", "size"), [64], "input.size is [64]; expected [width, height]"),
        (("input", "mean"), [0.0, 0.0], "input.mean is [0.0, 0.0]; expected a list of 3 numbers"),
        (("input", "std"), [1.0, 0.0, 1.0], "input.std is [1.0, 0.0, 1.0]; expected non-zero numbers"),
        (("landmarks", "count"), 0, "landmarks.count is 0; expected an integer >= 1"),
        (("version",), 3, "version is 3; expected 1 or 2"),
        (("kind",), "sparse", "kind is \"sparse\"; expected 'dense' or 'query'"),
        (("crop", "first_frame"), "mtcnn", "crop.first_frame is \"mtcnn\""),
        (("crop", "align"), {"left": 0, "right": 7}, "crop.align.right is 7; expected a landmark index below"),
    ]
    for path, value, expected in cases:
        spec = copy.deepcopy(S.detector_spec())
        obj = spec
        for k in path[:-1]:
            obj = obj[k]
        obj[path[-1]] = value
        msg = _error(tmp_path, S.constant_model(PTS), spec)
        assert expected in msg, (path, msg)


def test_missing_spec_and_bad_json(tmp_path):
    import onnx

    onnx.save(S.constant_model(PTS), str(tmp_path / "lonely.onnx"))
    with pytest.raises(CaptureError, match="lonely.json does not exist"):
        Detector.load(tmp_path / "lonely.onnx")
    (tmp_path / "lonely.json").write_text("{not json")
    with pytest.raises(CaptureError, match="not valid JSON"):
        Detector.load(tmp_path / "lonely.onnx")
    with pytest.raises(CaptureError, match="does not exist"):
        Detector.load(tmp_path / "nothing.onnx")


def test_explicit_spec_path(tmp_path):
    import onnx

    onnx.save(S.constant_model(PTS), str(tmp_path / "m.onnx"))
    (tmp_path / "other.json").write_text(json.dumps(S.detector_spec(name="other")))
    assert Detector.load(tmp_path / "m.onnx", tmp_path / "other.json").name == "other"


def test_confidence_and_presence_outputs_checked(tmp_path):
    conf = {"name": "confidence", "kind": "probability"}
    msg = _error(tmp_path, S.constant_model(PTS), S.detector_spec(confidence=conf))
    assert "outputs.confidence.name is 'confidence'" in msg
    msg = _error(tmp_path, S.constant_model(PTS, confidence=[1, 1, 1]),
                 S.detector_spec(confidence={"name": "confidence", "kind": "variance"}))
    assert "outputs.confidence.kind is \"variance\"" in msg
    det = _load(tmp_path, S.constant_model(PTS, confidence=[1, 1, 1], presence=1.0),
                S.detector_spec(confidence=conf, presence={"name": "face_score", "threshold": 0.5}))
    assert det.spec.presence.threshold == 0.5


def test_query_spec_needs_query_input(tmp_path):
    msg = _error(tmp_path, S.constant_model(PTS), S.detector_spec(kind="query", query={"name": "points"}))
    assert "query.name is 'points'" in msg and "no such input" in msg
    msg = _error(tmp_path, S.query_model(3), S.detector_spec())
    assert "inputs the spec does not feed: points" in msg
    msg = _error(tmp_path, S.query_model(5), S.detector_spec(kind="query", query={"name": "points"}))
    assert "landmarks.count is 3" in msg


def test_nan_output_is_a_clear_error(tmp_path):
    det = _load(tmp_path, S.constant_model(PTS, nan=True), S.detector_spec(first_frame="full_frame"))
    frames = [np.zeros((48, 64, 3), np.uint8)] * 2
    with pytest.raises(CaptureError) as e:
        det.detect(frames, frame_indices=[5, 6])
    msg = str(e.value)
    assert "output 'landmarks'" in msg and "NaN or infinite" in msg and "frame 5" in msg


def test_face_finder_spec_strict(tmp_path):
    spec = {"format": "capture-face-detector", "version": 1,
            "input": {"name": "image", "layout": "NCHW", "size": [128, 96], "color": "RGB", "dtype": "float32"},
            "outputs": {"boxes": {"name": "boxes", "format": "xyxy", "frame": "crop_unit"},
                        "scores": {"name": "scores", "threshold": 0.5}}}
    (tmp_path / "fd.json").write_text(json.dumps(spec))
    assert load_face_finder_spec(tmp_path / "fd.json").boxes.format == "xyxy"
    spec["outputs"]["boxes"]["format"] = "ltrb"
    (tmp_path / "fd.json").write_text(json.dumps(spec))
    with pytest.raises(CaptureError, match="outputs.boxes.format is \"ltrb\""):
        load_face_finder_spec(tmp_path / "fd.json")


def test_first_frame_onnx_path_must_exist(tmp_path):
    with pytest.raises(CaptureError, match="crop.first_frame names faces.onnx"):
        parse_detector_spec(S.detector_spec(first_frame="faces.onnx"), tmp_path / "x.json")
