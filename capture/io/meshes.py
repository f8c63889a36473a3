"""Reading registered meshes: one topology, units converted to millimetres, bad input reported.

Vertex order is the correspondence between shapes, so meshes are loaded with trimesh's
``process=False`` (no vertex merging or reordering).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from capture.io.errors import CaptureError

if TYPE_CHECKING:
    import trimesh

MESH_SUFFIXES = (".obj", ".ply")
UNITS_TO_MM = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}


#: Plausible largest extent (mm) of a face or head mesh; outside it the stated units are wrong.
FACE_SIZE_RANGE_MM = (40.0, 1000.0)


def check_face_size(vertices: np.ndarray, units: str, what: str, flag: str = "--units") -> float:
    """The largest bounding-box side (mm) of ``vertices`` (V, 3) mm; one line when it is not a face's size.

    The message names the unit that would make it plausible (millimetre meshes read with ``--units m``
    give a 186 m face).
    """
    extent = float(np.ptp(np.asarray(vertices, np.float64).reshape(-1, 3), axis=0).max())
    lo, hi = FACE_SIZE_RANGE_MM
    if lo <= extent <= hi:
        return extent
    scale = UNITS_TO_MM.get(units, 1.0)
    fits = [u for u, s in UNITS_TO_MM.items() if u != units and lo <= extent / scale * s <= hi]
    hint = f" (as {fits[0]} it would be {extent / scale * UNITS_TO_MM[fits[0]]:.0f} mm)" if fits else ""
    raise CaptureError(f"{what} is {extent:.4g} mm across with {flag} {units}, but a face is {lo:g}-{hi:g} mm{hint}; "
                       f"check {flag}")


def units_scale(units: str) -> float:
    """Millimetres per unit of ``units`` (mm, cm, m, in)."""
    try:
        return UNITS_TO_MM[units]
    except KeyError:
        raise CaptureError(f"unknown units '{units}': use one of {', '.join(UNITS_TO_MM)}") from None


def load_mesh(path: str | Path, scale: float = 1.0, what: str = "mesh") -> trimesh.Trimesh:
    """Load one triangle mesh keeping vertex order; multiply coordinates by ``scale`` (to mm)."""
    import trimesh

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
        import trimesh

        return trimesh.Trimesh(self.vertices[0], self.faces, process=False)


def load_mesh_folder(folder: Path, units: str, n_vertices: int, fix: str) -> tuple[list[Path], np.ndarray]:
    """The OBJ/PLY meshes of ``folder`` in file-name order -> (files, vertices ``(T, V, 3)`` float64 mm).

    Every mesh must have ``n_vertices`` vertices (one line ending in ``fix`` otherwise); the first is
    checked to be a face's size in ``units`` (:func:`check_face_size`).
    """
    files = sorted(p for p in Path(folder).iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES)
    if not files:
        raise CaptureError(f"no .obj or .ply meshes in {folder}; {fix}")
    scale = units_scale(units)
    verts = []
    for p in files:
        mesh = load_mesh(p, scale, "mesh")
        if len(mesh.vertices) != n_vertices:
            raise CaptureError(f"mesh {p.name} has {len(mesh.vertices)} vertices but the actor's template has "
                               f"{n_vertices}; {fix}")
        if not verts:
            check_face_size(mesh.vertices, units, f"mesh {p.name}")
        verts.append(np.asarray(mesh.vertices, np.float64))
    return files, np.stack(verts)


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
    check_face_size(ref.vertices, units, f"the neutral {files[0].name}")
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
