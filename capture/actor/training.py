"""The actor-training stage: registered shapes (+ bones) in, actor package out, resumable.

``train_actor(options)`` loads and checks the shapes, finds the face frame and forehead, computes
the sparse anatomical constraints against the given bones (or an estimated bone surface), trains
the model with progress, checkpoints to ``A/training/`` every ``checkpoint_seconds`` and on
interrupt (Ctrl-C or SIGTERM), and writes the package. Running the same command again resumes an
unfinished training; a finished actor is only replaced with ``overwrite``.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import json
import os
import platform
import shutil
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import trimesh

import capture
from capture.actor.package import TRAINING_DIR, actor_dir, is_actor, remove_actor, save_actor
from capture.io.atomic import atomic_path, write_bytes, write_json
from capture.io.errors import CaptureError, read_text_file, Interrupted
from capture.io.machine import machine
from capture.io.signals import sigterm_as_interrupt
from capture.io.meshes import ShapeSet, load_mesh, load_shape_dir, units_scale
from models.anatomy_constraints import AnatomyConstraints, compute_anatomy_constraints, default_trusted_region
from models.bone_estimate import estimate_bone_surface
from models.face_frame import FaceFrame, estimate_face_frame, estimate_jaw_pivot, forehead_region, midline_landmarks
from models.input_chart import Tearing, opened, parted_vertices, tearing_shape
from models.jaw_motion import find_jaw_opening
from models.mirror import (ONE_SIDED_THRESHOLD, MirrorMap, mirror_displacements, mirror_points, mirrored_name,
                           one_sided, other_side)
from models.precision import HIDDEN_MATMUL
from models.rotation import rot6d_to_matrix
from models.touching import touching_pairs
from models.train import PRESETS, ActorTrainer, Evaluation, TrainingData, TrainSettings, model_config_for


@dataclass
class TrainOptions:
    """Inputs of ``capture actor train`` (resolved, plain data)."""

    actor: str
    shapes: Path
    neutral: str | None = None
    skull: Path | None = None
    jaw: Path | None = None
    units: str = "mm"
    bone_units: str | None = None        # default: same as ``units``
    preset: str = "default"
    overrides: dict = field(default_factory=dict)   # TrainSettings fields changed on the command line
    symmetry_plane: tuple[float, float, float, float] | None = None  # (nx, ny, nz, offset_mm)
    forehead: Path | None = None         # vertex index list
    trusted: Path | None = None          # vertex index list for the constraints
    device: str = "cpu"
    threads: int = 0                     # torch CPU threads while training (0 = leave torch's setting)
    overwrite: bool = False
    checkpoint_seconds: float = 60.0
    eval_every: int = 50
    mirror: bool = True                  # add the other side of one-sided shapes (models.mirror)
    jaw_from_motion: bool = True         # without a jaw mesh, read the jaw from the shapes (models.jaw_motion)


def resolve_settings(preset: str, overrides: dict) -> TrainSettings:
    """The preset with command-line overrides applied."""
    if preset not in PRESETS:
        raise CaptureError(f"unknown preset '{preset}': use one of {', '.join(PRESETS)}")
    base = PRESETS[preset]
    unknown = set(overrides) - set(TrainSettings.__dataclass_fields__)
    if unknown:
        raise CaptureError(f"unknown training setting(s): {', '.join(sorted(unknown))}")
    settings = replace(base, **{k: v for k, v in overrides.items() if v is not None})
    if settings.iterations < 1 or settings.lr <= 0 or settings.width < 1 or settings.depth < 1:
        raise CaptureError("iterations, lr, width and depth must be positive")
    if settings.hidden_matmul not in HIDDEN_MATMUL:
        raise CaptureError(f"unknown --hidden-matmul '{settings.hidden_matmul}': use one of {', '.join(HIDDEN_MATMUL)}")
    if not 0 <= settings.input_chart < 1:
        raise CaptureError(f"--input-chart must be a fraction in [0, 1) (got {settings.input_chart}); 0.3 is the "
                           f"default, 0 reads every point where it is, as in the paper")
    return settings


def read_vertex_list(path: Path, n_vertices: int, what: str) -> np.ndarray:
    """A vertex selection file: JSON list of indices, or whitespace/comma separated integers."""
    if not path.is_file():
        raise CaptureError(f"{what} file not found: {path}")
    text = read_text_file(path, f"{what} file")
    try:
        values = json.loads(text) if text.lstrip().startswith("[") else [int(v) for v in text.replace(",", " ").split()]
        idx = np.asarray(values, dtype=np.int64).reshape(-1)
    except (ValueError, TypeError, json.JSONDecodeError):
        raise CaptureError(f"{what} file {path} must hold vertex indices (a JSON list or integers separated by spaces)") from None
    if idx.size == 0 or idx.min() < 0 or idx.max() >= n_vertices:
        raise CaptureError(f"{what} file {path}: indices must lie in 0..{n_vertices - 1} (found "
                           f"{'none' if idx.size == 0 else f'{idx.min()}..{idx.max()}'})")
    return np.unique(idx)


def _fingerprint(files: list[Path], settings: dict) -> str:
    h = hashlib.sha256()
    for f in files:
        h.update(str(f.name).encode())
        h.update(f.read_bytes())
    h.update(json.dumps(settings, sort_keys=True).encode())
    return h.hexdigest()


def _constraint_template_points(con: AnatomyConstraints, template: np.ndarray, faces: np.ndarray) -> np.ndarray:
    tri = template[faces[con.face_index]]                       # (M, 3, 3)
    return np.einsum("mk,mkc->mc", con.barycentric, tri)


#: The final weights are replaced by the best evaluated ones of the session when their error is this much higher.
KEEP_BEST_MARGIN = 1.02

#: How far towards the lip-parting shape the neutral is opened where the mirror matches points (0 = the neutral).
MIRROR_MATCH_OPEN = 0.3
#: Median distance (mm) of the reflected neutral from itself above which the mirrored shapes are flagged as rough.
MIRROR_ASYMMETRY_WARN_MM = 2.0


def mirror_map(shapes: ShapeSet, frame: FaceFrame, tear: Tearing | None = None) -> MirrorMap:
    """Where each vertex's mirror image lies on the face (:func:`models.mirror.mirror_points`).

    Each reflected vertex is matched where the touching lips are apart: on the neutral ``MIRROR_MATCH_OPEN``
    of the way to the shape that parts them (:func:`models.input_chart.tearing_shape`), as the input chart
    reads it. At the closed neutral a reflected upper-lip vertex can land on the lower lip, and its mirrored
    motion with it (ICT's noseSneer_R made from noseSneer_L: 3.3 mm off ICT's own noseSneer_R at the lip when
    matched closed, 0.3 mm when matched open; BENCHMARKS.md). ``tear``: :func:`models.input_chart.tearing_shape`
    of ``shapes``, found when None."""
    if tear is None:
        tear = tearing_shape(shapes.vertices[0], shapes.faces, shapes.vertices)
    match = opened(shapes.vertices, tear, MIRROR_MATCH_OPEN)
    surface = trimesh.Trimesh(match, shapes.faces, process=False)

    def closest(points):
        pts, _, tri = trimesh.proximity.closest_point(surface, points)
        return pts, tri

    return mirror_points(match, shapes.faces, frame.symmetry_normal, frame.symmetry_offset, closest)


def with_mirrored_shapes(shapes: ShapeSet, frame: FaceFrame,
                         tear: Tearing | None = None) -> tuple[ShapeSet, dict, dict]:
    """``shapes`` plus the other side of each one-sided expression (:mod:`models.mirror`); what was added:
    ``{new name: {"from": source name, "residual": relative residual against the given shapes}}``; and how
    symmetric the neutral is about the plane: ``{"median_mm", "p90_mm"}`` of the reflected vertices'
    distances to the surface where :func:`mirror_map` matches them (0.2 / 0.7 mm on the ICT sample)."""
    v0 = shapes.vertices[0]
    mmap = mirror_map(shapes, frame, tear)
    disp = shapes.vertices[1:] - v0
    mirrored = mirror_displacements(disp, shapes.faces, mmap, frame.symmetry_normal)
    residual = one_sided(disp, mirrored)
    names, verts, added = list(shapes.names), [shapes.vertices], {}
    for k in np.flatnonzero(residual > ONE_SIDED_THRESHOLD):
        if other_side(shapes.names[k + 1]) in shapes.names:     # both sides scanned: the scans win
            continue
        name = mirrored_name(shapes.names[k + 1], set(names))
        names.append(name)
        verts.append((v0 + mirrored[k])[None])
        added[name] = {"from": shapes.names[k + 1], "residual": round(float(residual[k]), 3)}
    asymmetry = {"median_mm": round(float(np.median(mmap.distance)), 3),
                 "p90_mm": round(float(np.percentile(mmap.distance, 90)), 3)}
    return replace(shapes, names=names, vertices=np.concatenate(verts)), added, asymmetry


def prepare(options: TrainOptions, shapes: ShapeSet, report: Callable[[str], None]):
    """Face frame, forehead, bones and constraints for ``shapes`` -> (TrainingData, extras dict).

    With ``options.mirror`` the other side of each one-sided shape is added (``extras["shapes"]`` is the set
    trained on, ``extras["mirrored"]`` says what was added)."""
    neutral = shapes.neutral
    V = len(neutral.vertices)
    frame = estimate_face_frame(neutral.vertices, neutral.faces)
    frame_source = "estimated from the neutral (mirror ICP)"
    if options.symmetry_plane is not None:
        nx, ny, nz, off = options.symmetry_plane
        n = np.array([nx, ny, nz], dtype=np.float64)
        if not np.isfinite(n).all() or np.linalg.norm(n) < 1e-9:
            raise CaptureError("--symmetry-plane needs a non-zero normal: nx,ny,nz,offset_mm")
        norm = np.linalg.norm(n)
        frame = replace(frame, symmetry_normal=n / norm, symmetry_offset=float(off) / norm)
        frame_source = "given by --symmetry-plane"
    mirrored: dict = {}
    asymmetry = None
    tear = tearing_shape(shapes.vertices[0], shapes.faces, shapes.vertices)   # for the mirror and the input chart
    if options.mirror:
        shapes, mirrored, asymmetry = with_mirrored_shapes(shapes, frame, tear)
        if mirrored:
            report("mirrored shapes added (the other side of one-sided expressions): " +
                   ", ".join(f"{n} from {m['from']}" for n, m in mirrored.items()))
            if asymmetry["median_mm"] > MIRROR_ASYMMETRY_WARN_MM:
                report(f"warning: the neutral is {asymmetry['median_mm']:.1f} mm (median) from its own mirror image "
                       f"about the symmetry plane, so the mirrored shapes are rough; check the plane "
                       f"(--symmetry-plane) and the mirrored shapes, or train with --no-mirror")
    if options.forehead is not None:
        fore_idx = read_vertex_list(options.forehead, V, "forehead")
        fore_source = f"file {options.forehead}"
    else:
        fore_idx = np.flatnonzero(forehead_region(neutral.vertices, neutral.faces, frame))
        fore_source = "automatic (upper face band, see models.face_frame)"
    if options.trusted is None:
        trusted = default_trusted_region(neutral, frame)
        trusted_source = "automatic (vertices at least 10 mm from an open border)"
    else:
        trusted_source = f"file {options.trusted}"
        trusted = np.zeros(V, dtype=bool)
        trusted[read_vertex_list(options.trusted, V, "trusted region")] = True

    bone_scale = units_scale(options.bone_units or options.units)
    bones: dict[str, trimesh.Trimesh] = {}
    if options.skull is not None:
        bones["skull"] = load_mesh(options.skull, bone_scale, "skull")
    if options.jaw is not None:
        bones["jaw"] = load_mesh(options.jaw, bone_scale, "jaw")
    estimated = not bones
    if estimated:
        bones["estimated"] = estimate_bone_surface(neutral, frame)
        report("no --skull/--jaw given: using an ESTIMATED bone surface (inward offset of the neutral by "
               "typical soft-tissue thickness); the anatomy is an estimate")
    con = compute_anatomy_constraints(neutral, list(bones.values()), trusted=trusted)
    pivot = estimate_jaw_pivot(frame, neutral.vertices, bones.get("jaw"))
    cpts = _constraint_template_points(con, neutral.vertices, neutral.faces)
    at_points = np.einsum("mk,nmkc->nmc", con.barycentric, shapes.vertices[:, neutral.faces[con.face_index]])
    if "jaw" in bones:
        on_jaw = con.bone_label == list(bones).index("jaw")
        jaw_source = {"from": "mesh", "file": str(options.jaw)}
    elif options.jaw_from_motion:
        on_jaw, jaw_source = jaw_from_motion(shapes, at_points, frame, pivot, report)
    else:
        on_jaw = np.zeros(len(cpts), dtype=bool)
        jaw_source = {"from": "none", "why": "--no-jaw-from-motion"}
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)
    data = TrainingData(
        template=f32(neutral.vertices), shapes=f32(shapes.vertices), constraint_points=f32(cpts),
        bone_target=f32(con.bone_point), thickness_target=f32(con.thickness), normal_target=f32(con.bone_normal),
        forehead_points=f32(neutral.vertices[fore_idx]),
        jaw_points=f32(cpts[on_jaw]),
        jaw_positions=f32(at_points[:, on_jaw]),
        symmetry_normal=f32(frame.symmetry_normal),
        symmetry_offset=float(frame.symmetry_offset),
    )
    extras = dict(frame=frame, frame_source=frame_source, forehead_idx=fore_idx, forehead_source=fore_source,
                  bones=bones, bones_estimated=estimated, constraints=con, jaw_pivot=pivot, jaw_source=jaw_source,
                  trusted_source=trusted_source, shapes=shapes, mirrored=mirrored,
                  mirror_asymmetry=asymmetry, tearing=tear)
    return data, extras


def jaw_from_motion(shapes: ShapeSet, at_points: np.ndarray, frame: FaceFrame, pivot: np.ndarray,
                    report: Callable[[str], None]) -> tuple[np.ndarray, dict]:
    """Without a jaw mesh: which constrained points are jaw, read from the shape that opens the jaw about
    ``pivot`` (:mod:`models.jaw_motion`) -> ((M,) bool, what for the actor's record).

    ``at_points (N, M, 3)``: the constrained points in every shape (neutral first)."""
    neutral = shapes.vertices[0]
    lips = [neutral[ix] for ix in parted_vertices(shapes.vertices, touching_pairs(neutral, shapes.faces))]
    tip = midline_landmarks(neutral, frame).nose_tip
    opening = find_jaw_opening(at_points[0], at_points, frame, pivot, tip, lips)
    if opening is None:
        report("jaw: no jaw mesh, and no shape opens a jaw (a turn of 5 degrees or more about a lateral axis "
               "through the estimated pivot), so the actor has no jaw and opens its mouth by displacements; give "
               "--jaw (and --skull) for one")
        return np.zeros(at_points.shape[1], dtype=bool), {"from": "none", "why": "no shape opens a jaw"}
    name = shapes.names[opening.shape]
    report(f"jaw: no jaw mesh, so it is read from the shapes' motion: {name} turns it {opening.angle_deg:.1f} degrees "
           f"about the estimated pivot; {int(opening.follows.sum())} of {len(opening.follows)} constrained points "
           f"turn with it")
    return opening.follows, {"from": "motion", "shape": name, "angle_deg": opening.angle_deg,
                             "points": int(opening.follows.sum())}


def with_input_chart(data: TrainingData, shapes: ShapeSet, tear: Tearing, fraction: float,
                     report: Callable[[str], None]) -> tuple[TrainingData, dict]:
    """``data`` with the input chart of ``fraction`` (:mod:`models.input_chart`), and what it is for the actor's
    record. ``tear``: :func:`models.input_chart.tearing_shape` of the scans (``extras["tearing"]`` of
    :func:`prepare`; the mirrored shapes come after the scans, so its index holds in ``shapes``)."""
    if fraction <= 0:
        return data, {"fraction": 0.0}
    if tear.shape is None:
        report(f"input chart: none (no shape parts the neutral's touching surfaces; {tear.touching} pairs of "
               f"vertices touch)")
        return data, {"fraction": 0.0, "touching_pairs": tear.touching}
    name = shapes.names[tear.shape]
    report(f"input chart: the networks read the template {fraction:g} of the way to {name}, where "
           f"{tear.pairs} of the neutral's {tear.touching} touching vertex pairs part (worst "
           f"{tear.worst_mm[0]:.2f} -> {tear.worst_mm[1]:.1f} mm)")
    offset = opened(shapes.vertices, tear, fraction) - shapes.vertices[0]
    f32 = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)
    data = replace(data, faces=torch.as_tensor(np.asarray(shapes.faces), dtype=torch.int64), chart_offset=f32(offset))
    return data, {"fraction": fraction, "shape": name, "tearing_pairs": tear.pairs, "touching_pairs": tear.touching,
                  "worst_pair_mm": list(tear.worst_mm)}


@contextlib.contextmanager
def _restore_threads(n: int):
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _load_average() -> tuple[float, ...]:
    """The system's 1/5/15-minute load averages (empty where the OS has none): timings depend on them."""
    try:
        return tuple(round(v, 2) for v in os.getloadavg())
    except (AttributeError, OSError):
        return ()


def _evaluation_metadata(ev: Evaluation, names: list[str]) -> dict:
    return {
        "per_shape": {n: {"mean_mm": m, "max_mm": x} for n, m, x in zip(names, ev.shape_mean_mm, ev.shape_max_mm)},
        "mean_mm": ev.mean_mm, "max_mm": max(ev.shape_max_mm),
        "anatomy": {"bone_mm": ev.bone_mm, "thickness_mm": ev.thickness_mm, "normal_deg": ev.normal_deg},
        "symmetry_mm": ev.symmetry_mm, "forehead_k": ev.forehead_k, "jaw_vertices": ev.jaw_vertices,
    }


def train_actor(options: TrainOptions, progress: "TrainingProgress | None" = None,
                report: Callable[[str], None] = print) -> Path:
    """Train (or resume training) actor ``options.actor``; returns the package directory."""
    out = actor_dir(options.actor)
    if is_actor(out):
        if not options.overwrite:
            raise CaptureError(f"actor '{options.actor}' already exists at {out}; pass --overwrite to retrain it")
        remove_actor(out)
    settings = resolve_settings(options.preset, options.overrides)
    if options.threads < 0:
        raise CaptureError(f"--threads must be 1 or more, or 0 for torch's default (got {options.threads})")
    shapes = load_shape_dir(options.shapes, options.neutral, options.units)
    if options.device != "cpu" and not torch.cuda.is_available() and options.device.startswith("cuda"):
        raise CaptureError(f"device '{options.device}' is not available on this machine; use --device cpu")

    inputs = list(shapes.files)
    for what, p in (("skull", options.skull), ("jaw", options.jaw), ("forehead", options.forehead),
                    ("trusted region", options.trusted)):
        if p is not None:
            if not Path(p).is_file():
                raise CaptureError(f"{what} file not found: {p}")
            inputs.append(Path(p))
    resolved = {
        "preset": options.preset, "settings": settings.to_dict(), "units": options.units,
        "bone_units": options.bone_units or options.units, "neutral": shapes.names[0],
        "symmetry_plane": options.symmetry_plane,
    }
    if not settings.input_chart:  # a training without the chart keeps the fingerprint it had before charts
        del resolved["settings"]["input_chart"]
    # How Adam's moments meet the closed-form solves, and how many constrained points a step draws, change the
    # path, not the problem: not part of what a resumed training must match (actor.json records them).
    for path_only in ("keep_moments_at_solves", "constraint_points_per_step", "sampled_until"):
        del resolved["settings"][path_only]
    fingerprint_no_mirror = _fingerprint(inputs, resolved)   # a training without mirrors keeps the fingerprint it had
    if options.mirror:                                         # before they existed, so it still resumes
        resolved["mirror"] = True
    fingerprint_fixed_jaw = _fingerprint(inputs, resolved)     # likewise a training without a jaw mesh begun
    if options.jaw is None and options.jaw_from_motion:        # before the jaw was read from the shapes
        resolved["jaw_from_motion"] = True
    fingerprint = _fingerprint(inputs, resolved)
    train_dir = out / TRAINING_DIR
    ckpt_path = train_dir / "checkpoint.pt"
    state = None
    if ckpt_path.is_file():
        state = torch.load(ckpt_path, map_location="cpu", weights_only=True)
        if state.get("fingerprint") != fingerprint:
            if not options.overwrite and options.mirror and state.get("fingerprint") == fingerprint_no_mirror:
                raise CaptureError(f"actor '{options.actor}' has an unfinished training started without mirrored shapes "
                                   f"(--no-mirror, or before they were the default); add --no-mirror to resume it, or "
                                   f"pass --overwrite to start over with them")
            if not options.overwrite and state.get("fingerprint") == fingerprint_fixed_jaw != fingerprint:
                raise CaptureError(f"actor '{options.actor}' has an unfinished training started before the jaw was read "
                                   f"from the shapes' motion; add --no-jaw-from-motion to resume it, or pass --overwrite "
                                   f"to start over with the jaw")
            # Settings that were the default before: a training begun under one fingerprinted them so (a training
            # without the chart has no input_chart key); the message names the flag that resumes it.
            earlier_defaults = (
                (settings.input_chart, {k: v for k, v in resolved["settings"].items() if k != "input_chart"},
                 "started without the input chart (before it was the default); add --input-chart 0 to resume it, or "
                 "pass --overwrite to start over with it"),
                (settings.points_per_step, {**resolved["settings"], "points_per_step": 0},
                 "that steps on every point (--points-per-step 0, the default before sampled steps); add "
                 "--points-per-step 0 to resume it, or pass --overwrite to start over"),
            )
            for in_effect, earlier, what in earlier_defaults:
                if (not options.overwrite and in_effect
                        and state.get("fingerprint") == _fingerprint(inputs, {**resolved, "settings": earlier})):
                    raise CaptureError(f"actor '{options.actor}' has an unfinished training {what}")
            if not options.overwrite:
                raise CaptureError(f"actor '{options.actor}' has an unfinished training with other shapes or settings "
                                   f"at {out}; rerun that command to resume it, or pass --overwrite to start over")
            remove_actor(out)
            state = None
    elif out.exists() and any(out.iterdir()) and not options.overwrite:
        raise CaptureError(f"{out} exists and is not an actor; choose another name or pass --overwrite")

    t_prep = time.perf_counter()
    data, extras = prepare(options, shapes, report)
    shapes = extras["shapes"]
    data, chart = with_input_chart(data, shapes, extras["tearing"], settings.input_chart, report)
    con: AnatomyConstraints = extras["constraints"]
    report(f"anatomy constraints: {len(con.thickness)} points ({100 * con.coverage:.1f} % of {con.n_vertices} "
           f"vertices), thickness median {np.median(con.thickness):.1f} mm")
    prep_seconds = time.perf_counter() - t_prep

    config = model_config_for(data, settings, extras["jaw_pivot"])
    trainer = ActorTrainer(data, settings, config, device=options.device)
    elapsed_before = cpu_before = 0.0
    if state is not None:
        trainer.load_state_dict(state["trainer"])
        elapsed_before = float(state.get("train_seconds", 0.0))
        cpu_before = float(state.get("train_cpu_seconds", 0.0))
        report(f"resuming training of '{options.actor}' at iteration {trainer.iteration} of {settings.iterations}")
    train_dir.mkdir(parents=True, exist_ok=True)
    write_json(train_dir / "settings.json", {**resolved, "fingerprint": fingerprint,
                                             "inputs": [str(p) for p in inputs]})

    def save_checkpoint(seconds: float) -> None:
        with atomic_path(ckpt_path) as tmp:
            torch.save({"fingerprint": fingerprint, "trainer": trainer.state_dict(), "train_seconds": seconds,
                        "train_cpu_seconds": cpu_before + time.process_time() - cpu0}, tmp)

    log_path = train_dir / "log.jsonl"
    t0, cpu0 = time.perf_counter(), time.process_time()
    last_ckpt = t0
    ev = None
    progress = progress or TrainingProgress(enabled=False)
    best = None   # (mean mm, iteration, trainer.weights()) of the best evaluation of this session
    threads_before = torch.get_num_threads()
    if options.threads:
        torch.set_num_threads(options.threads)
    threads_used = torch.get_num_threads()
    with sigterm_as_interrupt(), _restore_threads(threads_before), \
            progress.session(settings.iterations, trainer.iteration, trainer.work) as update:
        try:
            while trainer.iteration < settings.iterations:
                terms = trainer.step()
                if not np.isfinite(terms["total"]):
                    raise CaptureError(f"training diverged at iteration {trainer.iteration} (loss is not finite); "
                                       f"lower --lr or use --preset default")
                if trainer.iteration % options.eval_every == 0 or trainer.iteration == settings.iterations:
                    ev = trainer.evaluate()
                    if best is None or ev.mean_mm < best[0]:
                        best = (ev.mean_mm, trainer.iteration, trainer.weights())
                    with open(log_path, "a") as fh:
                        fh.write(json.dumps({"iteration": trainer.iteration, "seconds": elapsed_before + time.perf_counter() - t0,
                                             "cpu_seconds": cpu_before + time.process_time() - cpu0,
                                             "mean_mm": ev.mean_mm, "worst_shape_mm": max(ev.shape_mean_mm),
                                             "max_mm": max(ev.shape_max_mm), **terms}) + "\n")
                update(trainer.iteration, terms["total"], ev.mean_mm if ev else float("nan"))
                now = time.perf_counter()
                if now - last_ckpt > options.checkpoint_seconds:
                    save_checkpoint(elapsed_before + now - t0)
                    last_ckpt = now
        except KeyboardInterrupt:
            save_checkpoint(elapsed_before + time.perf_counter() - t0)
            raise Interrupted(f"training of '{options.actor}' interrupted at iteration {trainer.iteration}; "
                              f"checkpoint saved in {train_dir}: run the same command to resume") from None
    train_seconds = elapsed_before + time.perf_counter() - t0
    train_cpu_seconds = cpu_before + time.process_time() - cpu0
    ev = trainer.evaluate()
    weights_of = trainer.iteration
    if best is not None and ev.mean_mm > KEEP_BEST_MARGIN * best[0]:
        # a late loss spike (Adam at the end of a short schedule) is not what the user gets
        report(f"the last steps raised the training error to {ev.mean_mm:.4f} mm; the actor keeps the weights of "
               f"iteration {best[1]} ({best[0]:.4f} mm)")
        trainer.load_weights(best[2])
        weights_of = best[1]
        ev = trainer.evaluate()

    R = rot6d_to_matrix(trainer.jaw_rot6d.detach()).cpu().numpy()
    t = trainer.jaw_t.detach().cpu().numpy()
    frame: FaceFrame = extras["frame"]
    metadata = {
        "name": out.name,
        "units": "mm",
        "created": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds"),
        "software": {"capture": capture.__version__, "torch": torch.__version__, "python": platform.python_version()},
        "shape_names": shapes.names, "neutral": shapes.names[0],
        "n_vertices": int(shapes.vertices.shape[1]), "n_faces": int(len(shapes.faces)),
        "source": {"shapes": str(options.shapes), "files": [str(p) for p in shapes.files],
                   "mirrored_shapes": extras["mirrored"], "mirror_asymmetry": extras["mirror_asymmetry"],
                   "units": options.units, "skull": str(options.skull) if options.skull else None,
                   "jaw": str(options.jaw) if options.jaw else None, "bones_estimated": extras["bones_estimated"],
                   "jaw_source": extras["jaw_source"]},
        "model": config.to_dict(),
        "training": {"preset": options.preset, "settings": settings.to_dict(), "iterations": trainer.iteration,
                     "weights_of_iteration": weights_of,
                     "train_seconds": train_seconds, "train_cpu_seconds": train_cpu_seconds,
                     "prepare_seconds": prep_seconds, "device": options.device,
                     "torch_threads": threads_used, "hidden_matmul": trainer.hidden_matmul, "input_chart": chart,
                     "load_average": list(_load_average()), "machine": machine()},
        "quality": _evaluation_metadata(ev, shapes.names),
        "anatomy_constraints": {"count": int(len(con.thickness)), "coverage": float(con.coverage),
                                "candidates": int(con.n_candidates),
                                "thickness_mm": {"median": float(np.median(con.thickness)),
                                                 "min": float(con.thickness.min()), "max": float(con.thickness.max())},
                                "bones_estimated": extras["bones_estimated"],
                                "trusted_region": extras["trusted_source"]},
        "face_frame": {**frame.to_dict(), "source": extras["frame_source"]},
        "forehead": {"n_vertices": int(len(extras["forehead_idx"])), "source": extras["forehead_source"],
                     "vertices": [int(i) for i in extras["forehead_idx"]]},
        "jaw_pivot_mm": [float(v) for v in extras["jaw_pivot"]],
        "jaw_transforms": {name: {"R": R[i].tolist(), "t_mm": t[i].tolist()} for i, name in enumerate(shapes.names[1:])},
        "landmark_embeddings": {},
    }
    save_actor(out, metadata, trainer.model, trainer.jaw_rot6d, trainer.jaw_t, shapes.neutral,
               extras["bones"], con.to_arrays())
    if log_path.exists():
        write_bytes(out / "training_log.jsonl", log_path.read_bytes())
    shutil.rmtree(train_dir, ignore_errors=True)
    return out


def progress_line(iteration: int, total: int, loss: float, err_mm: float, elapsed_s: float, left_s: float | None) -> str:
    """One plain progress line: iteration, loss, current error (mm), time so far and time left."""
    left = "estimating" if left_s is None else f"about {_minutes(left_s)} left"
    err = "not measured yet" if not np.isfinite(err_mm) else f"{err_mm:.4f} mm"
    return (f"training: iteration {iteration}/{total} ({100 * iteration / max(total, 1):.0f} %), loss {loss:.3e}, "
            f"error {err}, {_minutes(elapsed_s)} elapsed, {left}")


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min" if seconds >= 60 else f"{seconds:.0f} s"


def time_left(done_here: float, seconds_here: float, remaining: float) -> float | None:
    """Seconds left for ``remaining`` work (iterations, or steps' costs) at the rate of this session (None before
    any step)."""
    if done_here <= 0 or seconds_here <= 0:
        return None
    return remaining * seconds_here / done_here


class TrainingProgress:
    """Training progress: iteration, loss, current mean error (mm), time elapsed and time left.

    Enabled: a rich progress bar. Disabled (``--no-progress``, logs, batch jobs): one plain line
    every ``interval_s`` seconds and one at the end, through ``write`` (default: standard error).
    """

    def __init__(self, enabled: bool = True, interval_s: float = 60.0, write: Callable[[str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.enabled = enabled
        self.interval_s = interval_s
        self.write = write or (lambda line: print(line, file=sys.stderr, flush=True))
        self.clock = clock

    @contextlib.contextmanager
    def session(self, total: int, start: int, work: Callable[[int], float] | None = None):
        """Progress of iterations ``start..total``; ``work(i)`` is the cost of the first i of them (default i),
        from which the time left is reckoned when steps differ in cost."""
        work = work or float
        if not self.enabled:
            yield self._line_updater(total, start, work)
            return
        from rich.progress import (BarColumn, Progress, TextColumn, TimeElapsedColumn,
                                   TimeRemainingColumn)

        # The bar counts work, so that its time left holds when steps differ in cost; the text counts iterations.
        columns = [TextColumn("training"), BarColumn(), TextColumn("{task.fields[iteration]}/" + str(total)),
                   TextColumn("loss {task.fields[loss]:.3e}  error {task.fields[err]:.4f} mm"),
                   TimeElapsedColumn(), TextColumn("left"), TimeRemainingColumn()]
        with Progress(*columns, transient=False) as bar:
            task = bar.add_task("train", total=work(total), completed=work(start), iteration=start, loss=float("nan"),
                                err=float("nan"))

            def update(iteration: int, loss: float, err: float) -> None:
                bar.update(task, completed=work(iteration), iteration=iteration, loss=loss, err=err)

            yield update

    def _line_updater(self, total: int, start: int, work: Callable[[int], float]) -> Callable[[int, float, float], None]:
        t0 = self.clock()
        last = [t0]

        def update(iteration: int, loss: float, err: float) -> None:
            now = self.clock()
            if now - last[0] < self.interval_s and iteration < total:
                return
            last[0] = now
            self.write(progress_line(iteration, total, loss, err, now - t0,
                                     time_left(work(iteration) - work(start), now - t0, work(total) - work(iteration))))

        return update
