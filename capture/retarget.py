"""``capture retarget RUN_DIR --to B``: play a finished run of actor A on actor B (paper, Sec. 5.4).

What is played is exactly what the run solved: the per-frame head and jaw transforms and the
coefficient field ``w_j(c) = F_W(z_j, c)`` of each fitted window (``RUN_DIR/fit/<key>/windows/``, the
:class:`models.fit.SequenceFit` states the fit keeps), blended across window overlaps with the fit's own
smoothstep (:mod:`capture.fit.take`), so retargeting A onto A reproduces the run's meshes. B's meshes are
:func:`models.retarget.retarget_points` / :func:`models.retarget.pose_part` (B's anatomy, A's coefficients
at the corresponding template point).

A and B must be in correspondence: one template topology (vertex count and triangles) and the same
expression shapes (names; a different order is matched by name). Anything else is a one-line error.

Output folder (``--out``, default ``runs/<run name>_on_<B>``), the same files as ``capture run``::

    run.json, report.json         what was retargeted (source run and its fit, both actors, settings, timings)
    meshes/, take.usdc, params.npz, overlay.mp4, export.json    B's full performance (``--formats``)
    jaw/, soft_tissue/            with ``--parts``: the rigid jaw motion only / the soft tissue with the jaw at rest
    fit/<key>/                    B's frames (cache: a rerun exports without replaying)

``params.npz`` holds the played parameters (A's head and jaw transforms, codes and coefficients at A's
landmarks); there are no detections, so no ``landmarks.npz``. Every stage skips work already done.
"""

from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import torch

from capture.io.errors import CaptureError, Interrupted

PART_DIRS = {"full": ".", "jaw": "jaw", "soft_tissue": "soft_tissue"}


@dataclass
class RetargetConfig:
    """Settings of ``capture retarget`` (saved resolved in run.json and report.json)."""

    run_dir: Path
    to: str
    out: Path | None = None              # None: runs/<run name>_on_<B>
    source_actor: str | None = None      # None: the actor named in the run's run.json
    formats: tuple[str, ...] | None = None   # None: the source run's formats
    parts: tuple[str, ...] = ("full",)
    mesh_frame: str = "camera"
    device: str = "cpu"
    threads: int = 1
    overwrite: bool = False
    progress: bool = True

    def to_dict(self) -> dict:
        d = asdict(self)
        d["run_dir"], d["out"] = str(self.run_dir), None if self.out is None else str(self.out)
        d["formats"] = None if self.formats is None else list(self.formats)
        d["parts"] = list(self.parts)
        return d


# --------------------------------------------------------------------------------------- checks
def expression_order(source_meta: dict, target_meta: dict) -> list[int]:
    """``order[e]``: B's expression column for A's expression e; a one-line error unless the sets agree."""
    a, b = source_meta["shape_names"][1:], target_meta["shape_names"][1:]
    sa, sb = source_meta["name"], target_meta["name"]
    if len(a) != len(b) or set(a) != set(b):
        missing, extra = sorted(set(a) - set(b)), sorted(set(b) - set(a))
        raise CaptureError(
            f"actors '{sa}' ({len(a)} expressions) and '{sb}' ({len(b)}) do not correspond: '{sb}' lacks "
            f"{missing or 'none'} and has extra {extra or 'none'}; retargeting needs both actors learned from "
            f"the same expression shapes (same names; mirrored shapes count: train both with or both without "
            f"--no-mirror)")
    return [b.index(name) for name in a]


def check_topology(source, target) -> None:
    """One vertex order and triangle list, or a one-line error."""
    va, vb = len(source.template.vertices), len(target.template.vertices)
    if va != vb:
        raise CaptureError(f"actors '{source.name}' ({va} vertices) and '{target.name}' ({vb}) do not correspond: "
                           f"retargeting needs both learned from meshes of one topology (same vertex order)")
    fa, fb = np.asarray(source.template.faces), np.asarray(target.template.faces)
    if fa.shape != fb.shape or not np.array_equal(fa, fb):
        raise CaptureError(f"actors '{source.name}' and '{target.name}' have {va} vertices each but different "
                           f"triangles: retargeting needs both learned from meshes of one topology")


# ----------------------------------------------------------------------------------- source run
@dataclass
class SourceRun:
    """A finished ``capture run`` / ``capture fit3d`` folder, as retargeting reads it."""

    path: Path
    run: dict                 # run.json
    report: dict              # report.json
    fit_dir: Path             # fit/<key>/ of the exported fit
    fit_key: str              # its digest (export.json's key.fit)
    windows: list[tuple[int, dict]]   # (first take position, SequenceFit state), in order
    frames: list[int]         # video frame of each take position
    fps: float
    image_size: tuple[int, int]
    camera: object | None
    video: Path | None

    @property
    def settings(self) -> dict:
        return self.run["settings"]


def read_source_run(run_dir: Path) -> SourceRun:
    """Check and read a finished run folder; one-line errors say what is missing and how to get it."""
    try:
        return _read_source_run(run_dir)
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        what = f"lacks '{exc.args[0]}'" if isinstance(exc, KeyError) else f"is malformed ({exc.__class__.__name__})"
        raise CaptureError(f"the run in {run_dir} {what} in its run.json, report.json or fit; rerun its capture "
                           f"command to rebuild it, then retarget") from None


#: Largest solved-window file read back (bytes); a window of a long take's codes is a few MiB.
MAX_WINDOW_BYTES = 256 << 20


def _read_window(p: Path) -> dict:
    """One solved window (``torch.load`` with ``weights_only``: tensors only, no code runs); one line when bad."""
    if p.stat().st_size > MAX_WINDOW_BYTES:
        raise CaptureError(f"fit window {p} is {p.stat().st_size} bytes, more than a window can be; rerun the run's "
                           f"capture command with --overwrite")
    try:
        state = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # UnpicklingError, zip errors, EOFError, RuntimeError: all a damaged or crafted file
        raise CaptureError(f"unreadable fit window {p} ({exc.__class__.__name__}); rerun the run's capture command "
                           f"with --overwrite") from None
    if (not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values())
            or "codes" not in state or state["codes"].ndim != 2):
        raise CaptureError(f"fit window {p} does not hold a solved window's tensors; rerun the run's capture command "
                           f"with --overwrite")
    return state


def _read_source_run(run_dir: Path) -> SourceRun:
    from capture.run.stages import DONE_JSON, EXPORT_JSON
    from capture.run.store import RUN_FORMAT, RUN_JSON, read_json

    run_dir = Path(run_dir)
    run = read_json(run_dir / RUN_JSON)
    if run is None or run.get("format") != RUN_FORMAT:
        raise CaptureError(f"{run_dir} is not a run folder (no readable {RUN_JSON}); give the --out folder of a "
                           f"'capture run' or 'capture fit3d'")
    if run.get("status") != "done":
        raise CaptureError(f"the run in {run_dir} is not finished (status '{run.get('status')}'); rerun its "
                           f"capture command to finish it, then retarget")
    if "retarget" in run["settings"].get("command", ""):
        raise CaptureError(f"{run_dir} is itself a retargeted run; retarget the original run of the source actor")
    export = read_json(run_dir / EXPORT_JSON) or {}
    fit_key = (export.get("key") or {}).get("fit")
    report = read_json(run_dir / "report.json") or {}
    if not fit_key:
        raise CaptureError(f"{run_dir} has no finished export ({EXPORT_JSON}); rerun its capture command")
    fit_dir = run_dir / "fit" / fit_key[:16]
    done = read_json(fit_dir / DONE_JSON)
    win_files = sorted((fit_dir / "windows").glob("win_*.pt"))
    if done is None or not win_files:
        raise CaptureError(f"the fit of {run_dir} ({fit_dir}) or its solved windows are missing; rerun its capture "
                           f"command (it refits only what is missing), then retarget")
    windows = []
    for p in win_files:
        windows.append((int(p.stem.split("_")[1]), _read_window(p)))
    frames = [int(i) for i in done["frames"]]
    _check_windows(windows, int(run["settings"]["overlap"]), len(frames), fit_dir)
    s = run["settings"]
    if "video" in s:
        v = report.get("video", {})
        fps, size = float(v.get("fps", 0) or 0), tuple(v.get("size", (1, 1)))
        from calib.camera_io import camera_from_dict

        camera = camera_from_dict(run["fingerprints"]["camera"], f"{run_dir / RUN_JSON}")
        video = Path(s["video"])
    else:
        fps, size, camera, video = float(s.get("fps", 30.0)), (1, 1), None, None
    if not fps > 0:
        raise CaptureError(f"{run_dir / 'report.json'} gives no frame rate; rerun the run's capture command")
    return SourceRun(run_dir, run, report, fit_dir, fit_key, windows, frames, fps, (int(size[0]), int(size[1])),
                     camera, video)


def _check_windows(windows: list[tuple[int, dict]], overlap: int, n_frames: int, fit_dir: Path) -> None:
    """The windows must chain like the fit's plan (:func:`capture.fit.take.window_plan`) over all frames."""
    expect = 0
    for k, (start, state) in enumerate(windows):
        J = int(state["codes"].shape[0])
        last = k == len(windows) - 1
        if start != expect or (last and start + J != n_frames):
            raise CaptureError(f"the solved windows in {fit_dir / 'windows'} do not cover the run's {n_frames} frames "
                               f"(window at {start}, expected {expect}); rerun the run's capture command")
        expect = start + J - (0 if last else min(overlap, J - 1))


# ------------------------------------------------------------------------------------------ replay
def replay_vertices(source: SourceRun, actor_points, part: str) -> Iterator[np.ndarray]:
    """Vertices ``(V, 3)`` float32 mm of every take position, blended across overlaps as the fit did."""
    from capture.fit.take import _smoothstep
    from models.fit import FitSettings
    from models.retarget import window_vertices

    settings = FitSettings(**source.settings["fit_settings"])
    overlap = int(source.settings["overlap"])
    held: list[np.ndarray] = []
    for k, (start, state) in enumerate(source.windows):
        verts = window_vertices(state, settings, actor_points, part)
        J = len(verts)
        n_held, n_hold = len(held), (0 if k == len(source.windows) - 1 else min(overlap, J - 1))
        for i in range(J - n_hold):
            v = verts[i]
            if i < n_held:  # the same blend as capture.fit.take._blend
                a = _smoothstep((i + 1) / (n_held + 1))
                v = ((1 - a) * held[i] + a * v).astype(np.float32)
            yield v
        held = [verts[i] for i in range(J - n_hold, J)]


def retargeted_fits(source: SourceRun, actor_points, part: str) -> Iterator:
    """The source run's stored frame fits with B's vertices (no landmarks or errors: B was not observed)."""
    from capture.run.stages import iter_fits

    verts = replay_vertices(source, actor_points, part)
    for ff in iter_fits(source.fit_dir):
        yield dataclasses.replace(ff, vertices=next(verts), mesh_map=None, landmarks_fit=np.zeros((0, 2)),
                                  reprojection_rms_px=float("nan"), error3d_mm=float("nan"))


def b_rig_and_features(b, formats, order: list[int]) -> dict:
    """B's rig (curves, UsdSkel) with its expressions in A's order (the fits' coefficients are A's) and
    B's feature lines for the overlay (see :func:`capture.run.take.rig_and_features`)."""
    from capture.export.rig import FaceRig
    from capture.run.take import rig_and_features

    extra = rig_and_features(b, formats)
    if "rig" in extra:
        r = extra["rig"]
        extra["rig"] = FaceRig(r.neutral, r.skin_weight, r.expressions[order], tuple(r.names[i] for i in order),
                               r.jaw_pivot)
    return extra


# ----------------------------------------------------------------------------------------- command
def retarget_run(cfg: RetargetConfig) -> dict:
    """Retarget a finished run onto actor ``cfg.to``; returns the report (also ``OUT/report.json``)."""
    from capture.actor.package import WEIGHTS, load_actor
    from capture.export import ExportContext, ExportOptions
    from capture.fit.take import _num_threads
    from capture.run.take import base_report
    from capture.run.inputs import check_device, parse_formats
    from capture.run.report import write_report
    from capture.run.stages import export_stage, fit_dir_for, run_fit_cached
    from capture.run.store import digest, open_run_dir, file_sha256, write_run_json
    from capture.io.signals import sigterm_as_interrupt
    from models.retarget import PARTS, retarget_points

    t_start = time.perf_counter()
    check_device(cfg.device)
    bad = [p for p in cfg.parts if p not in PARTS]
    if bad or not cfg.parts:
        raise CaptureError(f"--parts must be a comma-separated list of {', '.join(PARTS)}; got {', '.join(bad) or 'none'}")
    if cfg.mesh_frame not in ("camera", "head"):
        raise CaptureError(f"--mesh-frame must be camera or head, got '{cfg.mesh_frame}'")
    if cfg.threads < 1:
        raise CaptureError(f"--threads must be at least 1, got {cfg.threads}")
    src = read_source_run(cfg.run_dir)
    source_name = cfg.source_actor or src.settings["actor"]
    try:
        a = load_actor(source_name, device=cfg.device)
    except CaptureError as exc:
        raise CaptureError(f"the run's actor cannot be loaded ({exc}); give it with --source-actor") from None
    a_sha = file_sha256(Path(a.path) / WEIGHTS)
    if a_sha != src.run["fingerprints"].get("actor_weights_sha256"):
        raise CaptureError(f"actor '{source_name}' ({a.path}) is not the actor the run in {cfg.run_dir} was fitted with "
                           f"(its weights differ); give the run's actor with --source-actor")
    b = load_actor(cfg.to, device=cfg.device)
    b_sha = file_sha256(Path(b.path) / WEIGHTS)
    check_topology(a, b)
    order = expression_order(a.metadata, b.metadata)
    formats = tuple(src.settings.get("formats") or ()) if cfg.formats is None else cfg.formats
    formats = parse_formats(",".join(formats))
    if "overlay" in formats and (src.video is None or not src.video.is_file()):
        raise CaptureError("--formats overlay needs the source run's video"
                           + (f" ({src.video}, not found)" if src.video else " (the run is a fit3d of meshes)")
                           + "; drop overlay from --formats")
    out = Path(cfg.out) if cfg.out is not None else Path("runs") / f"{Path(cfg.run_dir).resolve().name}_on_{b.name}"
    if out.resolve() == Path(cfg.run_dir).resolve():
        raise CaptureError("--out is the source run's folder; give a new folder for the retargeted run")

    take_id = digest({"retarget": src.run["take_id"], "source_fit": src.fit_key, "target": b_sha})
    label = f"retarget of {src.run.get('take_label', src.path.name)} onto actor {b.name}"
    settings = {**cfg.to_dict(), "command": "capture retarget", "out": str(out), "formats": list(formats),
                "source_actor": str(a.path), "to": str(b.path)}
    fingerprints = {"source_take": src.run["take_id"], "source_fit": src.fit_key, "source_weights_sha256": a_sha,
                    "target_weights_sha256": b_sha, "actor_weights_sha256": b_sha}
    parts = tuple(d for d in PART_DIRS.values() if d != ".")
    with open_run_dir(out, take_id, label, cfg.overwrite, what="retarget", extra=parts) as folder:
        out = folder.work
        write_run_json(out, take_id, label, settings, fingerprints, "running")

        verts_a = torch.as_tensor(np.asarray(a.template.vertices), dtype=torch.float32, device=cfg.device)
        verts_b = torch.as_tensor(np.asarray(b.template.vertices), dtype=torch.float32, device=cfg.device)
        log: list[dict] = []
        parts_out: dict[str, dict] = {}
        options = ExportOptions(mesh_frame=cfg.mesh_frame)
        camera = src.camera

        def images(frames):
            from capture.io.video import VideoReader

            with VideoReader(src.video) as reader:
                yield from reader.frames(frames)

        with sigterm_as_interrupt(), _num_threads(cfg.threads):
            t0 = time.perf_counter()
            target = retarget_points(a.model, verts_a, b.model, verts_b, order)
            log.append({"stage": "query", "status": "done", "seconds": time.perf_counter() - t0})
            for part in cfg.parts:
                key = {"kind": "retarget", "part": part, "source_fit": src.fit_key, "source_weights_sha256": a_sha,
                       "target_weights_sha256": b_sha, "expression_order": order}
                part_dir = out if part == "full" else out / PART_DIRS[part]
                try:
                    fdir = run_fit_cached(fit_dir_for(out, key), key, len(src.frames),
                                          lambda _cache, p=part: retargeted_fits(src, target, p), f"retarget {part}",
                                          cfg.progress, log)
                    log[-1]["stage"] = f"retarget {part}"
                    ctx = ExportContext(faces=np.asarray(b.template.faces), fps=src.fps, image_size=src.image_size,
                                        camera=camera, frame_count=len(src.frames), options=options,
                                        source=f"capture retarget {src.path.name} onto actor {b.name} ({part})",
                                        **b_rig_and_features(b, formats, order))
                    export_stage(fdir, ctx, formats, {"fit": digest(key), "formats": list(formats), "fps": src.fps,
                                                      "options": options.to_dict()}, part_dir,
                                 images=images if "overlay" in formats else None, log=log, progress=cfg.progress)
                    log[-1]["stage"] = f"export {part}"
                except KeyboardInterrupt:
                    raise Interrupted(f"interrupted during retarget {part}; finished work is kept in {out}: run the "
                                      f"same command to resume") from None
                files = json.loads((part_dir / "export.json").read_text())["files"]
                parts_out[part] = {"dir": str(part_dir), "files": len(files),
                                   "meshes": sum(f.startswith("meshes/") for f in files)}

        from capture.run.stages import iter_fits

        status = [str(f.status) for f in iter_fits(src.fit_dir)]
        report = base_report("capture retarget", folder.out, settings, log, t_start)
        report.update({
            "source_run": {"path": str(src.path), "take": src.run.get("take_label"), "fit_dir": str(src.fit_dir),
                           "windows": len(src.windows), "fit_settings": src.settings["fit_settings"]},
            "actors": {"source": {"name": a.name, "path": str(a.path), "weights_sha256": a_sha},
                       "target": {"name": b.name, "path": str(b.path), "weights_sha256": b_sha}},
            "correspondence": {"vertices": len(b.template.vertices), "expressions": a.metadata["shape_names"][1:],
                               "target_columns": order, "same_order": order == list(range(len(order)))},
            "frames": {"count": len(src.frames), "first": src.frames[0], "last": src.frames[-1],
                       "fitted": status.count("fitted"), "bridged": status.count("bridged")},
            "played": "per frame: head transform, jaw transform (about the target's jaw pivot), coefficient field "
                      "F_W(z_j, c) at the source's corresponding template point",
            "parts": parts_out, "outputs": {p: v["dir"] for p, v in parts_out.items()},
            "per_frame": [{"frame": f, "status": s} for f, s in zip(src.frames, status)]})
        write_report(out, report)
        write_run_json(out, take_id, label, settings, fingerprints, "done")
        folder.commit()
        return report
