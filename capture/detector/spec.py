"""Detector specs: the JSON that says how to feed a user's ONNX landmark detector and read it.

Two schemas live here (both documented in ``docs/detector_spec.md``):

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
VERSION = 1

LAYOUTS = ("NCHW", "NHWC")
COLORS = {"RGB": 3, "BGR": 3, "GRAY": 1}
DTYPES = ("float32", "uint8")
FRAMES = ("crop_pixels", "crop_unit", "crop_signed")
CONFIDENCE_KINDS = ("probability", "sigma_px")
BOX_FORMATS = ("xyxy", "xywh", "cxcywh")
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
    dtype: str             # float32 or uint8
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
class LandmarkOutput:
    name: str
    frame: str


@dataclass(frozen=True)
class ConfidenceOutput:
    name: str
    kind: str


@dataclass(frozen=True)
class PresenceOutput:
    name: str
    threshold: float


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
    name: str
    format: str
    frame: str


@dataclass(frozen=True)
class ScoresOutput:
    name: str
    threshold: float


@dataclass(frozen=True)
class FaceFinderSpec:
    """A face-box detector: the whole frame, letterboxed into ``input.size``, in; boxes + scores out."""

    path: Path | None
    input: InputSpec
    boxes: BoxesOutput
    scores: ScoresOutput
    raw: dict

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


def _parse_input(r: _Reader) -> InputSpec:
    r.check_keys(("name", "layout", "size", "color", "dtype"), ("scale", "mean", "std"))
    name = r.str_("name")
    layout = r.str_("layout", LAYOUTS)
    size = r.get("size")
    if (not isinstance(size, list) or len(size) != 2
            or not all(isinstance(s, int) and not isinstance(s, bool) and s > 0 for s in size)):
        r.fail(r.field("size"), "[width, height], two positive integers", size)
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
        r.fail(r.field("dtype"), "float32 when scale/mean/std are given (uint8 input takes raw 0..255 pixels)",
               dtype)
    return InputSpec(name=name, layout=layout, size=(size[0], size[1]), color=color, dtype=dtype,
                     scale=scale, mean=vecs[0], std=vecs[1])


def _read_json(path: Path, what: str) -> dict:
    if not path.is_file():
        raise CaptureError(f"{what} {path} does not exist; put the JSON spec beside the ONNX file "
                           f"(same stem) or pass its path")
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise CaptureError(f"{what} {path} is not valid JSON ({exc}); fix the file") from None


def parse_detector_spec(obj: Any, path: Path | None = None) -> DetectorSpec:
    """Validate a detector spec given as parsed JSON; ``path`` resolves relative face-finder paths."""
    label = path.name if path else "<spec>"
    r = _Reader(label, obj)
    r.check_keys(("format", "version", "name", "kind", "input", "crop", "outputs", "landmarks"), ("query",))
    if r.get("format") != DETECTOR_FORMAT:
        r.fail("format", repr(DETECTOR_FORMAT), r.get("format"))
    if r.get("version") != VERSION:
        r.fail("version", f"{VERSION} (this build reads format {VERSION})", r.get("version"))
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
    ol = o.sub("landmarks")
    ol.check_keys(("name", "frame"))
    landmarks = LandmarkOutput(name=ol.str_("name"), frame=ol.str_("frame", FRAMES))
    confidence = None
    if o.get("confidence") is not None:
        oc = o.sub("confidence")
        oc.check_keys(("name", "kind"))
        confidence = ConfidenceOutput(name=oc.str_("name"), kind=oc.str_("kind", CONFIDENCE_KINDS))
    presence = None
    if o.get("presence") is not None:
        op = o.sub("presence")
        op.check_keys(("name", "threshold"))
        presence = PresenceOutput(name=op.str_("name"), threshold=op.number("threshold"))
    names = [x.name for x in (landmarks, confidence, presence) if x is not None]
    if len(set(names)) != len(names):
        o.fail("outputs", "different output names for landmarks, confidence and presence", names)
    return DetectorSpec(path=path, name=name, kind=kind, input=inp, query=query, crop=crop,
                        landmarks=landmarks, confidence=confidence, presence=presence, count=count, raw=obj)


def parse_face_finder_spec(obj: Any, path: Path | None = None) -> FaceFinderSpec:
    label = path.name if path else "<face finder spec>"
    r = _Reader(label, obj)
    r.check_keys(("format", "version", "input", "outputs"))
    if r.get("format") != FACE_FINDER_FORMAT:
        r.fail("format", repr(FACE_FINDER_FORMAT), r.get("format"))
    if r.get("version") != VERSION:
        r.fail("version", f"{VERSION}", r.get("version"))
    inp = _parse_input(r.sub("input"))
    o = r.sub("outputs")
    o.check_keys(("boxes", "scores"))
    b = o.sub("boxes")
    b.check_keys(("name", "format", "frame"))
    boxes = BoxesOutput(name=b.str_("name"), format=b.str_("format", BOX_FORMATS), frame=b.str_("frame", FRAMES))
    s = o.sub("scores")
    s.check_keys(("name", "threshold"))
    scores = ScoresOutput(name=s.str_("name"), threshold=s.number("threshold"))
    if boxes.name == scores.name:
        o.fail("outputs.scores.name", "a different output than outputs.boxes.name", scores.name)
    return FaceFinderSpec(path=path, input=inp, boxes=boxes, scores=scores, raw=obj)


def load_detector_spec(path: str | Path) -> DetectorSpec:
    path = Path(path)
    return parse_detector_spec(_read_json(path, "detector spec"), path)


def load_face_finder_spec(path: str | Path) -> FaceFinderSpec:
    path = Path(path)
    return parse_face_finder_spec(_read_json(path, "face-detector spec"), path)
