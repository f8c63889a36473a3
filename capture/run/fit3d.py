"""``capture fit3d MESHES --actor A``: fit an actor to a registered 3D mesh sequence (offline scans).

MESHES is a folder of OBJ/PLY meshes in the actor's topology (same vertex order), one per frame,
sorted by file name. The fit (:func:`capture.fit.take.fit_meshes`) runs in resumable windows like
``capture run``; the exports are the same (no overlay: there is no video) and ``report.json`` gives
the mean 3D vertex distance (mm) to the given mesh per frame instead of a reprojection error.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from capture.io.errors import CaptureError, Interrupted
from capture.run.inputs import check_device, check_window, resolve_fit_settings
from capture.run.report import error_stats, frame_table
from capture.run.stages import export_stage, fit_frames, iter_fits, run_fit_cached
from capture.run.store import digest, open_run_dir, file_sha256, write_run_json
from capture.io.signals import sigterm_as_interrupt

FIT3D_FORMATS = ("obj", "usd", "npz")


@dataclass
class Fit3dConfig:
    """Settings of ``capture fit3d`` (saved resolved in run.json and report.json)."""

    meshes: Path
    actor: str
    out: Path | None = None            # None: ./runs/<folder name>
    units: str = "mm"
    fps: float = 30.0
    formats: tuple[str, ...] = FIT3D_FORMATS
    preset: str = "default"
    seed: int = 0
    iterations: int | None = None
    device: str = "cpu"
    window: int = 30
    overlap: int = 6
    overwrite: bool = False
    progress: bool = True
    threads: int = 1

    def to_dict(self) -> dict:
        d = asdict(self)
        d["meshes"], d["out"] = str(self.meshes), None if self.out is None else str(self.out)
        d["formats"] = list(self.formats)
        return d


def load_mesh_sequence(folder: Path, units: str, n_vertices: int) -> tuple[list[Path], np.ndarray]:
    """The meshes of ``folder`` sorted by name -> (files, vertices (T, V, 3) mm); topology checked."""
    from capture.io.meshes import load_mesh_folder

    folder = Path(folder)
    if not folder.is_dir():
        raise CaptureError(f"mesh folder {folder} does not exist; give a folder of OBJ/PLY meshes")
    return load_mesh_folder(folder, units, n_vertices, "fit3d needs meshes registered to the actor's topology")


def fit3d_take(cfg: Fit3dConfig) -> dict:
    from capture.actor.package import WEIGHTS, load_actor
    from capture.export import ExportContext, ExportOptions
    from capture.fit.take import WindowedFit, fit_meshes
    from capture.run.take import base_report, finish_report, html_report, rig_and_features
    from capture.io.video import video_identity

    t_start = time.perf_counter()
    check_window(cfg.window, cfg.overlap)
    check_device(cfg.device)
    if cfg.threads < 1:
        raise CaptureError(f"--threads must be at least 1, got {cfg.threads}")
    if "overlay" in cfg.formats:
        raise CaptureError("--formats overlay needs a video; fit3d exports obj, ply, usd and npz")
    if not cfg.fps > 0:
        raise CaptureError(f"--fps must be positive, got {cfg.fps}")
    settings = resolve_fit_settings(cfg.preset, cfg.seed, cfg.iterations, kind="3d")
    actor = load_actor(cfg.actor, device=cfg.device)
    files, meshes = load_mesh_sequence(cfg.meshes, cfg.units, len(actor.template.vertices))
    out = Path(cfg.out) if cfg.out is not None else Path("runs") / Path(cfg.meshes).name
    take_id = digest([[p.name, video_identity(p)] for p in files] + [cfg.units])
    label = f"mesh sequence {Path(cfg.meshes).name} ({len(files)} meshes, id {take_id[:12]})"
    weights_sha = file_sha256(Path(actor.path) / WEIGHTS)
    resolved = {**cfg.to_dict(), "out": str(out), "fit_settings": settings.to_dict()}
    fingerprints = {"meshes": take_id, "actor_weights_sha256": weights_sha}
    with open_run_dir(out, take_id, label, cfg.overwrite, what="fit3d") as folder:
        out = folder.work
        write_run_json(out, take_id, label, resolved, fingerprints, "running")

        key = {"kind": "fit3d", "fit_settings": settings.to_dict(), "window": cfg.window, "overlap": cfg.overlap,
               "device": cfg.device, "actor_weights_sha256": weights_sha, "meshes": take_id}
        fdir = out / "fit" / digest(key)[:16]
        log: list[dict] = []
        stage = "fit"
        with sigterm_as_interrupt():
            try:
                how = lambda cache: WindowedFit(settings, cfg.window, cfg.overlap, cache, cfg.device, cfg.threads)  # noqa: E731
                run_fit_cached(fdir, key, len(meshes), lambda cache: fit_meshes(actor, meshes, how(cache)), "fit3d",
                               cfg.progress, log)
                frames = fit_frames(fdir)
                stage = "export"
                ctx = ExportContext(faces=np.asarray(actor.template.faces), fps=cfg.fps, image_size=(1, 1), camera=None,
                                    frame_count=len(frames), options=ExportOptions(),
                                    source=f"capture fit3d {Path(cfg.meshes).name}, actor {actor.name}",
                                    **rig_and_features(actor, cfg.formats))
                export_stage(fdir, ctx, cfg.formats, {"fit": digest(key), "formats": list(cfg.formats), "fps": cfg.fps,
                                                      "options": ExportOptions().to_dict()},
                             out, log=log, progress=cfg.progress)
            except KeyboardInterrupt:
                raise Interrupted(f"interrupted during {stage}; finished work is kept in {out}: run the same "
                                  f"command to resume") from None
        from capture.run.report import FrameSummary, finite_or_none

        fits = [FrameSummary(int(f.frame), str(f.status), finite_or_none(getattr(f, "error3d_mm", None)))
                for f in iter_fits(fdir)]
        errors = [f.error for f in fits]
        rows, skipped = frame_table(fits, "error3d_mm", errors, {})
        for r, p in zip(rows, files):
            r["mesh"] = p.name
        report = base_report("capture fit3d", folder.out, resolved, log, t_start)
        report.update({"meshes": {"folder": str(cfg.meshes), "count": len(files), "identity": take_id, "units": cfg.units},
                       "actor": {"name": actor.name, "path": str(actor.path)}, "camera": None,
                       "frames": {"requested": len(files), "first": 0, "last": len(files) - 1,
                                  "fitted": len(rows) - len(skipped), "skipped": len(skipped)},
                       "error": {"kind": "3D vertex error", "unit": "mm", **error_stats(errors)},
                       "skipped_frames": skipped, "per_frame": rows, "notes": []})
        finish_report(report, rows, "error3d_mm", out)
        html_report(out, report, fdir, actor, rows, "error3d_mm", "mm", cfg.fps)
        if len(fits) != len(files):
            raise CaptureError(f"only {len(fits)} of {len(files)} meshes were fitted; see report.json and rerun")
        write_run_json(out, take_id, label, resolved, fingerprints, "done")
        folder.commit()
        return report
