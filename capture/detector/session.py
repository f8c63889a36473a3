"""ONNX Runtime sessions and the check of a spec against the model's declared inputs and outputs.

:func:`open_session` loads a model on the CPU with a fixed number of threads. :func:`check_image_input`
and friends compare the declared shapes and element types with the spec and raise one line that names
the spec field, the expected and the found value. Dimensions that the model leaves symbolic or
unknown ("dynamic") match anything.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from capture.detector.spec import InputSpec
from capture.io.errors import CaptureError

ORT_TYPES = {"tensor(float)": "float32", "tensor(uint8)": "uint8", "tensor(double)": "float64",
             "tensor(float16)": "float16", "tensor(int64)": "int64", "tensor(int32)": "int32"}
FLOAT_OUTPUTS = ("float32", "float64", "float16")


def open_session(onnx_path: Path, threads: int):
    """An onnxruntime CPU session with ``threads`` intra-op threads (not spinning between calls).

    A one-line error if the file is missing or onnxruntime cannot load it.
    """
    import onnxruntime as ort

    if not onnx_path.is_file():
        raise CaptureError(f"detector model {onnx_path} does not exist; check the --detector path")
    opts = ort.SessionOptions()
    opts.intra_op_num_threads = max(1, int(threads))
    opts.inter_op_num_threads = 1
    opts.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    opts.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    opts.log_severity_level = 3
    # Worker threads that spin between calls take the CPU from cropping, decoding and other processes;
    # on 2 shared cores not spinning was ~3x faster at batch 1 (benchmarks/bench_detector.py).
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    try:
        return ort.InferenceSession(str(onnx_path), sess_options=opts, providers=["CPUExecutionProvider"])
    except Exception as exc:  # onnxruntime raises its own exception types for bad files
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CaptureError(f"cannot load detector model {onnx_path.name}: {msg[:200]}; "
                           f"check that it is a valid ONNX file") from None


def _dim(d: Any) -> int | None:
    return d if isinstance(d, int) and d > 0 else None


def fmt_shape(shape: Sequence[Any]) -> str:
    return "(" + ", ".join(str(d) if isinstance(d, int) and d > 0 else (str(d) if d else "?") for d in shape) + ")"


@dataclass(frozen=True)
class Port:
    """A declared model input or output: name, shape (None = dynamic) and element type."""

    name: str
    shape: tuple[int | None, ...]
    raw_shape: tuple[Any, ...]
    dtype: str


def ports(args) -> dict[str, Port]:
    return {a.name: Port(a.name, tuple(_dim(d) for d in a.shape), tuple(a.shape),
                         ORT_TYPES.get(a.type, a.type)) for a in args}


class ModelChecker:
    """Checks declared ports against a spec; errors start with ``detector spec <file>:``."""

    def __init__(self, spec_label: str, model_label: str, session):
        self.spec_label = spec_label
        self.model_label = model_label
        self.inputs = ports(session.get_inputs())
        self.outputs = ports(session.get_outputs())

    def fail(self, msg: str) -> None:
        raise CaptureError(f"detector spec {self.spec_label}: {msg}")

    def input(self, field: str, name: str) -> Port:
        if name not in self.inputs:
            self.fail(f"{field} is '{name}' but {self.model_label} has no such input "
                      f"(its inputs: {', '.join(self.inputs)})")
        return self.inputs[name]

    def output(self, field: str, name: str) -> Port:
        if name not in self.outputs:
            self.fail(f"{field} is '{name}' but {self.model_label} has no such output "
                      f"(its outputs: {', '.join(self.outputs)})")
        return self.outputs[name]

    def only_inputs(self, names: Sequence[str]) -> None:
        extra = [n for n in self.inputs if n not in names]
        if extra:
            self.fail(f"{self.model_label} has inputs the spec does not feed: {', '.join(extra)} "
                      f"(the spec feeds {', '.join(names)})")

    def shape(self, what: str, port: Port, expected: Sequence[int | str], why: str) -> None:
        """``expected``: ints must match static dims; strings are names of free dimensions."""
        if len(port.shape) != len(expected) or any(
                isinstance(e, int) and d is not None and d != e for d, e in zip(port.shape, expected)):
            self.fail(f"{why}, so the model {what} '{port.name}' should be {fmt_shape(expected)} "
                      f"but it is {fmt_shape(port.raw_shape)}")

    def float_output(self, field: str, port: Port) -> None:
        if port.dtype not in FLOAT_OUTPUTS:
            self.fail(f"{field}: the model output '{port.name}' should be a float tensor but it is {port.dtype}")


def check_image_input(chk: ModelChecker, inp: InputSpec, field: str = "input") -> Port:
    """Check the image input: name, rank and layout, static sizes, channel count and dtype."""
    port = chk.input(f"{field}.name", inp.name)
    if port.dtype != inp.dtype:
        chk.fail(f"{field}.dtype is {inp.dtype} but the model input '{inp.name}' is {port.dtype}")
    if len(port.shape) != 4:
        chk.fail(f"{field}.layout says {inp.layout}, so the model input '{inp.name}' should have 4 "
                 f"dimensions {fmt_shape(inp.expected_shape())} but it is {fmt_shape(port.raw_shape)}")
    n, *rest = port.shape
    exp = inp.expected_shape(n)
    c_axis = 1 if inp.layout == "NCHW" else 3
    hw_axes = (2, 3) if inp.layout == "NCHW" else (1, 2)
    bad_c = port.shape[c_axis] is not None and port.shape[c_axis] != inp.channels
    bad_hw = any(port.shape[a] is not None and port.shape[a] != exp[a] for a in hw_axes)
    if bad_c or bad_hw:
        # Name the field that most likely is wrong: layout if the other layout fits, else color/size.
        other = "NHWC" if inp.layout == "NCHW" else "NCHW"
        other_exp = InputSpec(inp.name, other, inp.size, inp.color, inp.dtype, inp.scale, inp.mean,
                              inp.std).expected_shape(n)
        fits_other = all(d is None or d == e for d, e in zip(port.shape[1:], other_exp[1:]))
        shown = fmt_shape(inp.expected_shape())
        found = fmt_shape(port.raw_shape)
        if fits_other:
            chk.fail(f"{field}.layout says {inp.layout}, so the model input '{inp.name}' should be {shown} "
                     f"but it is {found}")
        if bad_c:
            chk.fail(f"{field}.color is {inp.color} ({inp.channels} channel{'s' if inp.channels > 1 else ''}), "
                     f"so the model input '{inp.name}' should be {shown} but it is {found}")
        chk.fail(f"{field}.size is [{inp.width}, {inp.height}] (width, height), so the model input "
                 f"'{inp.name}' should be {shown} but it is {found}")
    return port


def batch_capacity(port: Port) -> int | None:
    """The model's fixed batch size, or None when the batch dimension is dynamic."""
    return port.shape[0]


def check_finite(label: str, name: str, arr: np.ndarray, frames: Sequence[int] | None = None) -> None:
    """A one-line error naming the output when a model returns NaN or infinity."""
    bad = ~np.isfinite(arr)
    if bad.any():
        n = int(bad.reshape(bad.shape[0], -1).any(axis=1).sum()) if arr.ndim else 1
        where = ""
        if frames is not None and arr.ndim:
            first = int(np.argmax(bad.reshape(bad.shape[0], -1).any(axis=1)))
            if first < len(frames):
                where = f" (first at frame {frames[first]})"
        raise CaptureError(f"detector model {label} returned NaN or infinite values in output '{name}' for "
                           f"{n} of {arr.shape[0] if arr.ndim else 1} crops{where}; the model is broken or "
                           f"its input normalisation (input.scale/mean/std) is wrong")
