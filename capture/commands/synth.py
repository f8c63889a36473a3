"""``capture synth``: render a synthetic take of an actor with known truth (see capture.synth.take)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from capture.io.errors import CaptureError


def _parse_distortion(text: Optional[str]) -> tuple[float, ...] | None:
    if text is None:
        return None
    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise CaptureError(f"--distortion must be comma-separated numbers k1,k2,p1,p2[,k3], got '{text}'") from None
    if len(vals) not in (4, 5, 8):
        raise CaptureError(f"--distortion needs 4, 5 or 8 OpenCV coefficients (k1,k2,p1,p2[,k3...]), got {len(vals)}")
    return vals


def synth_command(
    actor: str = typer.Option(..., "--actor", help="Actor name or folder to render."),
    out: Path = typer.Option(..., "--out", help="Output folder of the take."),
    frames: Optional[int] = typer.Option(None, "--frames", help="Number of frames (default 150; with --meshes all "
                                         "of the sequence's)."),
    fps: float = typer.Option(25.0, "--fps", help="Frame rate."),
    size: Optional[str] = typer.Option(None, "--size", help="Frame size WxH (default 1280x720, or the camera file's)."),
    preset: str = typer.Option("talk", "--preset", help="Motion: talk, turns, calm, frontal (no head rotation), yaw30."),
    seed: int = typer.Option(0, "--seed", help="Random seed of the motion."),
    landmarks: int = typer.Option(1000, "--landmarks", help="Number of detector landmarks (farthest-point sampled)."),
    distortion: Optional[str] = typer.Option(None, "--distortion", help="OpenCV distortion k1,k2,p1,p2[,k3] to render with."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="Camera file to use instead of the default 60 deg camera."),
    codec: str = typer.Option("h264-lossless", "--codec", help="h264-lossless (exact pixels) or h264 (yuv444p, --crf)."),
    crf: int = typer.Option(8, "--crf", help="Constant quality of --codec h264 (0 best .. 51)."),
    obj: bool = typer.Option(False, "--obj", help="Also write one OBJ mesh per frame."),
    look: bool = typer.Option(False, "--look", help="Also write take_look.mp4: the frames shaded like a face, "
                              "for people (the detector reads the coded take.mp4)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing take in --out."),
    meshes: Optional[Path] = typer.Option(None, "--meshes", help="Render this registered mesh sequence instead of "
                                          "the actor's own motion: a folder of OBJ/PLY (name order) or an .npz "
                                          "(T, V, 3), in the actor's topology and template frame; --preset then "
                                          "only moves the head (frontal: not at all)."),
    units: str = typer.Option("mm", "--units", help="Units of --meshes: mm, cm, m, in."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars."),
) -> None:
    """Render a synthetic take of an actor with known truth: video, camera, ground-truth meshes and
    parameters, landmarks, and a detector that reads the rendered pixels."""
    from capture.synth.progress import synthesize_shown
    from capture.synth.take import TRUTH_JSON, SynthConfig, parse_size

    if frames is None:
        frames = 1_000_000 if meshes is not None else 150
    cfg = SynthConfig(actor=actor, out=out, frames=frames, fps=fps, size=parse_size(size), preset=preset, seed=seed,
                      landmarks=landmarks, distortion=_parse_distortion(distortion), camera=camera, codec=codec,
                      crf=crf, obj=obj, look=look, overwrite=overwrite, meshes=meshes, units=units)
    path = synthesize_shown(cfg, progress)
    truth = json.loads((path / TRUTH_JSON).read_text())
    if truth["actor"].get("note"):          # a bundled actor: the embedding went into the user's copy
        typer.echo(truth["actor"]["note"])
    typer.echo(f"synthetic take written to {path}; its detector's landmark embedding: {truth['detector']['embedding']}")
