"""Detector specs: the JSON that says how to feed a user's ONNX landmark detector and read it.

Two schemas live here (both documented in ``docs/detector_spec.md``; version 1 files keep working,
version 2 adds the tensor-layout fields: landmark components and order, heatmaps, logits, anchors):

* :class:`DetectorSpec` (``"format": "capture-detector"``): a landmark detector, ``dense`` or ``query``.
* :class:`FaceFinderSpec` (``"format": "capture-face-detector"``): an optional face-box detector used
  by ``crop.first_frame`` to find the face in the first frame and after it is lost.

Parsing is strict: unknown keys, wrong types and values outside the allowed set raise a one-line
:class:`~capture.io.errors.CaptureError` naming the file, the field, what was expected and what was
found. Checking a spec against the model's declared inputs and outputs is in :mod:`.model_check`.
"""

from __future__ import annotations

import hashlib
import json
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from capture.io.errors import CaptureError

DETECTOR_FORMAT = "capture-detector"
FACE_FINDER_FORMAT = "capture-face-detector"
VERSION = 2                 # the newest format this build writes in examples
VERSIONS = (1, 2)           # the formats it reads

LAYOUTS = ("NCHW", "NHWC")
COLORS = {"RGB": 3, "BGR": 3, "GRAY": 1}
DTYPES = ("float32", "float16", "uint8")
FRAMES = ("crop_pixels", "crop_corner_pixels", "crop_unit", "crop_signed")
CONFIDENCE_KINDS = ("probability", "sigma_px")
CONFIDENCE_KINDS_V2 = ("probability", "logit", "sigma_px")
SCORE_KINDS = ("probability", "logit")    # version 2: presence / face scores (v1: raw score)
LANDMARK_KINDS = ("coordinates", "heatmap")
COMPONENTS = {"xy": 2, "xyz": 3}
ORDERS = ("interleaved", "planar")
HEATMAP_LAYOUTS = ("LHW", "HWL")
HEATMAP_REFINES = ("gaussian", "parabola", "none")
BOX_FORMATS = ("xyxy", "xywh", "cxcywh")
BOX_ENCODINGS = ("absolute", "anchor_linear", "anchor_ssd", "anchor_distance")
NMS_MODES = ("hard", "weighted")
FIRST_FRAME_BUILTINS = ("haar", "full_frame")
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


# ----------------------------------------------------------------------------------------------
# dataclasses


@dataclass(frozen=True)
class InputSpec:
    """How to turn a crop into the network's image input."""

    name: str
    layout: str            # NCHW or NHWC
    size: tuple[int, int]  # (width, height)
    color: str             # RGB, BGR or GRAY
    dtype: str             # float32, float16 (normalised as float32, then rounded) or uint8
    scale: float
    mean: tuple[float, ...]
    std: tuple[float, ...]

    @property
    def channels(self) -> int:
        return COLORS[self.color]

    @property
    def width(self) -> int:
        return self.size[0]

    @property
    def height(self) -> int:
        return self.size[1]

    def expected_shape(self, n: Any = "N") -> tuple:
        w, h, c = self.width, self.height, self.channels
        return (n, c, h, w) if self.layout == "NCHW" else (n, h, w, c)


@dataclass(frozen=True)
class QuerySpec:
    name: str  # input of shape (N, L, 3), float32, template points in mm


@dataclass(frozen=True)
class AlignSpec:
    left: int
    right: int


@dataclass(frozen=True)
class CropSpec:
    margin: float
    align: AlignSpec | None
    first_frame: str          # "haar", "full_frame" or an absolute path to a face-detector ONNX
    track: bool


@dataclass(frozen=True)
class HeatmapSpec:
    """Heatmap landmark output (N, L, H, W) (``layout`` LHW) or (N, H, W, L) (HWL)."""

    layout: str = "LHW"
    refine: str = "gaussian"     # sub-pixel step: gaussian (log-parabola), parabola, none
    values: str = "probability"  # probability or logit (sigmoid gives the confidence)


@dataclass(frozen=True)
class LandmarkOutput:
    name: str
    frame: str
    kind: str = "coordinates"     # coordinates or heatmap
    components: str = "xy"        # xy or xyz (z: a depth hint in the units of x)
    order: str = "interleaved"    # interleaved (x0 y0 [z0] x1 ...) or planar (x0 x1 ... y0 y1 ...)
    heatmap: HeatmapSpec | None = None

    @property
    def n_components(self) -> int:
        return COMPONENTS[self.components]


@dataclass(frozen=True)
class ConfidenceOutput:
    name: str
    kind: str


@dataclass(frozen=True)
class PresenceOutput:
    name: str
    threshold: float
    kind: str = "score"           # score (v1: compared as given), probability or logit (-> probability)


@dataclass(frozen=True)
class DetectorSpec:
    """A parsed and validated landmark-detector spec (format 1)."""

    path: Path | None
    name: str
    kind: str                 # dense or query
    input: InputSpec
    query: QuerySpec | None
    crop: CropSpec
    landmarks: LandmarkOutput
    confidence: ConfidenceOutput | None
    presence: PresenceOutput | None
    count: int
    raw: dict                 # the JSON as read (for the cache key and reports)

    @property
    def label(self) -> str:
        return self.path.name if self.path else f"<{self.name}>"

    def digest(self) -> str:
        """sha256 of the canonical JSON of the spec (key order and whitespace do not matter)."""
        return hashlib.sha256(json.dumps(self.raw, sort_keys=True).encode()).hexdigest()


@dataclass(frozen=True)
class BoxesOutput:
    name: str                               # the output; with ``parts``, their names joined (for messages)
    format: str
    frame: str
    encoding: str = "absolute"              # absolute, anchor_linear (BlazeFace), anchor_ssd, anchor_distance (SCRFD)
    scale: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0)   # anchor_linear: divisors of x, y, w, h
    variances: tuple[float, float] = (0.1, 0.2)       # anchor_ssd: centre and size variances
    parts: tuple[str, ...] = ()             # one output per anchor layer (SCRFD), concatenated in order

    @property
    def names(self) -> tuple[str, ...]:
        """The model outputs that hold the boxes, in anchor order."""
        return self.parts or (self.name,)


@dataclass(frozen=True)
class ScoresOutput:
    name: str                    # the output; with ``parts``, their names joined (for messages)
    threshold: float
    kind: str = "score"          # score (v1), probability or logit
    column: int | None = None    # for (N, K, C) scores with C > 1: the face column
    parts: tuple[str, ...] = ()  # one output per anchor layer (SCRFD), concatenated in order

    @property
    def names(self) -> tuple[str, ...]:
        """The model outputs that hold the scores, in anchor order."""
        return self.parts or (self.name,)


@dataclass(frozen=True)
class AnchorSpec:
    """SSD-style anchor layout over the finder input (see :func:`capture.detector.decode.make_anchors`)."""

    strides: tuple[int, ...]
    per_cell: tuple[int, ...]     # per stride entry
    offset: float = 0.5
    sizes: tuple[tuple[float, ...], ...] | None = None   # per stride entry: anchor sides in input px

    def count(self, input_size: tuple[int, int]) -> int:
        from capture.detector.decode import make_anchors

        return len(make_anchors(input_size, self))


@dataclass(frozen=True)
class NmsSpec:
    iou: float = 0.3
    mode: str = "hard"


@dataclass(frozen=True)
class FaceFinderSpec:
    """A face-box detector: the whole frame, letterboxed into ``input.size``, in; boxes + scores out."""

    path: Path | None
    input: InputSpec
    boxes: BoxesOutput
    scores: ScoresOutput
    raw: dict
    anchors: AnchorSpec | None = None
    nms: NmsSpec | None = None

    @property
    def label(self) -> str:
        return self.path.name if self.path else "<face finder>"

    def digest(self) -> str:
        return hashlib.sha256(json.dumps(self.raw, sort_keys=True).encode()).hexdigest()


# ----------------------------------------------------------------------------------------------
# strict field access


class _Reader:
    """Typed, strict access to one JSON object of a spec; errors carry the file and field path."""

    def __init__(self, label: str, obj: Any, where: str = ""):
        self.label = label
        self.where = where
        if not isinstance(obj, dict):
            self.fail(where or "the spec", "a JSON object", obj)
        self.obj = obj

    def fail(self, field: str, expected: str, found: Any) -> None:
        raise CaptureError(f"detector spec {self.label}: {field} is {_show(found)}; expected {expected}")

    def field(self, key: str) -> str:
        return f"{self.where}.{key}" if self.where else key

    def check_keys(self, required: tuple[str, ...], optional: tuple[str, ...] = ()) -> None:
        for key in self.obj:
            if key not in required and key not in optional:
                allowed = ", ".join(required + optional)
                raise CaptureError(f"detector spec {self.label}: unknown key '{self.field(key)}'; "
                                   f"allowed keys{' in ' + self.where if self.where else ''}: {allowed}")
        for key in required:
            if key not in self.obj:
                raise CaptureError(f"detector spec {self.label}: missing key '{self.field(key)}'")

    def get(self, key: str, default: Any = None) -> Any:
        return self.obj.get(key, default)

    def str_(self, key: str, choices: tuple[str, ...] | None = None) -> str:
        v = self.obj.get(key)
        if not isinstance(v, str) or not v:
            self.fail(self.field(key), "a non-empty string" + (f" ({' or '.join(choices)})" if choices else ""), v)
        if choices is not None and v not in choices:
            self.fail(self.field(key), " or ".join(repr(c) for c in choices), v)
        return v

    def number(self, key: str, lo: float | None = None, hi: float | None = None, default: Any = None) -> float:
        v = self.obj.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v != v:
            self.fail(self.field(key), "a number", v)
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            rng = f"a number in [{lo}, {hi}]" if hi is not None else f"a number >= {lo}"
            self.fail(self.field(key), rng, v)
        return float(v)

    def int_(self, key: str, lo: int | None = None) -> int:
        v = self.obj.get(key)
        if isinstance(v, bool) or not isinstance(v, int):
            self.fail(self.field(key), "an integer", v)
        if lo is not None and v < lo:
            self.fail(self.field(key), f"an integer >= {lo}", v)
        return int(v)

    def bool_(self, key: str) -> bool:
        v = self.obj.get(key)
        if not isinstance(v, bool):
            self.fail(self.field(key), "true or false", v)
        return v

    def sub(self, key: str) -> "_Reader":
        return _Reader(self.label, self.obj.get(key), self.field(key))


def _show(v: Any) -> str:
    s = json.dumps(v) if not isinstance(v, (tuple,)) else str(v)
    return s if len(s) <= 80 else s[:77] + "..."


# ----------------------------------------------------------------------------------------------
# parsing


#: Largest input side a spec may declare: one 4096 x 4096 float32 RGB tensor is 192 MiB already.
MAX_INPUT_SIDE = 4096


def _parse_input(r: _Reader) -> InputSpec:
    r.check_keys(("name", "layout", "size", "color", "dtype"), ("scale", "mean", "std"))
    name = r.str_("name")
    layout = r.str_("layout", LAYOUTS)
    size = r.get("size")
    if (not isinstance(size, list) or len(size) != 2
            or not all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)):
        r.fail(r.field("size"), "[width, height], two positive integers", size)
    if max(size) > MAX_INPUT_SIDE:
        r.fail(r.field("size"), f"at most {MAX_INPUT_SIDE} pixels a side (a landmark model's input is a crop)", size)
    color = r.str_("color", tuple(COLORS))
    dtype = r.str_("dtype", DTYPES)
    channels = COLORS[color]
    scale = r.number("scale", default=1.0)
    if scale == 0:
        r.fail(r.field("scale"), "a non-zero number", 0)
    vecs = []
    for key, default in (("mean", 0.0), ("std", 1.0)):
        v = r.get(key, [default] * channels)
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            v = [v] * channels
        if (not isinstance(v, list) or len(v) != channels
                or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v)):
            r.fail(r.field(key), f"a list of {channels} numbers (one per {color} channel)", v)
        if key == "std" and any(x == 0 for x in v):
            r.fail(r.field(key), "non-zero numbers", v)
        vecs.append(tuple(float(x) for x in v))
    if dtype == "uint8" and (scale != 1.0 or any(m != 0 for m in vecs[0]) or any(s != 1 for s in vecs[1])):
        r.fail(r.field("dtype"), "float32 or float16 when scale/mean/std are given (uint8 input takes raw 0..255 pixels)",
               dtype)
    return InputSpec(name=name, layout=layout, size=(size[0], size[1]), color=color, dtype=dtype,
                     scale=scale, mean=vecs[0], std=vecs[1])


def _read_json(path: Path, what: str) -> dict:
    if not path.is_file():
        raise CaptureError(f"{what} {path} does not exist; put the JSON spec beside the ONNX file "
                           f"(same stem) or pass its path")
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"{what} {path} is not valid JSON ({exc}); fix the file") from None


def _version(r: _Reader) -> int:
    v = r.get("version")
    if isinstance(v, bool) or v not in VERSIONS:
        r.fail("version", f"{' or '.join(str(x) for x in VERSIONS)} (the formats this build reads)", v)
    return int(v)


def _parse_score(r: _Reader, version: int, cls):
    """``{"name", "threshold"[, "kind"]}``: v1 compares the raw score; v2 ``kind`` probability or logit
    (the threshold is then a probability in [0, 1] and a logit is turned into one by the sigmoid)."""
    extra = ("column",) if cls is ScoresOutput else ()
    r.check_keys(("name", "threshold"), (("kind",) + extra) if version >= 2 else ())
    kind = r.str_("kind", SCORE_KINDS) if r.get("kind") is not None else "score"
    thr = r.number("threshold", 0.0, 1.0) if kind != "score" else r.number("threshold")
    kw = {}
    if cls is ScoresOutput and r.get("column") is not None:
        kw["column"] = r.int_("column", lo=0)
    if cls is ScoresOutput and version >= 2:
        name, kw["parts"] = _output_names(r)
    else:
        name = r.str_("name")
    return cls(name=name, threshold=thr, kind=kind, **kw)


def _output_names(r: _Reader) -> tuple[str, tuple[str, ...]]:
    """A face detector's ``name``: one output, or a list of outputs, one per anchor layer (as SCRFD gives
    them), whose rows are concatenated in order. ``(name for messages, parts or ())``."""
    v = r.get("name")
    if not isinstance(v, list):
        return r.str_("name"), ()
    if not v or not all(isinstance(x, str) and x for x in v) or len(set(v)) != len(v):
        r.fail(r.field("name"), "an output name, or a list of distinct output names (one per anchor layer)", v)
    return ", ".join(v), tuple(v)


def _parse_landmark_output(r: _Reader, version: int) -> LandmarkOutput:
    if version == 1:
        r.check_keys(("name", "frame"))
        return LandmarkOutput(name=r.str_("name"), frame=r.str_("frame", FRAMES))
    r.check_keys(("name",), ("frame", "kind", "components", "order", "heatmap"))
    name = r.str_("name")
    kind = r.str_("kind", LANDMARK_KINDS) if r.get("kind") is not None else "coordinates"
    if kind == "heatmap":
        for key in ("frame", "components", "order"):
            if r.get(key) is not None:
                r.fail(r.field(key), "absent for a heatmap output (heatmap cells cover the input edge to "
                       "edge; set kind to 'coordinates' for positions)", r.get(key))
        hm = HeatmapSpec()
        if r.get("heatmap") is not None:
            h = r.sub("heatmap")
            h.check_keys((), ("layout", "refine", "values"))
            hm = HeatmapSpec(layout=h.str_("layout", HEATMAP_LAYOUTS) if h.get("layout") is not None else "LHW",
                             refine=h.str_("refine", HEATMAP_REFINES) if h.get("refine") is not None else "gaussian",
                             values=h.str_("values", SCORE_KINDS) if h.get("values") is not None else "probability")
        return LandmarkOutput(name=name, frame="crop_unit", kind="heatmap", heatmap=hm)
    if r.get("heatmap") is not None:
        r.fail(r.field("heatmap"), "absent unless kind is 'heatmap'", r.get("heatmap"))
    return LandmarkOutput(name=name, frame=r.str_("frame", FRAMES),
                          components=r.str_("components", tuple(COMPONENTS)) if r.get("components") is not None else "xy",
                          order=r.str_("order", ORDERS) if r.get("order") is not None else "interleaved")


def parse_detector_spec(obj: Any, path: Path | None = None) -> DetectorSpec:
    """Validate a detector spec given as parsed JSON; ``path`` resolves relative face-finder paths."""
    label = path.name if path else "<spec>"
    r = _Reader(label, obj)
    r.check_keys(("format", "version", "name", "kind", "input", "crop", "outputs", "landmarks"), ("query",))
    if r.get("format") != DETECTOR_FORMAT:
        r.fail("format", repr(DETECTOR_FORMAT), r.get("format"))
    version = _version(r)
    name = r.str_("name")
    if not NAME_RE.match(name):
        r.fail("name", "letters, digits, '_', '.', '-' (it names the landmark embedding file)", name)
    kind = r.str_("kind", ("dense", "query"))
    inp = _parse_input(r.sub("input"))

    query = None
    if kind == "query":
        if r.get("query") is None:
            r.fail("query", 'an object {"name": ...} for kind "query"', None)
        q = r.sub("query")
        q.check_keys(("name",))
        query = QuerySpec(name=q.str_("name"))
        if query.name == inp.name:
            q.fail("query.name", "a different input than input.name", query.name)
    elif r.get("query") is not None:
        r.fail("query", 'null for kind "dense" (set kind to "query" for a query-based detector)', r.get("query"))

    lm = r.sub("landmarks")
    lm.check_keys(("count",))
    count = lm.int_("count", lo=1)

    c = r.sub("crop")
    c.check_keys(("margin", "first_frame", "track"), ("align",))
    margin = c.number("margin", lo=0.0, hi=5.0)
    align = None
    if c.get("align") is not None:
        a = c.sub("align")
        a.check_keys(("left", "right"))
        left, right = a.int_("left", lo=0), a.int_("right", lo=0)
        for k, v in (("left", left), ("right", right)):
            if v >= count:
                a.fail(a.field(k), f"a landmark index below landmarks.count = {count}", v)
        if left == right:
            a.fail(a.field("right"), "a landmark other than crop.align.left", right)
        align = AlignSpec(left, right)
    first = c.str_("first_frame")
    if first not in FIRST_FRAME_BUILTINS:
        if not first.endswith(".onnx"):
            c.fail("crop.first_frame", "'haar', 'full_frame' or the path of a face-detector .onnx", first)
        fp = Path(first)
        if not fp.is_absolute() and path is not None:
            fp = path.parent / fp
        if not fp.is_file():
            raise CaptureError(f"detector spec {label}: crop.first_frame names {first} but {fp} does not exist; "
                               f"fix the path (relative to the spec) or use 'haar'")
        first = str(fp.resolve())
    crop = CropSpec(margin=margin, align=align, first_frame=first, track=c.bool_("track"))

    o = r.sub("outputs")
    o.check_keys(("landmarks",), ("confidence", "presence"))
    landmarks = _parse_landmark_output(o.sub("landmarks"), version)
    confidence = None
    if o.get("confidence") is not None:
        oc = o.sub("confidence")
        oc.check_keys(("name", "kind"))
        confidence = ConfidenceOutput(name=oc.str_("name"),
                                      kind=oc.str_("kind", CONFIDENCE_KINDS if version == 1 else CONFIDENCE_KINDS_V2))
    presence = None
    if o.get("presence") is not None:
        op = o.sub("presence")
        presence = _parse_score(op, version, PresenceOutput)
    names = [x.name for x in (landmarks, confidence, presence) if x is not None]
    if len(set(names)) != len(names):
        o.fail("outputs", "different output names for landmarks, confidence and presence", names)
    return DetectorSpec(path=path, name=name, kind=kind, input=inp, query=query, crop=crop,
                        landmarks=landmarks, confidence=confidence, presence=presence, count=count, raw=obj)


def _parse_anchors(r: _Reader) -> AnchorSpec:
    r.check_keys(("strides",), ("per_cell", "offset", "sizes"))
    strides = r.get("strides")
    if (not isinstance(strides, list) or not strides
            or not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in strides)):
        r.fail(r.field("strides"), "a list of positive integers (input px per anchor cell, one per layer)", strides)
    sizes = r.get("sizes")
    if sizes is not None:
        if r.get("per_cell") is not None:
            r.fail(r.field("per_cell"), "absent when sizes are given (one anchor per size)", r.get("per_cell"))
        if (not isinstance(sizes, list) or len(sizes) != len(strides)
                or not all(isinstance(row, list) and row and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                                 and v > 0 for v in row) for row in sizes)):
            r.fail(r.field("sizes"), f"{len(strides)} lists (one per stride) of anchor sides in input px", sizes)
        per_cell = tuple(len(row) for row in sizes)
        sizes = tuple(tuple(float(v) for v in row) for row in sizes)
    else:
        pc = r.get("per_cell", 1)
        if isinstance(pc, int) and not isinstance(pc, bool) and pc > 0:
            per_cell = (pc,) * len(strides)
        elif (isinstance(pc, list) and len(pc) == len(strides)
              and all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in pc)):
            per_cell = tuple(pc)
        else:
            r.fail(r.field("per_cell"), f"a positive integer or {len(strides)} of them (one per stride)", pc)
    return AnchorSpec(strides=tuple(strides), per_cell=per_cell, offset=r.number("offset", 0.0, 1.0, default=0.5),
                      sizes=sizes)


def parse_face_finder_spec(obj: Any, path: Path | None = None) -> FaceFinderSpec:
    label = path.name if path else "<face finder spec>"
    r = _Reader(label, obj)
    r.check_keys(("format", "version", "input", "outputs"), ("anchors", "nms"))
    if r.get("format") != FACE_FINDER_FORMAT:
        r.fail("format", repr(FACE_FINDER_FORMAT), r.get("format"))
    version = _version(r)
    if version == 1:
        for key in ("anchors", "nms"):
            if key in r.obj:
                r.fail(key, "absent in version 1 (set version to 2)", r.get(key))
    inp = _parse_input(r.sub("input"))
    o = r.sub("outputs")
    o.check_keys(("boxes", "scores"))
    b = o.sub("boxes")
    if version == 1:
        b.check_keys(("name", "format", "frame"))
        boxes = BoxesOutput(name=b.str_("name"), format=b.str_("format", BOX_FORMATS), frame=b.str_("frame", FRAMES))
    else:
        b.check_keys(("name",), ("format", "frame", "encoding", "scale", "variances"))
        enc = b.str_("encoding", BOX_ENCODINGS) if b.get("encoding") is not None else "absolute"
        kw: dict = {}
        if enc == "absolute":
            for key in ("scale", "variances"):
                if b.get(key) is not None:
                    b.fail(b.field(key), "absent for encoding 'absolute' (it belongs to the anchor encodings)",
                           b.get(key))
            fmt, frame = b.str_("format", BOX_FORMATS), b.str_("frame", FRAMES)
        else:
            for key in ("format", "frame"):
                if b.get(key) is not None:
                    b.fail(b.field(key), f"absent for encoding '{enc}' (anchor regressors are cx, cy, w, h "
                           f"offsets; the anchors fix the frame)", b.get(key))
            fmt, frame = "cxcywh", "crop_unit"
            if enc == "anchor_linear":
                sc = b.get("scale", [1.0, 1.0, 1.0, 1.0])
                if isinstance(sc, (int, float)) and not isinstance(sc, bool):
                    sc = [sc] * 4
                if (not isinstance(sc, list) or len(sc) != 4
                        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and v != 0 for v in sc)):
                    b.fail(b.field("scale"), "one non-zero number or four (x, y, w, h divisors, e.g. 128)", sc)
                kw["scale"] = tuple(float(v) for v in sc)
                if b.get("variances") is not None:
                    b.fail(b.field("variances"), "absent for encoding 'anchor_linear'", b.get("variances"))
            elif enc == "anchor_distance":
                for key in ("scale", "variances"):
                    if b.get(key) is not None:
                        b.fail(b.field(key), "absent for encoding 'anchor_distance' (distances are in anchor sides)",
                               b.get(key))
            else:
                va = b.get("variances", [0.1, 0.2])
                if (not isinstance(va, list) or len(va) != 2
                        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 for v in va)):
                    b.fail(b.field("variances"), "two positive numbers [centre, size], e.g. [0.1, 0.2]", va)
                kw["variances"] = (float(va[0]), float(va[1]))
                if b.get("scale") is not None:
                    b.fail(b.field("scale"), "absent for encoding 'anchor_ssd'", b.get("scale"))
        name, parts = _output_names(b)
        boxes = BoxesOutput(name=name, format=fmt, frame=frame, encoding=enc, parts=parts, **kw)
    scores = _parse_score(o.sub("scores"), version, ScoresOutput)
    if set(boxes.names) & set(scores.names):
        o.fail("outputs.scores.name", "different outputs than outputs.boxes.name", scores.name)
    anchors = _parse_anchors(r.sub("anchors")) if r.get("anchors") is not None else None
    if (anchors is None) != (boxes.encoding == "absolute"):
        if anchors is None:
            r.fail("anchors", f"an anchor layout for outputs.boxes.encoding '{boxes.encoding}'", None)
        r.fail("outputs.boxes.encoding", "'anchor_linear', 'anchor_ssd' or 'anchor_distance' when anchors are given",
               boxes.encoding)
    if anchors is not None and anchors.sizes is None and boxes.encoding == "anchor_ssd":
        r.fail("anchors.sizes", "anchor sides in input px for encoding 'anchor_ssd'", None)
    if boxes.parts or scores.parts:      # outputs one per anchor layer (SCRFD): both lists, one name per layer
        from capture.detector.decode import anchor_layers

        for field, out in (("outputs.boxes.name", boxes), ("outputs.scores.name", scores)):
            shown = list(out.parts) if out.parts else out.name
            if anchors is None:
                r.fail(field, "one output name (a list of outputs, one per anchor layer, needs an anchor layout)",
                       shown)
            layers = len(anchor_layers(anchors.strides, anchors.per_cell, anchors.sizes))
            if len(out.parts) != layers:
                r.fail(field, f"a list of {layers} output names, one per anchor layer of distinct stride (boxes and "
                       f"scores are both lists when one is)", shown)
    nms = None
    if r.get("nms") is not None:
        n = r.sub("nms")
        n.check_keys(("iou",), ("mode",))
        nms = NmsSpec(iou=n.number("iou", 0.0, 1.0),
                      mode=n.str_("mode", NMS_MODES) if n.get("mode") is not None else "hard")
    return FaceFinderSpec(path=path, input=inp, boxes=boxes, scores=scores, raw=obj, anchors=anchors, nms=nms)


def load_detector_spec(path: str | Path) -> DetectorSpec:
    path = Path(path)
    return parse_detector_spec(_read_json(path, "detector spec"), path)


def load_face_finder_spec(path: str | Path) -> FaceFinderSpec:
    path = Path(path)
    return parse_face_finder_spec(_read_json(path, "face-detector spec"), path)
