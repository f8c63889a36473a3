"""``capture synth``: render a take of an actor with known truth, and the detector that reads it.

Outputs in the take directory (all written atomically; ``truth.json`` last, it marks a finished take)::

    take.mp4                     the video (lossless H.264 RGB by default, see capture.synth.video)
    take_look.mp4                with --look only: the same frames Lambert-shaded, for people
                                 (capture.synth.look; nothing reads it, the detector reads take.mp4)
    camera.json                  the camera used (calib.camera_io)
    truth_meshes.npz             vertices (T, V, 3) float32 mm, camera frame; faces (F, 3) int32
    truth_params.npz             head_R (T,3,3), head_t (T,3) mm: x_cam = head_R x + head_t for a head-frame x;
                                 jaw_R (T,3,3), jaw_t (T,3) mm (the model's jaw transform about its pivot);
                                 coefficients (T, N-1); shape_names; yaw/pitch/roll_deg (T,); jaw_open (T,)
    truth_landmarks.npz          points_2d (T, L, 2) px (pixel centres at integers, with distortion),
                                 visible (T, L) bool, depth_mm (T, L), points_3d (T, L, 3) camera mm,
                                 face_index (L,), barycentric (L, 3)
    detector/<name>.onnx, .json  the synthetic dense detector and its spec (docs/detector_spec.md)
    meshes/frame_XXXXXX.obj      with --obj only
    truth.json                   resolved settings, seed, timings, versions, files

With ``meshes`` (``capture synth --meshes SEQ``, :mod:`capture.synth.mesh_sequence`) the face of each
frame is the given registered mesh (template frame, mm) instead of the actor's model, with the preset's
head motion on top: the truth of shapes outside the actor's span.

The actor package gets ``landmarks/<name>.json`` (the detector's embedding; exact by construction).
Truth meshes are in the camera frame; the head-frame mesh of frame j is
``head_R[j]^T (v - head_t[j])``.
"""

from __future__ import annotations

import platform
import shutil
import time
from contextlib import ExitStack
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from calib.camera import Camera, default_camera
from calib.camera_io import check_camera_plausible, read_camera, write_camera
from capture.actor.package import load_actor, user_copy_of_bundled
from capture.io.atomic import atomic_path, write_bytes, write_json
from capture.io.errors import CaptureError
from capture.synth import scene
from capture.synth.detector_onnx import (LandmarkSet, build_detector, embedding_dict, export_onnx, landmark_colours,
                                         sample_landmarks, spec_dict)
from capture.synth.look import shade
from capture.synth.mesh_sequence import read_mesh_sequence
from capture.synth.motion import PRESETS, generate_motion, preset_dict
from capture.synth.raster import Raster, rasterize, sample_nearest
from capture.synth.texture import BACKGROUND, PositionCode, dither_to_uint8
from capture.synth.video import CODECS, DEFAULT_CRF, VideoWriter
from models.rotation import matrix_to_rot6d, rot6d_to_matrix

TRUTH_JSON = "truth.json"
VIDEO = "take.mp4"
LOOK_VIDEO = "take_look.mp4"
LOOK_CRF = 18

#: Visibility: a landmark is visible when it faces the camera (cosine between its outward normal and
#: the ray to the camera above this) and its depth is within the tolerance of the z-buffer.
FACING_MIN_COS = 0.1
DEPTH_TOL_MM = 1.0


@dataclass
class SynthConfig:
    """Settings of ``capture synth`` (saved resolved in truth.json)."""

    actor: str
    out: Path
    frames: int = 150
    fps: float = 25.0
    size: tuple[int, int] | None = None          # None: the camera file's size, else 1280x720
    preset: str = "talk"
    seed: int = 0
    landmarks: int = 1000
    distortion: tuple[float, ...] | None = None
    camera: Path | None = None
    codec: str = "h264-lossless"
    crf: int = DEFAULT_CRF
    detector_size: int = 768
    obj: bool = False
    look: bool = False
    overwrite: bool = False
    meshes: Path | None = None                   # a mesh sequence to render (capture.synth.mesh_sequence)
    units: str = "mm"                            # units of --meshes


def parse_size(text: str | None) -> tuple[int, int] | None:
    """``"1280x720"`` -> ``(1280, 720)``; None stays None."""
    if text is None:
        return None
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise CaptureError(f"--size must look like 1280x720, got '{text}'") from None
    return w, h


@dataclass
class FrameTruth:
    """Everything known about one rendered frame."""

    image: np.ndarray            # (H, W, 3) uint8 RGB
    raster: Raster
    points_2d: np.ndarray        # (L, 2)
    points_3d: np.ndarray        # (L, 3) camera mm
    visible: np.ndarray          # (L,) bool


def detector_name(count: int) -> str:
    return f"synthetic_dense_{count}"


def _check_config(cfg: SynthConfig) -> None:
    if cfg.preset not in PRESETS:
        raise CaptureError(f"unknown preset '{cfg.preset}'; choose one of {', '.join(PRESETS)}")
    if cfg.frames < 1:
        raise CaptureError(f"--frames must be at least 1, got {cfg.frames}")
    if not 0 < cfg.fps <= 240:
        raise CaptureError(f"--fps must be in (0, 240], got {cfg.fps}")
    if not 3 <= cfg.landmarks <= 20000:
        raise CaptureError(f"--landmarks must be between 3 and 20000, got {cfg.landmarks}")
    if cfg.codec not in CODECS:
        raise CaptureError(f"unknown codec '{cfg.codec}'; choose one of {', '.join(CODECS)}")
    if not 0 <= cfg.crf <= 51:
        raise CaptureError(f"--crf must be in 0..51, got {cfg.crf}")
    if cfg.size is not None and (cfg.size[0] < 16 or cfg.size[1] < 16 or cfg.size[0] % 2 or cfg.size[1] % 2):
        raise CaptureError(f"--size must be even and at least 16x16 (H.264), got {cfg.size[0]}x{cfg.size[1]}")
    if cfg.size is not None and max(cfg.size) > 8192:
        raise CaptureError(f"--size {cfg.size[0]}x{cfg.size[1]} is larger than 8192 pixels a side (8K); give a smaller "
                           f"frame size")


def _prepare_out(out: Path, overwrite: bool) -> None:
    if out.exists() and not out.is_dir():
        raise CaptureError(f"--out {out} is a file; give a directory")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise CaptureError(f"--out {out} exists and is not empty; pass --overwrite or choose another folder")
        if not (out / TRUTH_JSON).is_file() and not (out / VIDEO).exists():
            raise CaptureError(f"--out {out} is not a synthetic take (no {TRUTH_JSON}); refusing to overwrite it")
        shutil.rmtree(out)
    out.mkdir(parents=True, exist_ok=True)


def resolve_camera(cfg: SynthConfig) -> Camera:
    """The camera of the take: the given file (adjusted to --size) or the default guess; --distortion
    replaces its distortion coefficients."""
    if cfg.camera is not None:
        cam = read_camera(cfg.camera)
        if cfg.size is not None:
            cam = cam.for_frame_size(*cfg.size)
    else:
        w, h = cfg.size or (1280, 720)
        cam = default_camera(w, h)
        cam = Camera(cam.K, cam.dist, cam.image_size, None,
                     "capture synth: 60 deg horizontal field of view, centred principal point", False)
    if cfg.distortion is not None:
        cam = Camera(cam.K, np.asarray(cfg.distortion, dtype=np.float64), cam.image_size, cam.rms,
                     f"{cam.provenance}; distortion {list(cfg.distortion)} from capture synth", cam.is_default)
        check_camera_plausible(cam, f"--distortion {','.join(f'{v:g}' for v in cfg.distortion)}")
    if cam.width % 2 or cam.height % 2:
        raise CaptureError(f"frame size {cam.width}x{cam.height} must be even for H.264")
    return cam


def expression_names(actor) -> list[str]:
    """Names of the N-1 expression shapes, in the order of the model's expression basis."""
    names = actor.shape_names
    if len(names) == actor.config.n_expressions + 1:
        neutral = actor.metadata.get("neutral", names[0])
        names = [n for n in names if n != neutral] if neutral in names else names[1:]
    if len(names) != actor.config.n_expressions:
        raise CaptureError(f"actor '{actor.name}' lists {len(names)} expression shapes but its model has "
                           f"{actor.config.n_expressions}; retrain the actor")
    return list(names)


def jaw_transforms(actor, jaw_shape: int | None, jaw_open: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame jaw rotations (T, 3, 3) and translations (T, 3) mm: the learned transform of the
    jawOpen-like shape scaled by the opening fraction (rotation by its angle, translation linearly)."""
    T = len(jaw_open)
    if jaw_shape is None:
        return np.repeat(np.eye(3)[None], T, 0), np.zeros((T, 3))
    R_open = rot6d_to_matrix(actor.jaw_rot6d[jaw_shape].double()).numpy()
    t_open = actor.jaw_t[jaw_shape].double().numpy()
    rotvec = Rotation.from_matrix(R_open).as_rotvec()
    R = Rotation.from_rotvec(jaw_open[:, None] * rotvec[None]).as_matrix()
    return R, jaw_open[:, None] * t_open[None]


def visibility(raster: Raster, points_cam: np.ndarray, normals_cam: np.ndarray, uv: np.ndarray,
               camera: Camera) -> np.ndarray:
    """Landmarks ``(L,)`` that face the camera and are not hidden (depth within tolerance of the
    z-buffer at their nearest pixel; the tolerance grows with the surface's slope)."""
    w, h = camera.image_size
    ray = -points_cam / np.linalg.norm(points_cam, axis=1, keepdims=True)
    cos = np.einsum("lc,lc->l", normals_cam, ray)
    inside = (uv[:, 0] > -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] > -0.5) & (uv[:, 1] < h - 0.5)
    zbuf = sample_nearest(raster.depth, uv)
    px_mm = points_cam[:, 2] / camera.fx
    tan = np.sqrt(np.clip(1.0 - cos ** 2, 0, None)) / np.clip(cos, FACING_MIN_COS, None)
    tol = DEPTH_TOL_MM + 0.75 * px_mm * tan
    return inside & (cos > FACING_MIN_COS) & (points_cam[:, 2] <= zbuf + tol)


def render_frame(vertices_cam: np.ndarray, faces: np.ndarray, colours: np.ndarray, camera: Camera,
                 landmarks: LandmarkSet) -> FrameTruth:
    """Render one frame of the position-coded face and its landmark truth."""
    uv = scene.project(camera, vertices_cam)
    raster = rasterize(uv, vertices_cam[:, 2], faces, camera.image_size)
    image = dither_to_uint8(raster.interpolate(colours, faces, BACKGROUND))
    tri = vertices_cam[faces[landmarks.face_index]]                      # (L, 3, 3)
    p3 = np.einsum("lk,lkc->lc", landmarks.barycentric, tri)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True).clip(1e-12)
    p2 = scene.project(camera, p3[None])[0]
    return FrameTruth(image, raster, p2, p3, visibility(raster, p3, n, p2, camera))


def synthesize(cfg: SynthConfig, on_stage: Callable[[str, int], None] | None = None,
               on_frame: Callable[[], None] | None = None) -> Path:
    """Render the take described by ``cfg`` (see the module docstring); returns the take directory.

    ``on_stage(description, total)`` and ``on_frame()`` report progress (the command line shows bars).
    """
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    _check_config(cfg)
    actor = load_actor(cfg.actor)
    camera = resolve_camera(cfg)
    sequence = None
    if cfg.meshes is not None:  # the expressions come from the meshes, the head motion from the preset
        sequence = read_mesh_sequence(cfg.meshes, len(actor.template.vertices), cfg.units)[:cfg.frames]
        cfg = replace(cfg, frames=len(sequence))
    out = Path(cfg.out)
    _prepare_out(out, cfg.overwrite)
    stage = on_stage or (lambda d, n: None)
    tick = on_frame or (lambda: None)

    # --- motion and model evaluation
    t0 = time.perf_counter()
    template = actor.template
    tv = np.asarray(template.vertices, dtype=np.float64)
    faces = np.asarray(template.faces, dtype=np.int64)
    names = expression_names(actor)
    angles = np.degrees(np.linalg.norm(Rotation.from_matrix(
        rot6d_to_matrix(actor.jaw_rot6d.double()).numpy()).as_rotvec(), axis=1))
    motion = generate_motion(PRESETS[cfg.preset], cfg.frames, cfg.fps, names, cfg.seed, angles)
    if sequence is not None:
        motion.jaw_open[:] = 0.0
        motion.coefficients[:] = 0.0
        motion.jaw_shape = None
    jaw_R, jaw_t = jaw_transforms(actor, motion.jaw_shape, motion.jaw_open)
    head_R, head_t = scene.head_transforms(camera, tv, motion.yaw_deg, motion.pitch_deg, motion.roll_deg,
                                           motion.offset_mm)
    if sequence is not None:
        verts_head = sequence.astype(np.float32)
    else:
        with torch.no_grad():
            c = torch.as_tensor(tv, dtype=torch.float32)
            anatomy = actor.model(c)
            verts_head = np.empty((cfg.frames, len(tv), 3), dtype=np.float32)
            for s in range(0, cfg.frames, 64):
                e = min(cfg.frames, s + 64)
                verts_head[s:e] = actor.model.shape(
                    anatomy, matrix_to_rot6d(torch.as_tensor(jaw_R[s:e], dtype=torch.float32)),
                    torch.as_tensor(jaw_t[s:e], dtype=torch.float32),
                    torch.as_tensor(motion.coefficients[s:e], dtype=torch.float32)).numpy()
    verts_cam = scene.to_camera(verts_head.astype(np.float64), head_R, head_t).astype(np.float32)
    timings["model_s"] = time.perf_counter() - t0

    # --- landmarks, colour code, detector
    t0 = time.perf_counter()
    code = PositionCode.for_template(tv)
    colours = code.encode(tv)
    landmarks = sample_landmarks(template, cfg.landmarks, seed=0)
    name = detector_name(cfg.landmarks)
    detector = build_detector(landmark_colours(colours, faces, landmarks), cfg.detector_size, code.levels_per_mm)
    onnx_bytes = export_onnx(detector)
    timings["detector_build_s"] = time.perf_counter() - t0

    # --- render and encode
    t0 = time.perf_counter()
    T, L = cfg.frames, cfg.landmarks
    pts2 = np.zeros((T, L, 2), np.float32)
    pts3 = np.zeros((T, L, 3), np.float32)
    vis = np.zeros((T, L), bool)
    stage("rendering", T)
    with ExitStack() as stack:
        tmp = stack.enter_context(atomic_path(out / VIDEO))
        writer = stack.enter_context(VideoWriter(tmp, camera.image_size, cfg.fps, cfg.codec, cfg.crf))
        look_writer = None
        if cfg.look:
            look_tmp = stack.enter_context(atomic_path(out / LOOK_VIDEO))
            look_writer = stack.enter_context(VideoWriter(look_tmp, camera.image_size, cfg.fps, "h264", LOOK_CRF))
        for j in range(T):
            fr = render_frame(verts_cam[j].astype(np.float64), faces, colours, camera, landmarks)
            writer.write(fr.image)
            if look_writer is not None:
                look_writer.write(shade(fr.raster, verts_cam[j].astype(np.float64), faces))
            pts2[j], pts3[j], vis[j] = fr.points_2d, fr.points_3d, fr.visible
            tick()
    timings["render_encode_s"] = time.perf_counter() - t0

    # --- files
    t0 = time.perf_counter()
    write_camera(out / "camera.json", camera)
    _write_npz(out / "truth_meshes.npz", vertices=verts_cam, faces=faces.astype(np.int32))
    _write_npz(out / "truth_params.npz", head_R=head_R.astype(np.float32), head_t=head_t.astype(np.float32),
               jaw_R=jaw_R.astype(np.float32), jaw_t=jaw_t.astype(np.float32),
               coefficients=motion.coefficients.astype(np.float32), shape_names=np.array(names, dtype=str),
               yaw_deg=motion.yaw_deg, pitch_deg=motion.pitch_deg, roll_deg=motion.roll_deg,
               jaw_open=motion.jaw_open, fps=np.float64(cfg.fps))
    _write_npz(out / "truth_landmarks.npz", points_2d=pts2, visible=vis,
               depth_mm=pts3[..., 2], points_3d=pts3, face_index=landmarks.face_index.astype(np.int32),
               barycentric=landmarks.barycentric.astype(np.float32))
    if cfg.obj:
        stage("writing OBJ meshes", T)
        for j in range(T):
            mesh = trimesh.Trimesh(verts_cam[j], faces, process=False)
            write_bytes(out / "meshes" / f"frame_{j:06d}.obj", trimesh.exchange.obj.export_obj(mesh).encode())
            tick()
    source = (f"capture synth: {L} points by farthest-point sampling on the front of the template; "
              "exact (the detector finds their position colour)")
    embedding = embedding_dict(name, landmarks, source)
    write_bytes(out / "detector" / f"{name}.onnx", onnx_bytes)
    write_json(out / "detector" / f"{name}.json", spec_dict(name, L, cfg.detector_size))
    # the embedding goes into the actor's package; a bundled actor is read-only, so into the user's copy of it
    emb_actor, copy_note = user_copy_of_bundled(actor.path, None if Path(cfg.actor).is_dir() else cfg.actor)
    write_json(emb_actor / "landmarks" / f"{name}.json", embedding)
    timings["files_s"] = time.perf_counter() - t0
    timings["total_s"] = time.perf_counter() - t_start
    timings["render_per_frame_s"] = timings["render_encode_s"] / T

    settings = {k: (str(v) if isinstance(v, Path) else v) for k, v in asdict(cfg).items()}
    settings["size"] = list(camera.image_size)
    settings["distortion"] = camera.dist.tolist()
    report = {
        "format": "capture-synth-take", "version": 1,
        "actor": {"name": actor.name, "path": str(actor.path), "embedding_in": str(emb_actor), "note": copy_note},
        "settings": settings,
        "seed": cfg.seed,
        "preset": preset_dict(PRESETS[cfg.preset]),
        "camera": camera.describe(),
        "conventions": {"head": "x_cam = head_R @ x_head + head_t (mm); see capture/synth/scene.py",
                        "pixels": "OpenCV, pixel centres at integer coordinates",
                        "meshes": "truth_meshes.npz vertices in camera coordinates (mm)"},
        "jaw_shape": None if motion.jaw_shape is None else names[motion.jaw_shape],
        "meshes": (None if cfg.meshes is None else
                   {"source": str(cfg.meshes), "units": cfg.units, "frames": T,
                    "note": "expressions from the mesh sequence (template frame), head motion of the preset on "
                            "top; truth_params jaw and coefficients are not known (rest and 0)"}),
        "colour_code": {**code.to_dict(), "quantisation": "ordered 4x4 Bayer dither (capture.synth.texture)"},
        "detector": {"name": name, "onnx": f"detector/{name}.onnx", "spec": f"detector/{name}.json",
                     "embedding": str(emb_actor / "landmarks" / f"{name}.json")},
        "video": {"file": VIDEO, "codec": cfg.codec, "crf": cfg.crf if cfg.codec == "h264" else 0,
                  "fps": cfg.fps, "frames": T},
        "look_video": ({"file": LOOK_VIDEO, "codec": "h264", "crf": LOOK_CRF,
                        "note": "Lambert-shaded for people; not read by the detector (capture.synth.look)"}
                       if cfg.look else None),
        "visible_fraction": float(vis.mean()),
        "motion_ranges_deg": {k: [float(v.min()), float(v.max())] for k, v in
                              (("yaw", motion.yaw_deg), ("pitch", motion.pitch_deg), ("roll", motion.roll_deg))},
        "timings": {k: round(v, 3) for k, v in timings.items()},
        "versions": {"python": platform.python_version(), "numpy": np.__version__, "torch": torch.__version__},
        "files": sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and "meshes" not in p.parts)
        + [TRUTH_JSON],
    }
    write_json(out / TRUTH_JSON, report)
    return out


def _write_npz(path: Path, **arrays) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **arrays)
