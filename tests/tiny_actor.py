"""A tiny actor with known structure: the synthetic face mask, a jaw that opens by LBS, two bumps.

Shapes (mm, x = the face's left, y = up, z = forward):
* ``neutral``: :func:`tests.synthetic_face.synthetic_face` at low resolution (1,785 vertices).
* ``jawOpen``: LBS with a smooth jaw weight (1 below the mouth, 0 above) and a 12 degree rotation
  about a pivot behind the face: exactly representable by the model.
* ``smile``: two Gaussian bumps at the mouth corners, 4 mm up and back.
* ``browUp``: a Gaussian bump on the forehead, 4 mm up.
The bones are the neutral offset 8 mm inward along its vertex normals, split at y = -35 mm into a
skull (above) and a jaw (below).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from tests.synthetic_face import synthetic_face

JAW_PIVOT = np.array([0.0, 10.0, -20.0])
JAW_DEG = 12.0


def tiny_shapes(proportions: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """The shapes and triangles; ``proportions`` scales the face's width, height and depth (another identity
    with the same expressions in correspondence: the regions move with the face)."""
    v, f = synthetic_face(n_th=35, n_ph=51)
    x, y = v[:, 0], v[:, 1]  # the regions of the expressions, in the unscaled face's coordinates
    scale = np.asarray(proportions, np.float64)
    v = v * scale
    k = np.clip((-30.0 - y) / 25.0, 0.0, 1.0)
    k = k * k * (3 - 2 * k)
    R = Rotation.from_euler("x", JAW_DEG, degrees=True).as_matrix()
    moved = (v - JAW_PIVOT * scale) @ R.T + JAW_PIVOT * scale
    jaw = v + k[:, None] * (moved - v)
    smile = v.copy()
    for side in (-1.0, 1.0):
        g = np.exp(-((x - side * 28.0) ** 2 + (y + 40.0) ** 2) / (2 * 10.0 ** 2))
        smile += g[:, None] * np.array([0.0, 4.0, -2.0])
    brow = v + (np.exp(-(x ** 2 / (2 * 30.0 ** 2) + (y - 60.0) ** 2 / (2 * 12.0 ** 2))))[:, None] * np.array([0, 4.0, 0])
    return {"neutral": v, "jawOpen": jaw, "smile": smile, "browUp": brow}, f


def write_tiny_actor_inputs(root: Path, units_scale: float = 1.0, fmt: str = "ply",
                            proportions: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> tuple[Path, Path, Path]:
    """Write the shapes (in units of ``1/units_scale`` mm) and bones; returns (shapes dir, skull, jaw)."""
    shapes, f = tiny_shapes(proportions)
    sdir = root / "shapes"
    sdir.mkdir(parents=True, exist_ok=True)
    for name, v in shapes.items():
        trimesh.Trimesh(v / units_scale, f, process=False).export(sdir / f"{name}.{fmt}")
    neutral = trimesh.Trimesh(shapes["neutral"], f, process=False)
    bone = trimesh.Trimesh(neutral.vertices - 8.0 * neutral.vertex_normals, f, process=False)
    lower = bone.triangles_center[:, 1] < -35.0 * proportions[1]
    paths = []
    for name, keep in (("skull", ~lower), ("jaw", lower)):
        part = bone.submesh([np.flatnonzero(keep)], append=True)
        paths.append(root / f"{name}.ply")
        part.export(paths[-1])
    return sdir, paths[0], paths[1]


def tiny_training_data(root: Path):
    """The tiny actor's inputs written under ``root`` and prepared as the trainer sees them:
    ``(TrainingData, jaw pivot)`` (face frame, forehead and constraints as ``capture actor train``)."""
    from capture.actor.training import TrainOptions, prepare
    from capture.io.meshes import load_shape_dir

    shapes, skull, jaw = write_tiny_actor_inputs(root)
    data, extras = prepare(TrainOptions(actor="x", shapes=shapes, skull=skull, jaw=jaw), load_shape_dir(shapes),
                           report=lambda m: None)
    return data, extras["jaw_pivot"]


def train_tiny_actor(root: Path, iterations: int = 100, width: int = 64, name: str = "tiny",
                     proportions: tuple[float, float, float] = (1.0, 1.0, 1.0)) -> Path:
    """Write the inputs under ``root`` and train the tiny actor through the command line; its folder."""
    from capture.cli import main

    shapes, skull, jaw = write_tiny_actor_inputs(root, proportions=proportions)
    actor = root / "actors" / name
    assert main(["actor", "train", str(actor), "--shapes", str(shapes), "--skull", str(skull), "--jaw", str(jaw),
                 "--iterations", str(iterations), "--width", str(width), "--no-progress"]) == 0
    return actor


def synth_tiny_take(actor: Path, out: Path, frames: int, landmarks: int = 200) -> Path:
    """A small synthetic take (320x240, talking preset) of ``actor`` through ``capture synth``."""
    from capture.cli import main

    assert main(["synth", "--actor", str(actor), "--out", str(out), "--frames", str(frames), "--size", "320x240",
                 "--preset", "talk", "--landmarks", str(landmarks), "--no-progress"]) == 0
    return out
