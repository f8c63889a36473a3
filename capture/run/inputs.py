"""Inputs of ``capture run``: the typed config and its resolution into checked, loaded inputs.

Everything a user can get wrong is checked here, before anything is written: the video opens and has
frames, the actor exists, the camera fits the video (a pure resize is adjusted and reported), the
detector's spec matches its model, the actor has a landmark embedding for the detector, ``--frames``
parses and lies in the video, ``--formats`` are known. Each problem is one
:class:`~capture.io.errors.CaptureError` line.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from capture.export.base import DEFAULT_OVERLAY, OVERLAY_LAYERS
from capture.io.errors import CaptureError
from capture.run.store import digest, file_sha256

DEFAULT_FORMATS = ("obj", "usd", "npz", "overlay")


@dataclass
class RunConfig:
    """Settings of ``capture run`` (saved resolved, as plain data, in ``run.json`` and ``report.json``)."""

    video: Path
    actor: str
    camera: Path | None = None          # None: the documented default guess from the frame size
    detector: Path | None = None        # None: the one ONNX in VIDEO's folder/detector/
    out: Path | None = None             # None: ./runs/<video stem>
    frames: str | None = None           # "START:END" (END exclusive), either side may be empty
    formats: tuple[str, ...] = DEFAULT_FORMATS
    preset: str = "default"
    seed: int = 0
    iterations: int | None = None       # None: the preset's
    device: str = "cpu"
    window: int = 30
    overlap: int = 6
    overwrite: bool = False
    progress: bool = True
    threads: int = 1                    # torch and onnxruntime threads
    segments: tuple | None = None       # capture batch: the fit is stitched from these (start, end) segments
    overlay: tuple[str, ...] = DEFAULT_OVERLAY  # overlay.mp4 layers (--overlay), see capture.export.base
    side_processes: bool = True         # the streamed fit (capture.fit.process) and the report's figures
                                        # (capture.export.report_figures) in processes of their own; capture
                                        # batch turns it off: a take there is a Ray task with a CPU budget

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("video", "camera", "detector", "out"):
            d[k] = None if d[k] is None else str(d[k])
        d["formats"] = list(self.formats)
        d["overlay"] = list(self.overlay)
        return d


def parse_formats(text: str | None, default: tuple[str, ...] = DEFAULT_FORMATS) -> tuple[str, ...]:
    """``"obj,usd"`` -> ``("obj", "usd")`` (:func:`capture.export.parse_formats`); None: ``default``."""
    from capture.export import parse_formats as parse

    if text is None or not text.strip():
        return tuple(default)
    return parse(text)


def parse_overlay(text: str | None) -> tuple[str, ...]:
    """``"mesh,landmarks"`` -> the overlay's layers (order kept); None: the default; ``none``: only the frame.

    Raises CaptureError (one line listing the known layers) for an unknown name."""
    if text is None or not text.strip():
        return DEFAULT_OVERLAY
    names: list[str] = []
    for raw in text.split(","):
        name = raw.strip().lower()
        if name in ("", "none"):
            continue
        if name not in OVERLAY_LAYERS:
            raise CaptureError(f"unknown overlay layer '{name}' in --overlay; known layers: "
                               f"{', '.join(OVERLAY_LAYERS)} (or none)")
        if name not in names:
            names.append(name)
    return tuple(names)


def parse_frame_range(text: str | None, n_frames: int) -> tuple[int, int]:
    """``"START:END"`` (END exclusive; empty sides mean 0 and the end; negative counts from the end).

    Returns ``(start, end)`` with ``0 <= start < end <= n_frames``.
    """
    if text is None or text.strip() in ("", ":"):
        return 0, n_frames
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        start = int(parts[0]) if parts[0].strip() else 0
        end = int(parts[1]) if parts[1].strip() else n_frames
    except ValueError:
        raise CaptureError(f"--frames must look like START:END (e.g. 0:100, 50:, :200), got '{text}'") from None
    if start < 0:
        start += n_frames
    if end < 0:
        end += n_frames
    if not (0 <= start < end <= n_frames):
        raise CaptureError(f"--frames {text} is outside the video's frames 0..{n_frames - 1} (or empty); "
                           f"give START:END with 0 <= START < END <= {n_frames}")
    return start, end


def default_detector(video: Path) -> Path:
    """The single ONNX detector in ``VIDEO's folder/detector/`` (as ``capture synth`` writes), else an error."""
    d = video.parent / "detector"
    found = sorted(p for p in d.glob("*.onnx") if p.with_suffix(".json").is_file()) if d.is_dir() else []
    if len(found) != 1:
        why = "none" if not found else f"{len(found)}"
        raise CaptureError(f"no --detector given and {d} holds {why} ONNX detector(s) with a spec; pass "
                           f"--detector FILE.onnx (with its FILE.json spec, see docs/detector_spec.md)")
    return found[0]


@dataclass
class ResolvedCamera:
    camera: object                     # calib.camera.Camera for the video's upright frame size
    source: str                        # file path or "default"
    note: str                          # one line for the summary (resize, default guess)


def resolve_camera(path: Path | None, width: int, height: int) -> ResolvedCamera:
    """The camera for ``width x height`` frames: the file's (resized when only the scale differs) or the default."""
    from calib.camera import default_camera
    from calib.camera_io import read_camera

    if path is None:
        cam = default_camera(width, height)
        return ResolvedCamera(cam, "default", f"no --camera: DEFAULT GUESS ({cam.describe()}); calibrate for "
                                              f"accurate results")
    path = Path(path)
    if path.is_dir():
        raise CaptureError(f"camera file {path} is a folder; give the camera file (.json, .yaml or .xml) with --camera")
    if not path.is_file():
        raise CaptureError(f"camera file {path} does not exist; check --camera")
    cam = read_camera(path)
    if cam.image_size == (width, height):
        return ResolvedCamera(cam, str(path), f"camera {path.name}: {cam.describe()}")
    a_cam, a_vid = cam.width / cam.height, width / height
    if abs(a_vid / a_cam - 1.0) > 0.01:
        hint = (" (the video is rotated: calibrate with upright footage of the same camera)"
                if abs((height / width) / a_cam - 1.0) <= 0.01 else "")
        raise CaptureError(f"camera {path} is for {cam.width}x{cam.height} frames but the video's upright frames "
                           f"are {width}x{height} (another aspect ratio){hint}; use the camera of this video or crop "
                           f"the calibration to match")
    adj = cam.for_frame_size(width, height)
    return ResolvedCamera(adj, str(path), f"camera {path.name} calibrated at {cam.width}x{cam.height}, resized to "
                                          f"the video's {width}x{height}")


@dataclass
class RunInputs:
    """Checked and loaded inputs of one run."""

    config: RunConfig
    out: Path
    video_info: object                 # capture.io.video.VideoInfo
    video_id: str
    frame_range: tuple[int, int]
    actor: object                      # capture.actor.package.Actor
    actor_weights_sha256: str
    camera: ResolvedCamera
    detector: object                   # capture.detector.Detector
    landmark_points: np.ndarray        # (L, 3) template mm
    embedding_sha256: str
    fit_settings: object               # models.fit.FitSettings
    notes: list[str] = field(default_factory=list)


def resolve_fit_settings(preset: str, seed: int, iterations: int | None = None, kind: str = "2d"):
    """The fit preset with ``seed`` and, when given, ``iterations`` (later windows: at most as many);
    ``kind`` ``2d`` (landmark fits, :data:`models.fit.FIT_PRESETS`) or ``3d`` (mesh fits, ``FIT3D_PRESETS``)."""
    from dataclasses import replace

    from models.fit_settings import FIT3D_PRESETS, FIT_PRESETS

    presets = FIT3D_PRESETS if kind == "3d" else FIT_PRESETS
    if preset not in presets:
        raise CaptureError(f"unknown fit preset '{preset}'; use one of {', '.join(presets)}")
    s = replace(presets[preset], seed=int(seed))
    if iterations is not None:
        if iterations < 1:
            raise CaptureError(f"--iterations must be at least 1, got {iterations}")
        warm = None if s.warm_iterations is None else min(s.warm_iterations, int(iterations))
        s = replace(s, iterations=int(iterations), warm_iterations=warm)
    return s


def check_device(device: str) -> None:
    if device == "cpu":      # without importing torch
        return
    import torch

    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError):
        raise CaptureError(f"unknown --device '{device}'; use cpu or cuda") from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise CaptureError(f"--device {device}: no CUDA GPU is available to torch here; use --device cpu")


def check_window(window: int, overlap: int) -> None:
    if window < 2 or overlap < 0 or overlap >= window:
        raise CaptureError(f"--window must be at least 2 frames and larger than the overlap {overlap}; got {window}")


def resolve_inputs(cfg: RunConfig) -> RunInputs:
    """Open and check every input of ``capture run``; nothing is written."""
    from capture.actor.package import WEIGHTS, load_actor
    from capture.detector import Detector, embedded_points, read_embedding
    from capture.detector.embedding import embedding_path
    from capture.io.video import open_video, video_identity

    check_window(cfg.window, cfg.overlap)
    check_device(cfg.device)
    if cfg.threads < 1:
        raise CaptureError(f"--threads must be at least 1, got {cfg.threads}")
    settings = resolve_fit_settings(cfg.preset, cfg.seed, cfg.iterations)
    with open_video(cfg.video) as reader:
        info = reader.info
    if info.fps <= 0:
        raise CaptureError(f"video {cfg.video} has no frame rate in its header; re-encode it with a frame rate")
    frame_range = parse_frame_range(cfg.frames, info.frame_count)
    actor = load_actor(cfg.actor, device=cfg.device)
    camera = resolve_camera(cfg.camera, info.width, info.height)
    det_path = Path(cfg.detector) if cfg.detector is not None else default_detector(Path(cfg.video))
    detector = Detector.load(det_path, threads=cfg.threads)
    emb_file = embedding_path(actor.path, detector.name)
    if not emb_file.is_file():
        raise CaptureError(f"actor '{actor.name}' has no landmark embedding for detector '{detector.name}' "
                           f"({emb_file} is missing); make one with 'capture actor embed {cfg.actor} --detector "
                           f"{det_path} --vertices/--triangles/--points/--mesh ...' (docs/byo_detector.md)")
    emb = read_embedding(actor.path, detector.name, actor.template_arrays, detector.count)
    points = embedded_points(emb, actor.template_arrays)
    out = Path(cfg.out) if cfg.out is not None else Path("runs") / Path(cfg.video).stem
    notes = [camera.note]
    from capture.actor.package import is_bundled

    if is_bundled(actor.path):
        notes.append(f"actor '{cfg.actor}': the bundled actor {actor.path}")
    if cfg.detector is None:
        notes.append(f"detector {det_path} (found beside the video)")
    return RunInputs(config=cfg, out=out, video_info=info, video_id=video_identity(cfg.video),
                     frame_range=frame_range, actor=actor,
                     actor_weights_sha256=file_sha256(Path(actor.path) / WEIGHTS), camera=camera,
                     detector=detector, landmark_points=points,
                     embedding_sha256=digest(emb.to_json()),
                     fit_settings=settings, notes=notes)
