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
        detail = str(exc.__cause__ or exc).strip().splitlines()[-1][-160:]
        raise CaptureError(f"{path}: not an OpenCV YAML/XML file ({detail})") from None
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
        K = nodes["camera_matrix"].mat()
        dist = nodes["distortion_coefficients"].mat()
        if K is None or dist is None:
            raise CaptureError(f"{path}: camera_matrix and distortion_coefficients must be !!opencv-matrix nodes")
        width, height = nodes["image_width"].real(), nodes["image_height"].real()
        if width != int(width) or height != int(height):
            raise CaptureError(f"{path}: image_width and image_height must be integers")
        rms_node = fs.getNode("avg_reprojection_error")
        rms = None if rms_node.empty() else float(rms_node.real())
    finally:
        fs.release()
    try:
        return Camera(K, np.asarray(dist).reshape(-1), (int(width), int(height)), rms, f"OpenCV file {path}")
    except CaptureError as exc:
        raise CaptureError(f"{path}: {exc}") from None


# ------------------------------------------------------------------------------------- dispatch
def read_camera(path: str | os.PathLike) -> Camera:
    """Read a camera file: ``.json`` (ours) or ``.yaml``/``.yml``/``.xml`` (OpenCV)."""
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".json":
        return read_camera_json(path)
    if suffix in OPENCV_SUFFIXES:
        return read_camera_opencv(path)
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
