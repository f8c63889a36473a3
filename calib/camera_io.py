"""Camera files: the project's camera JSON and OpenCV's own YAML/XML calibration files.

The project's camera JSON (``format: capture-camera``, ``version: 1``)::

    {
      "format": "capture-camera",
      "version": 1,
      "image_size": [1920, 1080],                       # width, height in pixels
      "K": [[fx, 0, cx], [0, fy, cy], [0, 0, 1]],       # pixels, pixel centres at integers
      "dist": [k1, k2, p1, p2, k3],                     # OpenCV order; 0, 4, 5, 8, 12 or 14 values
      "rms_px": 0.21,                                   # calibration RMS, null when unknown
      "std_dev": {"fx": 0.8, "fy": 0.8, "cx": 0.5, "cy": 0.4},   # optional, 1-sigma, pixels
      "is_default": false,                              # true for a guessed camera
      "provenance": "capture calibrate of take1.mp4 ..."
    }

Only ``K``, ``dist`` and ``image_size`` are required; unknown keys are errors (they are usually
typos). OpenCV files (``.yaml``, ``.yml``, ``.xml``) are read and written through
``cv2.FileStorage`` with the keys ``camera_matrix``, ``distortion_coefficients``, ``image_width``,
``image_height`` (and ``avg_reprojection_error`` when known), as OpenCV's calibration sample does.
Every problem with a file is one :class:`~capture.io.errors.CaptureError` line naming the file.
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from calib.camera import Camera
from capture.io.atomic import atomic_path, write_json
from capture.io.errors import CaptureError

FORMAT = "capture-camera"
VERSION = 1
OPENCV_SUFFIXES = (".yaml", ".yml", ".xml")
_REQUIRED = ("K", "dist", "image_size")
_OPTIONAL = ("format", "version", "rms_px", "std_dev", "is_default", "provenance")


# ------------------------------------------------------------------------------------------ JSON
def camera_to_dict(camera: Camera) -> dict[str, Any]:
    """The camera as plain JSON-ready data (the schema in the module docstring)."""
    return {
        "format": FORMAT,
        "version": VERSION,
        "image_size": [camera.width, camera.height],
        "K": camera.K.tolist(),
        "dist": camera.dist.tolist(),
        "rms_px": camera.rms,
        "std_dev": dict(camera.std_dev),
        "is_default": camera.is_default,
        "provenance": camera.provenance,
    }


def camera_from_dict(data: Any, source: str = "camera JSON") -> Camera:
    """Parse the camera JSON schema; ``source`` names the file in error messages."""
    if not isinstance(data, dict):
        raise CaptureError(f"{source}: expected a JSON object with K, dist and image_size")
    unknown = sorted(set(data) - set(_REQUIRED) - set(_OPTIONAL))
    if unknown:
        raise CaptureError(
            f"{source}: unknown key(s) {', '.join(unknown)}; allowed: {', '.join(_REQUIRED + _OPTIONAL)}"
        )
    missing = [k for k in _REQUIRED if k not in data]
    if missing:
        raise CaptureError(f"{source}: missing {', '.join(missing)}; a camera file needs K, dist and image_size")
    if data.get("format", FORMAT) != FORMAT:
        raise CaptureError(f"{source}: format is {data['format']!r}, expected {FORMAT!r}")
    if data.get("version", VERSION) != VERSION:
        raise CaptureError(
            f"{source}: camera file version {data['version']!r} is not supported (this build reads {VERSION})"
        )
    try:
        K = np.asarray(data["K"], dtype=np.float64)
        dist = np.asarray(data["dist"], dtype=np.float64).reshape(-1)
        size = data["image_size"]
        if not (isinstance(size, list) and len(size) == 2 and all(isinstance(v, int) for v in size)):
            raise CaptureError(f"{source}: image_size must be [width, height] integers, got {size!r}")
        rms = data.get("rms_px")
        if rms is not None and not (isinstance(rms, (int, float)) and math.isfinite(rms) and rms >= 0):
            raise CaptureError(f"{source}: rms_px must be a non-negative number or null, got {rms!r}")
        std = data.get("std_dev") or {}
        if not isinstance(std, dict):
            raise CaptureError(f"{source}: std_dev must be an object like {{\"fx\": 0.5}}")
        return Camera(
            K, dist, (size[0], size[1]), rms,
            str(data.get("provenance") or f"camera file {source}"),
            bool(data.get("is_default", False)), std,
        )
    except CaptureError as exc:
        msg = str(exc)
        raise CaptureError(msg if msg.startswith(source) else f"{source}: {msg}") from None
    except (TypeError, ValueError) as exc:
        raise CaptureError(f"{source}: K must be 3x3 numbers and dist a list of numbers ({exc})") from None


def write_camera_json(path: str | os.PathLike, camera: Camera) -> Path:
    """Atomically write the camera JSON."""
    return write_json(path, camera_to_dict(camera))


def read_camera_json(path: str | os.PathLike) -> Camera:
    path = Path(path)
    text = _read_text(path)
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise CaptureError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    return camera_from_dict(data, str(path))


# --------------------------------------------------------------------------------------- OpenCV
def write_camera_opencv(path: str | os.PathLike, camera: Camera) -> Path:
    """Atomically write an OpenCV FileStorage calibration file (format chosen by the suffix)."""
    import cv2

    path = Path(path)
    if path.suffix.lower() not in OPENCV_SUFFIXES:
        raise CaptureError(f"{path}: OpenCV camera files end in .yaml, .yml or .xml")
    with atomic_path(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        try:
            fs.write("image_width", camera.width)
            fs.write("image_height", camera.height)
            fs.write("camera_matrix", camera.K)
            fs.write("distortion_coefficients", camera.dist.reshape(-1, 1) if camera.dist.size else np.zeros((5, 1)))
            if camera.rms is not None:
                fs.write("avg_reprojection_error", camera.rms)
        finally:
            fs.release()
    return path


def read_camera_opencv(path: str | os.PathLike) -> Camera:
    """Read ``camera_matrix``, ``distortion_coefficients``, ``image_width``, ``image_height``."""
    import cv2

    path = Path(path)
    _read_text(path)  # existence and readability, with our message
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except Exception as exc:  # cv2.error (wrapped in SystemError by the bindings) on a parse error
        detail = str(exc.__cause__ or exc).strip().splitlines()[-1]
        detail = detail.split(" error: ", 1)[-1].strip()[-120:]  # OpenCV's own message, not its source path
        raise CaptureError(f"{path}: not an OpenCV YAML/XML file ({detail}); give the file written by "
                           f"cv2.FileStorage or capture calibrate") from None
    try:
        if not fs.isOpened():
            raise CaptureError(f"{path}: OpenCV could not open this file as YAML/XML")
        nodes = {k: fs.getNode(k) for k in ("camera_matrix", "distortion_coefficients", "image_width", "image_height")}
        missing = [k for k, n in nodes.items() if n.empty()]
        if missing:
            raise CaptureError(
                f"{path}: missing {', '.join(missing)}; an OpenCV calibration file needs camera_matrix, "
                "distortion_coefficients, image_width and image_height"
            )
        mats = {}
        for k in ("camera_matrix", "distortion_coefficients"):
            m = None
            if nodes[k].isMap():
                try:
                    m = nodes[k].mat()
                except Exception:  # cv2.error: a map that is not an opencv-matrix
                    m = None
            if m is None or not np.issubdtype(np.asarray(m).dtype, np.number):
                raise CaptureError(f"{path}: {k} must be an !!opencv-matrix node (rows, cols, dt, data); fix the file "
                                   f"or recalibrate with capture calibrate")
            mats[k] = np.asarray(m, np.float64)
        K, dist = mats["camera_matrix"], mats["distortion_coefficients"]
        for k in ("image_width", "image_height"):
            if not (nodes[k].isInt() or nodes[k].isReal()):
                raise CaptureError(f"{path}: {k} must be a number of pixels, got a {_node_kind(nodes[k])}")
        width, height = nodes["image_width"].real(), nodes["image_height"].real()
        if not (math.isfinite(width) and math.isfinite(height)) or width != int(width) or height != int(height):
            raise CaptureError(f"{path}: image_width and image_height must be integers")
        rms_node = fs.getNode("avg_reprojection_error")
        rms = None
        if not rms_node.empty():
            if not (rms_node.isInt() or rms_node.isReal()):
                raise CaptureError(f"{path}: avg_reprojection_error must be a number, got a {_node_kind(rms_node)}")
            rms = float(rms_node.real())
    finally:
        fs.release()
    try:
        return Camera(K, np.asarray(dist).reshape(-1), (int(width), int(height)), rms, f"OpenCV file {path}")
    except CaptureError as exc:
        raise CaptureError(f"{path}: {exc}") from None


def _node_kind(node) -> str:
    for name in ("isString", "isMap", "isSeq", "isNone"):
        if getattr(node, name)():
            return {"isString": "string", "isMap": "map", "isSeq": "sequence", "isNone": "null"}[name]
    return "non-number"


# ---------------------------------------------------------------------------------- plausibility
#: Horizontal fields of view (degrees) a camera file may describe; outside is a unit or typing error.
FOV_RANGE_DEG = (1.0, 175.0)
#: Largest fy / fx (or fx / fy) accepted (anamorphic lenses are at most 2x).
MAX_ASPECT = 4.0
#: Largest round-trip error (px) of undistorting and re-distorting points over the image.
MAX_DISTORTION_ROUNDTRIP_PX = 1.0
#: Largest factor by which distortion may stretch or shrink the view at the image's edge.
MAX_DISTORTION_SCALE = 4.0


def camera_problem(camera: Camera) -> tuple[str, str] | None:
    """``(problem, advice)`` when a camera cannot be right, else None: the principal point outside the image, a
    field of view outside :data:`FOV_RANGE_DEG`, a wild aspect, or distortion that does not invert over the image
    (round trip > :data:`MAX_DISTORTION_ROUNDTRIP_PX`) or stretches the view more than :data:`MAX_DISTORTION_SCALE`.
    ``advice`` is for a camera file someone wrote; a calibration that produces such a model gives its own."""
    import cv2

    w, h = camera.image_size
    if not (-0.5 <= camera.cx <= w - 0.5 and -0.5 <= camera.cy <= h - 0.5):
        return (f"principal point ({camera.cx:g}, {camera.cy:g}) lies outside the {w}x{h} image",
                "check K (cx, cy are pixels, near the image centre) or recalibrate")
    fov = camera.fov_deg()
    lo, hi = FOV_RANGE_DEG
    if not all(lo <= f <= hi for f in fov):
        return (f"fx={camera.fx:g}, fy={camera.fy:g} give a {fov[0]:.3g} x {fov[1]:.3g} degree field of view for "
                f"{w}x{h} images (plausible: {lo:g}-{hi:g})", "focal lengths are in pixels: check K or recalibrate")
    if not 1.0 / MAX_ASPECT <= camera.fy / camera.fx <= MAX_ASPECT:
        return f"fy / fx = {camera.fy / camera.fx:.3g} is not a real lens's pixel aspect", "check K"
    if not (camera.dist.size and np.any(camera.dist != 0)):
        return None
    order = "check the coefficients' order (k1, k2, p1, p2, k3) or recalibrate"
    u, v = np.meshgrid(np.linspace(0, w - 1, 9), np.linspace(0, h - 1, 9))
    px = np.stack([u.ravel(), v.ravel()], 1).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-9)
    und = cv2.undistortPointsIter(px, camera.K, camera.dist, None, None, crit).reshape(-1, 2)
    back = None
    if np.isfinite(und).all():
        pts = np.concatenate([und, np.ones((len(und), 1))], 1)
        back = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), camera.K, camera.dist)[0].reshape(-1, 2)
    err = np.inf if back is None or not np.isfinite(back).all() else float(np.abs(back - px.reshape(-1, 2)).max())
    if not err <= MAX_DISTORTION_ROUNDTRIP_PX:
        return (f"the distortion coefficients {np.round(camera.dist[:5], 4).tolist()} do not invert over the {w}x{h} "
                f"image (points move {err:.3g} px on a round trip)", order)
    pin = (px.reshape(-1, 2) - (camera.cx, camera.cy)) / (camera.fx, camera.fy)
    rd, ru = np.linalg.norm(pin, axis=1), np.linalg.norm(und, axis=1)
    far = rd > 0.25 * rd.max()
    worst = ru[far] / rd[far]
    if far.any() and not (1.0 / MAX_DISTORTION_SCALE <= worst.min() and worst.max() <= MAX_DISTORTION_SCALE):
        bad = worst.min() if worst.min() < 1.0 / MAX_DISTORTION_SCALE else worst.max()
        return (f"the distortion coefficients {np.round(camera.dist[:5], 4).tolist()} scale the view by {bad:.3g} at "
                f"the image's edge (a lens does at most {MAX_DISTORTION_SCALE:g}x)", order)
    return None


def check_camera_plausible(camera: Camera, source: str) -> Camera:
    """``camera``, or a one-line :class:`CaptureError` naming ``source`` when it cannot be right
    (:func:`camera_problem`)."""
    problem = camera_problem(camera)
    if problem:
        raise CaptureError(f"{source}: {problem[0]}; {problem[1]}")
    return camera


# ------------------------------------------------------------------------------------- dispatch
def read_camera(path: str | os.PathLike, check: bool = True) -> Camera:
    """Read a camera file: ``.json`` (ours) or ``.yaml``/``.yml``/``.xml`` (OpenCV).

    With ``check`` (the default) the camera must also be plausible (:func:`check_camera_plausible`).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        return check_camera_plausible(read_camera_json(path), str(path)) if check else read_camera_json(path)
    if suffix in OPENCV_SUFFIXES:
        return check_camera_plausible(read_camera_opencv(path), str(path)) if check else read_camera_opencv(path)
    raise CaptureError(f"{path}: unknown camera file type; use .json (capture) or .yaml/.yml/.xml (OpenCV)")


def write_camera(path: str | os.PathLike, camera: Camera) -> Path:
    """Write a camera file, format chosen by the suffix as in :func:`read_camera`."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        return write_camera_json(path, camera)
    if suffix in OPENCV_SUFFIXES:
        return write_camera_opencv(path, camera)
    raise CaptureError(f"{path}: unknown camera file type; use .json (capture) or .yaml/.yml/.xml (OpenCV)")


def _read_text(path: Path) -> str:
    if not path.exists():
        raise CaptureError(f"camera file {path} does not exist; pass the file written by `capture calibrate`")
    if path.is_dir():
        raise CaptureError(f"camera file {path} is a directory; pass a .json, .yaml or .xml file")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise CaptureError(f"cannot read camera file {path}: {exc.__class__.__name__}") from None
