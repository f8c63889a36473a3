"""Reading registered meshes: one topology, units converted to millimetres, bad input reported.

Vertex order is the correspondence between shapes, so meshes are loaded with trimesh's
``process=False`` (no vertex merging or reordering).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh

from capture.io.errors import CaptureError

MESH_SUFFIXES = (".obj", ".ply")
UNITS_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}


def units_scale(units: str) -> float:
    """Millimetres per unit of ``units`` (mm, cm, m, in)."""
    try:
        return UNITS_TO_MM[units]
    except KeyError:
        raise CaptureError(f"unknown units '{units}': use one of {', '.join(UNITS_TO_MM)}") from None


def load_mesh(path: str | Path, scale: float = 1.0, what: str = "mesh") -> trimesh.Trimesh:
    """Load one triangle mesh keeping vertex order; multiply coordinates by ``scale`` (to mm)."""
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{what} file not found: {path}")
    try:
        mesh = trimesh.load(path, process=False, maintain_order=True, force="mesh")
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise CaptureError(f"cannot read {what} {path}: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else 'unreadable'}") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise CaptureError(f"cannot read {what} {path}: no triangles found")
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        raise CaptureError(f"{what} {path} has {int(bad.sum())} vertices with NaN or infinite coordinates "
                           f"(first: vertex {int(np.flatnonzero(bad)[0])}); fix or re-export the mesh")
    return trimesh.Trimesh(vertices * scale, np.asarray(mesh.faces), process=False)


@dataclass
class ShapeSet:
    """Registered shapes of one actor: the neutral first, one topology, millimetres."""

    names: list[str]           # shape names (file stems), names[0] is the neutral
    vertices: np.ndarray       # (N, V, 3) float64 mm
    faces: np.ndarray          # (F, 3) int64
    files: list[Path]

    @property
    def neutral(self) -> trimesh.Trimesh:
        return trimesh.Trimesh(self.vertices[0], self.faces, process=False)


def load_shape_dir(directory: str | Path, neutral: str | None = None, units: str = "mm") -> ShapeSet:
    """Load every OBJ/PLY in ``directory`` as one actor's registered shapes.

    Args:
        directory: folder of meshes sharing one topology; the file stem is the shape name.
        neutral: stem of the neutral shape; default ``neutral`` when such a file exists.
        units: units of the files (converted to mm).

    Raises:
        CaptureError: empty or missing folder, no neutral, unreadable file, NaN, or topology mismatch
            (naming the file and the counts).
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise CaptureError(f"shapes folder not found: {directory}")
    files = sorted(p for p in directory.iterdir() if p.suffix.lower() in MESH_SUFFIXES and p.is_file())
    if not files:
        raise CaptureError(f"no .obj or .ply meshes in {directory}")
    stems = [p.stem for p in files]
    dupes = sorted({s for s in stems if stems.count(s) > 1})
    if dupes:
        raise CaptureError(f"two meshes share the shape name '{dupes[0]}' in {directory}; keep one file per shape")
    if neutral is None:
        if "neutral" not in stems:
            raise CaptureError(f"no neutral shape in {directory}: name it neutral.obj/.ply or pass --neutral NAME")
        neutral = "neutral"
    if neutral not in stems:
        raise CaptureError(f"neutral shape '{neutral}' not found in {directory} (shapes: {', '.join(stems[:8])}"
                           f"{', ...' if len(stems) > 8 else ''})")
    if len(files) < 2:
        raise CaptureError(f"only the neutral in {directory}: an actor needs the neutral and at least one expression")
    order = [stems.index(neutral)] + [i for i in range(len(files)) if stems[i] != neutral]
    files = [files[i] for i in order]
    scale = units_scale(units)
    meshes = [load_mesh(p, scale, "shape") for p in files]
    ref = meshes[0]
    for path, mesh in zip(files[1:], meshes[1:]):
        if len(mesh.vertices) != len(ref.vertices) or len(mesh.faces) != len(ref.faces):
            raise CaptureError(
                f"{path.name} has {len(mesh.vertices)} vertices and {len(mesh.faces)} triangles but the neutral "
                f"{files[0].name} has {len(ref.vertices)} and {len(ref.faces)}: all shapes must share one topology")
        if not np.array_equal(mesh.faces, ref.faces):
            raise CaptureError(f"{path.name} has the same counts as {files[0].name} but different triangles: "
                               f"all shapes must share one topology (same vertex order and faces)")
    return ShapeSet(names=[p.stem for p in files], vertices=np.stack([m.vertices for m in meshes]),
                    faces=np.asarray(ref.faces, dtype=np.int64), files=files)
