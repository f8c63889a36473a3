"""Small ONNX models with known behaviour, built with ``onnx.helper`` (tests, benchmarks, examples).

* :func:`constant_model`: fixed landmarks (and optional confidence / presence) whatever the image; the
  exact full-frame mapping of known crop coordinates can be checked.
* :func:`centroid_model`: one landmark per colour channel at the intensity-weighted centroid of that
  channel, in crop pixels; presence = the brightest input value. A real function of the image.
* :func:`query_model`: a query detector whose output is the x, y of its template points (crop px).
* :func:`conv_model`: a few strided 3x3 convolutions, global pooling and a linear layer: the cost of a
  small real landmark network (for throughput figures); its landmarks barely depend on the image.
* :func:`box_model`: a face detector returning fixed boxes and scores.

:func:`detector_spec` makes a matching spec dict; :func:`save_detector` writes ``stem.onnx`` +
``stem.json``. Nothing here downloads anything.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Sequence

import numpy as np

OPSET = 17
IR_VERSION = 8


def _onnx():
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    return onnx, TensorProto, helper, numpy_helper


def _image_input(name, layout, size, channels, dtype, batch):
    _, TensorProto, helper, _ = _onnx()
    w, h = size
    shape = [batch if batch is not None else "N"] + ([channels, h, w] if layout == "NCHW" else [h, w, channels])
    et = TensorProto.FLOAT if dtype == "float32" else TensorProto.UINT8
    return helper.make_tensor_value_info(name, et, shape)


def _model(nodes, inputs, outputs, inits):
    onnx, _, helper, _ = _onnx()
    graph = helper.make_graph(nodes, "synthetic", inputs, outputs, initializer=inits)
    m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="capture")
    m.ir_version = IR_VERSION
    onnx.checker.check_model(m)
    return m


def _const(name, arr):
    _, _, _, numpy_helper = _onnx()
    return numpy_helper.from_array(np.asarray(arr), name)


def _zero_of_image(nodes, inits, image, dtype, out="zero"):
    """(N, 1, 1) float zero that depends on the image (so outputs carry the batch dimension)."""
    _, _, helper, _ = _onnx()
    src = image
    if dtype == "uint8":
        nodes.append(helper.make_node("Cast", [image], ["img_f"], to=1))
        src = "img_f"
    nodes.append(helper.make_node("ReduceMean", [src], ["img_mean"], axes=[1, 2, 3], keepdims=1))  # (N,1,1,1)
    inits.append(_const("zero_c", np.float32(0.0)))
    nodes.append(helper.make_node("Mul", ["img_mean", "zero_c"], ["img_zero4"]))
    inits.append(_const("sq_axes", np.array([3], np.int64)))
    nodes.append(helper.make_node("Squeeze", ["img_zero4", "sq_axes"], [out]))  # (N,1,1)


def constant_model(points: np.ndarray, *, size=(64, 64), layout="NCHW", channels=3, dtype="float32",
                   batch: int | None = None, confidence: np.ndarray | None = None, presence: float | None = None,
                   nan: bool = False, image="image", landmarks="landmarks", flat: bool = False):
    """Landmarks ``points`` (L, 2) for every crop; optional constant confidence (L,) and presence.

    ``flat``: the landmark output is (N, 2L) (x0, y0, x1, y1, ...) instead of (N, L, 2).
    """
    _, TensorProto, helper, _ = _onnx()
    pts = np.asarray(points, np.float32)[None]
    if nan:
        pts = pts.copy()
        pts[0, 0, 0] = np.nan
    nodes, inits = [], [_const("lm_const", pts)]
    _zero_of_image(nodes, inits, image, dtype)
    n = batch if batch is not None else "N"
    L = pts.shape[1]
    if flat:
        inits.append(_const("flat_shape", np.array([-1, 2 * L], np.int64)))
        nodes += [helper.make_node("Add", ["zero", "lm_const"], ["lm3"]),
                  helper.make_node("Reshape", ["lm3", "flat_shape"], [landmarks])]
        outputs = [helper.make_tensor_value_info(landmarks, TensorProto.FLOAT, [n, 2 * L])]
    else:
        nodes.append(helper.make_node("Add", ["zero", "lm_const"], [landmarks]))  # (N, L, 2)
        outputs = [helper.make_tensor_value_info(landmarks, TensorProto.FLOAT, [n, L, 2])]
    if confidence is not None:
        inits.append(_const("conf_const", np.asarray(confidence, np.float32)[None]))
        inits.append(_const("sq1", np.array([2], np.int64)))
        nodes.append(helper.make_node("Squeeze", ["zero", "sq1"], ["zero2"]))  # (N, 1)
        nodes.append(helper.make_node("Add", ["zero2", "conf_const"], ["confidence"]))
        outputs.append(helper.make_tensor_value_info("confidence", TensorProto.FLOAT, [n, L]))
    if presence is not None:
        inits.append(_const("pres_const", np.array([presence], np.float32)))
        inits.append(_const("rs_n", np.array([-1], np.int64)))
        nodes.append(helper.make_node("Reshape", ["zero", "rs_n"], ["zero1"]))  # (N,)
        nodes.append(helper.make_node("Add", ["zero1", "pres_const"], ["face_score"]))
        outputs.append(helper.make_tensor_value_info("face_score", TensorProto.FLOAT, [n]))
    return _model(nodes, [_image_input(image, layout, size, channels, dtype, batch)], outputs, inits)


def centroid_model(*, size=(64, 64), layout="NCHW", channels=3, batch: int | None = None,
                   with_presence=True, confidence: float | None = None):
    """Per-channel intensity centroid (crop px), (N, C, 2); presence = max input value, (N,)."""
    _, TensorProto, helper, _ = _onnx()
    w, h = size
    nodes, inits = [], []
    x = "image"
    if layout == "NHWC":
        nodes.append(helper.make_node("Transpose", ["image"], ["x_nchw"], perm=[0, 3, 1, 2]))
        x = "x_nchw"
    inits += [_const("gx", np.arange(w, dtype=np.float32).reshape(1, 1, 1, w)),
              _const("gy", np.arange(h, dtype=np.float32).reshape(1, 1, h, 1)),
              _const("axes23", np.array([2, 3], np.int64)), _const("eps", np.float32(1e-12)),
              _const("axm1", np.array([-1], np.int64))]
    nodes += [helper.make_node("ReduceSum", [x, "axes23"], ["s"], keepdims=0),
              helper.make_node("Add", ["s", "eps"], ["s_e"]),
              helper.make_node("Mul", [x, "gx"], ["xw"]),
              helper.make_node("Mul", [x, "gy"], ["yw"]),
              helper.make_node("ReduceSum", ["xw", "axes23"], ["sx"], keepdims=0),
              helper.make_node("ReduceSum", ["yw", "axes23"], ["sy"], keepdims=0),
              helper.make_node("Div", ["sx", "s_e"], ["cx"]),
              helper.make_node("Div", ["sy", "s_e"], ["cy"]),
              helper.make_node("Unsqueeze", ["cx", "axm1"], ["cx1"]),
              helper.make_node("Unsqueeze", ["cy", "axm1"], ["cy1"]),
              helper.make_node("Concat", ["cx1", "cy1"], ["landmarks"], axis=-1)]
    n = batch if batch is not None else "N"
    outputs = [helper.make_tensor_value_info("landmarks", TensorProto.FLOAT, [n, channels, 2])]
    if with_presence:
        nodes.append(helper.make_node("ReduceMax", [x], ["face_score"], axes=[1, 2, 3], keepdims=0))
        outputs.append(helper.make_tensor_value_info("face_score", TensorProto.FLOAT, [n]))
    if confidence is not None:
        inits.append(_const("conf_v", np.float32(confidence)))
        inits.append(_const("zero_s", np.float32(0.0)))
        nodes += [helper.make_node("Mul", ["s", "zero_s"], ["s0"]),
                  helper.make_node("Add", ["s0", "conf_v"], ["confidence"])]
        outputs.append(helper.make_tensor_value_info("confidence", TensorProto.FLOAT, [n, channels]))
    return _model(nodes, [_image_input("image", layout, size, channels, "float32", batch)], outputs, inits)


def query_model(count: int, *, size=(64, 64), batch: int | None = None):
    """Query detector: landmarks (N, L, 2) = x, y of the query points (N, L, 3), in crop px."""
    _, TensorProto, helper, _ = _onnx()
    nodes, inits = [], [_const("q_starts", np.array([0], np.int64)), _const("q_ends", np.array([2], np.int64)),
                        _const("q_axes", np.array([2], np.int64))]
    _zero_of_image(nodes, inits, "image", "float32")
    nodes += [helper.make_node("Slice", ["points", "q_starts", "q_ends", "q_axes"], ["q_xy"]),
              helper.make_node("Add", ["q_xy", "zero"], ["landmarks"])]
    n = batch if batch is not None else "N"
    inputs = [_image_input("image", "NCHW", size, 3, "float32", batch),
              helper.make_tensor_value_info("points", TensorProto.FLOAT, [n, count, 3])]
    outputs = [helper.make_tensor_value_info("landmarks", TensorProto.FLOAT, [n, count, 2])]
    return _model(nodes, inputs, outputs, inits)


def conv_model(*, size=(256, 256), count=68, widths: Sequence[int] = (16, 32, 64, 96, 128), seed=0,
               points: np.ndarray | None = None, repeats: int = 0):
    """Strided 3x3 conv + ReLU stack, global average pool, linear -> (N, L, 2) crop px.

    Each stage is a stride-2 convolution to ``widths[i]`` channels followed by ``repeats`` stride-1
    convolutions at that width (``widths=(32, 64, 128, 256), repeats=1`` costs ~1.7 GFLOP at 256x256).

    Landmarks = ``points`` (default a ring in the middle of the crop) + 1e-3 x the linear layer, so a
    tracked crop stays put while the cost is that of a small real network.
    """
    _, TensorProto, helper, _ = _onnx()
    rng = np.random.default_rng(seed)
    w, h = size
    nodes, inits = [], []
    prev, c_in = "image", 3
    layers = [(c, s) for c in widths for s in [2] + [1] * repeats]
    for i, (c, stride) in enumerate(layers):
        wt = (rng.standard_normal((c, c_in, 3, 3)) * np.sqrt(2.0 / (9 * c_in))).astype(np.float32)
        inits += [_const(f"w{i}", wt), _const(f"b{i}", np.zeros(c, np.float32))]
        nodes += [helper.make_node("Conv", [prev, f"w{i}", f"b{i}"], [f"c{i}"], kernel_shape=[3, 3],
                                   strides=[stride, stride], pads=[1, 1, 1, 1]),
                  helper.make_node("Relu", [f"c{i}"], [f"r{i}"])]
        prev, c_in = f"r{i}", c
    if points is None:
        t = np.linspace(0, 2 * np.pi, count, endpoint=False)
        points = np.stack([(w - 1) / 2 + 0.3 * w * np.cos(t), (h - 1) / 2 + 0.35 * h * np.sin(t)], axis=1)
    fc = (rng.standard_normal((c_in, count * 2)) * 1e-3).astype(np.float32)
    inits += [_const("fc", fc), _const("fc_b", np.asarray(points, np.float32).reshape(-1)),
              _const("shape", np.array([-1, count, 2], np.int64))]
    nodes += [helper.make_node("GlobalAveragePool", [prev], ["gap"]),
              helper.make_node("Flatten", ["gap"], ["flat"], axis=1),
              helper.make_node("Gemm", ["flat", "fc", "fc_b"], ["lin"]),
              helper.make_node("Reshape", ["lin", "shape"], ["landmarks"])]
    inputs = [_image_input("image", "NCHW", size, 3, "float32", None)]
    outputs = [helper.make_tensor_value_info("landmarks", TensorProto.FLOAT, ["N", count, 2])]
    return _model(nodes, inputs, outputs, inits)


def box_model(boxes: np.ndarray, scores: np.ndarray, *, size=(128, 96)):
    """Face detector with fixed outputs: boxes (N, K, 4), scores (N, K)."""
    _, TensorProto, helper, _ = _onnx()
    b = np.asarray(boxes, np.float32)[None]
    s = np.asarray(scores, np.float32)[None]
    nodes, inits = [], [_const("b_const", b), _const("s_const", s), _const("sq2", np.array([2], np.int64))]
    _zero_of_image(nodes, inits, "image", "float32")
    nodes += [helper.make_node("Add", ["zero", "b_const"], ["boxes"]),
              helper.make_node("Squeeze", ["zero", "sq2"], ["zero_n1"]),
              helper.make_node("Add", ["zero_n1", "s_const"], ["scores"])]
    k = b.shape[1]
    outputs = [helper.make_tensor_value_info("boxes", TensorProto.FLOAT, ["N", k, 4]),
               helper.make_tensor_value_info("scores", TensorProto.FLOAT, ["N", k])]
    return _model(nodes, [_image_input("image", "NCHW", size, 3, "float32", None)], outputs, inits)


def detector_spec(name: str = "synthetic", count: int = 3, *, size=(64, 64), layout="NCHW", color="RGB",
                  dtype="float32", scale=1 / 255, margin=0.25, align=None, first_frame="haar", track=True,
                  frame="crop_pixels", confidence=None, presence=None, kind="dense", query=None) -> dict:
    """A spec dict (format 1) for the synthetic models; ``confidence``/``presence`` are output dicts."""
    channels = 1 if color == "GRAY" else 3
    inp = {"name": "image", "layout": layout, "size": list(size), "color": color, "dtype": dtype}
    if dtype == "float32":
        inp.update(scale=scale, mean=[0.0] * channels, std=[1.0] * channels)
    outputs = {"landmarks": {"name": "landmarks", "frame": frame}}
    if confidence is not None:
        outputs["confidence"] = confidence
    if presence is not None:
        outputs["presence"] = presence
    return {"format": "capture-detector", "version": 1, "name": name, "kind": kind, "input": inp,
            "query": query,
            "crop": {"margin": margin, "align": align, "first_frame": first_frame, "track": track},
            "outputs": outputs, "landmarks": {"count": count}}


def save_detector(model, spec: dict, directory: str | Path, stem: str = "detector") -> Path:
    """Write ``stem.onnx`` and ``stem.json`` into ``directory``; returns the ONNX path."""
    import onnx

    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    onnx.save(model, str(d / f"{stem}.onnx"))
    (d / f"{stem}.json").write_text(json.dumps(spec, indent=2))
    return d / f"{stem}.onnx"
