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
    et = {"float32": TensorProto.FLOAT, "float16": TensorProto.FLOAT16, "uint8": TensorProto.UINT8}[dtype]
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
    if dtype != "float32":
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


def query_model(count: int, *, size=(64, 64), batch: int | None = None, dtype: str = "float32"):
    """Query detector: landmarks (N, L, 2) = x, y of the query points (N, L, 3), in crop px (float32 out;
    ``dtype`` float16: both inputs in half precision, as a model exported in it has them)."""
    _, TensorProto, helper, _ = _onnx()
    nodes, inits = [], [_const("q_starts", np.array([0], np.int64)), _const("q_ends", np.array([2], np.int64)),
                        _const("q_axes", np.array([2], np.int64))]
    _zero_of_image(nodes, inits, "image", dtype)
    points = "points"
    if dtype != "float32":
        nodes.append(helper.make_node("Cast", ["points"], ["points_f"], to=TensorProto.FLOAT))
        points = "points_f"
    nodes += [helper.make_node("Slice", [points, "q_starts", "q_ends", "q_axes"], ["q_xy"]),
              helper.make_node("Add", ["q_xy", "zero"], ["landmarks"])]
    n = batch if batch is not None else "N"
    q_type = TensorProto.FLOAT16 if dtype == "float16" else TensorProto.FLOAT
    inputs = [_image_input("image", "NCHW", size, 3, dtype, batch),
              helper.make_tensor_value_info("points", q_type, [n, count, 3])]
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


def box_model(boxes: np.ndarray, scores: np.ndarray, *, size=(128, 96), layout="NCHW", batch: int | None = None,
              names=("boxes", "scores")):
    """Face detector with fixed outputs: boxes (N, K, D) (D = 4, or more, e.g. BlazeFace's 16 regressors),
    scores (N, K) or (N, K, C) as given by ``scores`` (K,) or (K, C)."""
    _, TensorProto, helper, _ = _onnx()
    b = np.asarray(boxes, np.float32)[None]
    s = np.asarray(scores, np.float32)[None]
    nodes, inits = [], [_const("b_const", b), _const("s_const", s), _const("sq2", np.array([2], np.int64))]
    _zero_of_image(nodes, inits, "image", "float32")
    nodes.append(helper.make_node("Add", ["zero", "b_const"], [names[0]]))
    if s.ndim == 2:
        nodes += [helper.make_node("Squeeze", ["zero", "sq2"], ["zero_n1"]),
                  helper.make_node("Add", ["zero_n1", "s_const"], [names[1]])]
    else:
        nodes.append(helper.make_node("Add", ["zero", "s_const"], [names[1]]))
    k = b.shape[1]
    n = batch if batch is not None else "N"
    outputs = [helper.make_tensor_value_info(names[0], TensorProto.FLOAT, [n, k, b.shape[2]]),
               helper.make_tensor_value_info(names[1], TensorProto.FLOAT, [n] + list(s.shape[1:]))]
    return _model(nodes, [_image_input("image", layout, size, 3, "float32", batch)], outputs, inits)


def layered_box_model(boxes: list[np.ndarray], scores: list[np.ndarray], strides: list[int], *, size=(128, 128),
                      batched: bool = False):
    """A face detector exported as SCRFD is: for each stride ``s`` outputs ``score_s`` (K_s, 1) and ``bbox_s``
    (K_s, 4) (and ``kps_s`` (K_s, 10), zeros, which the finder does not read), fixed to the given arrays;
    ``batched``: (1, K_s, D) instead (SCRFD's batched export). The input is (1, 3, H, W) float32."""
    _, TensorProto, helper, _ = _onnx()
    nodes = [helper.make_node("ReduceMean", ["image"], ["img_mean"], axes=[0, 1, 2, 3], keepdims=0),   # a scalar
             helper.make_node("Mul", ["img_mean", "zero_c"], ["zero"])]
    inits = [_const("zero_c", np.float32(0.0))]
    outputs = []
    for kind, arrays in (("score", scores), ("bbox", boxes), ("kps", [np.zeros((len(b), 10)) for b in boxes])):
        for s, a in zip(strides, arrays):
            a = np.asarray(a, np.float32).reshape(len(a), -1)
            a = a[None] if batched else a
            name = f"{kind}_{s}"
            inits.append(_const(f"{name}_const", a))
            nodes.append(helper.make_node("Add", ["zero", f"{name}_const"], [name]))
            outputs.append(helper.make_tensor_value_info(name, TensorProto.FLOAT, list(a.shape)))
    return _model(nodes, [_image_input("image", "NCHW", size, 3, "float32", 1)], outputs, inits)


def detector_spec(name: str = "synthetic", count: int = 3, *, size=(64, 64), layout="NCHW", color="RGB",
                  dtype="float32", scale=1 / 255, margin=0.25, align=None, first_frame="haar", track=True,
                  frame="crop_pixels", confidence=None, presence=None, kind="dense", query=None) -> dict:
    """A spec dict (format 1) for the synthetic models; ``confidence``/``presence`` are output dicts."""
    channels = 1 if color == "GRAY" else 3
    inp = {"name": "image", "layout": layout, "size": list(size), "color": color, "dtype": dtype}
    if dtype != "uint8":
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


# ----------------------------------------------------------------------------------------------
# the same detector in the tensor layouts of spec version 2

LAYOUTS_V2 = ("xyz_4d_corner", "planar_unit", "planar_flat_xyz_signed", "heatmap", "heatmap_hwl_logit")
HEATMAP_STRIDE = 4
HEATMAP_SIGMA = 1.5   # heatmap px


def depth_of(xy: np.ndarray) -> np.ndarray:
    """The z that :func:`relayout` gives a landmark at crop px ``xy`` (*, 2): ``0.5 x - 0.25 y + 3``."""
    xy = np.asarray(xy, np.float64)
    return 0.5 * xy[..., 0] - 0.25 * xy[..., 1] + 3.0


def presence_logit(p):
    """The presence logit of :func:`relayout` for a format-1 presence score ``p``: ``10 (p - 0.5)``."""
    return 10.0 * (np.asarray(p, np.float64) - 0.5)


def relayout(model, spec: dict, layout: str):
    """A format-1 synthetic detector (landmarks (N, L, 2) crop px [, confidence (N, L) probability]
    [, face_score (N,)]) re-exported in a version-2 layout, with the matching version-2 spec.

    The new outputs are computed from the old ones by appended ONNX nodes, so the decoded landmarks
    must equal the format-1 ones. Layouts (:data:`LAYOUTS_V2`):

    * ``xyz_4d_corner``: MediaPipe face-mesh style: landmarks ``(N, 1, 1, 3L)`` interleaved x, y, z in
      ``crop_corner_pixels`` (z = :func:`depth_of`), presence ``(N, 1, 1, 1)`` logit
      (:func:`presence_logit`), confidence ``(N, 1, L)`` logit.
    * ``planar_unit``: ``(N, 2, L)`` planar in ``crop_unit``.
    * ``planar_flat_xyz_signed``: ``(N, 3L)`` planar x..., y..., z... in ``crop_signed``.
    * ``heatmap``: ``(N, L, H/4, W/4)`` Gaussian heatmaps (sigma 1.5 heatmap px), probability values.
    * ``heatmap_hwl_logit``: the same as ``(N, H/4, W/4, L)`` logits.
    """
    import copy

    onnx, TensorProto, helper, _ = _onnx()
    g = model.graph
    outs = {o.name: o for o in g.output}
    n_dim = outs["landmarks"].type.tensor_type.shape.dim[0]
    n = n_dim.dim_value if n_dim.dim_value > 0 else (n_dim.dim_param or "N")
    L = outs["landmarks"].type.tensor_type.shape.dim[1].dim_value
    w, h = spec["input"]["size"]
    nodes, inits, new_outputs = [], [], []
    c = lambda name, arr: inits.append(_const(name, np.asarray(arr)))
    node = lambda op, i, o, **kw: nodes.append(helper.make_node(op, i, o, **kw))
    new = copy.deepcopy(spec)
    new["version"] = 2
    out = new["outputs"]
    c("v2_half", np.float32(0.5))
    c("v2_ax2", np.array([2], np.int64))
    c("v2_s0", np.array([0], np.int64))
    c("v2_s1", np.array([1], np.int64))
    c("v2_s2", np.array([2], np.int64))
    node("Slice", ["landmarks", "v2_s0", "v2_s1", "v2_ax2"], ["v2_x"])   # (N, L, 1)
    node("Slice", ["landmarks", "v2_s1", "v2_s2", "v2_ax2"], ["v2_y"])

    def add_z():
        c("v2_zx", np.float32(0.5))
        c("v2_zy", np.float32(0.25))
        c("v2_z0", np.float32(3.0))
        node("Mul", ["v2_x", "v2_zx"], ["v2_zx_"])
        node("Mul", ["v2_y", "v2_zy"], ["v2_zy_"])
        node("Sub", ["v2_zx_", "v2_zy_"], ["v2_zd"])
        node("Add", ["v2_zd", "v2_z0"], ["v2_z"])

    if layout in ("xyz_4d_corner", "planar_unit", "planar_flat_xyz_signed"):
        if layout == "xyz_4d_corner":
            node("Add", ["landmarks", "v2_half"], ["v2_xy"])
            frame = "crop_corner_pixels"
        else:
            c("v2_wh", np.array([w, h], np.float32))
            node("Add", ["landmarks", "v2_half"], ["v2_xyh"])
            node("Div", ["v2_xyh", "v2_wh"], ["v2_unit"])
            if layout == "planar_unit":
                frame, xy = "crop_unit", "v2_unit"
            else:
                c("v2_two", np.float32(2.0))
                c("v2_one", np.float32(1.0))
                node("Mul", ["v2_unit", "v2_two"], ["v2_u2"])
                node("Sub", ["v2_u2", "v2_one"], ["v2_signed"])
                frame, xy = "crop_signed", "v2_signed"
            node("Identity", [xy], ["v2_xy"])
        comps = "xyz" if layout != "planar_unit" else "xy"
        if comps == "xyz":
            add_z()
            if layout == "planar_flat_xyz_signed":
                # z in output units: crop_signed length = input px / (W / 2)
                c("v2_zscale", np.float32(2.0 / w))
                node("Mul", ["v2_z", "v2_zscale"], ["v2_zo"])
            else:
                node("Identity", ["v2_z"], ["v2_zo"])
            node("Concat", ["v2_xy", "v2_zo"], ["v2_xyz"], axis=2)
            src = "v2_xyz"
        else:
            src = "v2_xy"
        k = len(comps)
        if layout == "xyz_4d_corner":
            c("v2_shape", np.array([-1, 1, 1, k * L], np.int64))
            node("Reshape", [src, "v2_shape"], ["lm_out"])
            shape, order = [n, 1, 1, k * L], "interleaved"
        else:
            node("Transpose", [src], ["v2_planar"], perm=[0, 2, 1])   # (N, C, L)
            order = "planar"
            if layout == "planar_unit":
                node("Identity", ["v2_planar"], ["lm_out"])
                shape = [n, k, L]
            else:
                c("v2_shape", np.array([-1, k * L], np.int64))
                node("Reshape", ["v2_planar", "v2_shape"], ["lm_out"])
                shape = [n, k * L]
        new_outputs.append(helper.make_tensor_value_info("lm_out", TensorProto.FLOAT, shape))
        out["landmarks"] = {"name": "lm_out", "frame": frame, "components": comps, "order": order}
    elif layout in ("heatmap", "heatmap_hwl_logit"):
        s = HEATMAP_STRIDE
        wh_, hh_ = w // s, h // s
        c("v2_stride", np.float32(s))
        c("v2_gx", np.arange(wh_, dtype=np.float32).reshape(1, 1, 1, wh_))
        c("v2_gy", np.arange(hh_, dtype=np.float32).reshape(1, 1, hh_, 1))
        c("v2_ax3", np.array([3], np.int64))
        c("v2_k", np.float32(-1.0 / (2 * HEATMAP_SIGMA ** 2)))
        for a in ("x", "y"):   # heatmap px u = (x + 0.5) / s - 0.5
            node("Add", [f"v2_{a}", "v2_half"], [f"v2_{a}h"])
            node("Div", [f"v2_{a}h", "v2_stride"], [f"v2_{a}s"])
            node("Sub", [f"v2_{a}s", "v2_half"], [f"v2_{a}u"])
            node("Unsqueeze", [f"v2_{a}u", "v2_ax3"], [f"v2_{a}u4"])   # (N, L, 1, 1)
            node("Sub", [f"v2_g{a}", f"v2_{a}u4"], [f"v2_d{a}"])
            node("Mul", [f"v2_d{a}", f"v2_d{a}"], [f"v2_d{a}2"])
        node("Add", ["v2_dx2", "v2_dy2"], ["v2_e"])        # (N, L, Hh, Wh)
        node("Mul", ["v2_e", "v2_k"], ["v2_loggauss"])
        node("Exp", ["v2_loggauss"], ["v2_hm"])
        hm_spec: dict = {}
        if layout == "heatmap":
            node("Identity", ["v2_hm"], ["lm_out"])
            shape = [n, L, hh_, wh_]
        else:
            # logit = log g - log(1 - g), with g kept below 1 so that it stays finite
            c("v2_gmax", np.float32(1 - 1e-6))
            c("v2_gmin", np.float32(0.0))
            c("v2_one_", np.float32(1.0))
            node("Clip", ["v2_hm", "v2_gmin", "v2_gmax"], ["v2_hmc"])
            node("Sub", ["v2_one_", "v2_hmc"], ["v2_1mg"])
            node("Log", ["v2_1mg"], ["v2_l1mg"])
            node("Sub", ["v2_loggauss", "v2_l1mg"], ["v2_logit"])
            node("Transpose", ["v2_logit"], ["lm_out"], perm=[0, 2, 3, 1])
            shape = [n, hh_, wh_, L]
            hm_spec = {"layout": "HWL", "values": "logit"}
        new_outputs.append(helper.make_tensor_value_info("lm_out", TensorProto.FLOAT, shape))
        out["landmarks"] = {"name": "lm_out", "kind": "heatmap", **({"heatmap": hm_spec} if hm_spec else {})}
    else:
        raise ValueError(f"unknown layout {layout!r}; one of {LAYOUTS_V2}")

    if "confidence" in outs and layout == "xyz_4d_corner":
        c("v2_cone", np.float32(1.0))
        node("Log", ["confidence"], ["v2_lc"])
        node("Sub", ["v2_cone", "confidence"], ["v2_1mc"])
        node("Log", ["v2_1mc"], ["v2_l1mc"])
        node("Sub", ["v2_lc", "v2_l1mc"], ["v2_clogit"])
        c("v2_cshape", np.array([-1, 1, L], np.int64))
        node("Reshape", ["v2_clogit", "v2_cshape"], ["conf_out"])
        new_outputs.append(helper.make_tensor_value_info("conf_out", TensorProto.FLOAT, [n, 1, L]))
        out["confidence"] = {"name": "conf_out", "kind": "logit"}
    elif "confidence" in outs:
        new_outputs.append(outs["confidence"])
    if "face_score" in outs and "presence" in spec["outputs"]:
        c("v2_ten", np.float32(10.0))
        node("Sub", ["face_score", "v2_half"], ["v2_pc"])
        node("Mul", ["v2_pc", "v2_ten"], ["v2_plogit"])
        c("v2_pshape", np.array([-1, 1, 1, 1], np.int64))
        node("Reshape", ["v2_plogit", "v2_pshape"], ["presence_out"])
        new_outputs.append(helper.make_tensor_value_info("presence_out", TensorProto.FLOAT, [n, 1, 1, 1]))
        thr = float(1.0 / (1.0 + np.exp(-presence_logit(spec["outputs"]["presence"]["threshold"]))))
        out["presence"] = {"name": "presence_out", "kind": "logit", "threshold": thr}
    graph = helper.make_graph(list(g.node) + nodes, "synthetic_v2", list(g.input), new_outputs,
                              initializer=list(g.initializer) + inits)
    m = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], producer_name="capture")
    m.ir_version = IR_VERSION
    onnx.checker.check_model(m)
    return m, new
