"""One mesh file per frame: ``meshes/frame_<index:06d>.obj`` or ``.ply``.

Each file has the actor's full template topology (every vertex, in template order, and the faces of
``template.ply``), coordinates in millimetres, in the OpenCV camera frame (x right, y down,
z forward) or, with ``ExportOptions.mesh_frame = "head"``, in the actor's template frame.

The codecs (:func:`encode_obj`, :func:`encode_ply`) turn vertices into bytes; the face block is the
same for every frame, so it is encoded once per take. :func:`capture.io.atomic.write_bytes` is the one
thing that touches the disk. Resume: a frame whose file already exists is skipped unless
``overwrite`` (a rerun of an export only writes the missing frames). Frames without a mesh
(``skipped``: no face found) get no file.

* OBJ: text, ``v x y z`` with 4 decimals (0.1 um), 1-based ``f a b c``; no normals or UVs.
* PLY: binary little-endian, ``float x, y, z`` and ``list uchar int vertex_indices``.

Every template vertex is written, also ones no triangle uses. Readers keep them; trimesh's OBJ
reader keeps them only with ``trimesh.load(path, process=False, maintain_order=True)`` (as
:func:`capture.io.meshes.load_mesh` does) and otherwise drops them.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from capture.io.atomic import write_bytes
from capture.export.base import ExportContext, FrameFitLike, check_vertices, to_head_frame

MESH_DIR = "meshes"


def mesh_path(out_dir: Path, frame: int, fmt: str) -> Path:
    """``out_dir/meshes/frame_<frame:06d>.<fmt>``."""
    return Path(out_dir) / MESH_DIR / f"frame_{int(frame):06d}.{fmt}"


def obj_face_block(faces: np.ndarray) -> bytes:
    """The ``f`` lines of an OBJ (1-based indices) for (F, 3) faces."""
    f1 = np.asarray(faces, np.int64) + 1
    return (("f %d %d %d\n" * len(f1)) % tuple(f1.ravel())).encode("ascii")


def encode_obj(vertices: np.ndarray, face_block: bytes, header: str = "") -> bytes:
    """OBJ bytes for (V, 3) vertices and a face block from :func:`obj_face_block`."""
    v = np.asarray(vertices, np.float64)
    head = "".join(f"# {line}\n" for line in header.splitlines())
    body = ("v %.4f %.4f %.4f\n" * len(v)) % tuple(v.ravel())
    return head.encode("utf-8") + body.encode("ascii") + face_block


_PLY_FACE = np.dtype([("n", "u1"), ("idx", "<i4", (3,))])


def ply_face_block(faces: np.ndarray) -> bytes:
    """The binary face records of a PLY for (F, 3) faces."""
    rec = np.empty(len(faces), _PLY_FACE)
    rec["n"] = 3
    rec["idx"] = faces
    return rec.tobytes()


def encode_ply(vertices: np.ndarray, face_block: bytes, header: str = "") -> bytes:
    """Binary little-endian PLY bytes for (V, 3) vertices and a face block from :func:`ply_face_block`."""
    v = np.ascontiguousarray(vertices, dtype="<f4")
    n_faces = len(face_block) // _PLY_FACE.itemsize
    comments = "".join(f"comment {line}\n" for line in header.splitlines())
    head = (f"ply\nformat binary_little_endian 1.0\n{comments}element vertex {len(v)}\n"
            "property float x\nproperty float y\nproperty float z\n"
            f"element face {n_faces}\nproperty list uchar int vertex_indices\nend_header\n")
    return head.encode("ascii") + v.tobytes() + face_block


CODECS = {"obj": (obj_face_block, encode_obj), "ply": (ply_face_block, encode_ply)}


class MeshSequenceWriter:
    """Writes one OBJ or PLY per frame, atomically, skipping existing files unless ``overwrite``."""

    needs_image = False

    def __init__(self, out_dir: Path, ctx: ExportContext, fmt: str):
        if fmt not in CODECS:
            raise ValueError(f"mesh format must be one of {sorted(CODECS)}, got {fmt!r}")
        self.out_dir, self.ctx, self.fmt = Path(out_dir), ctx, fmt
        block, self._encode = CODECS[fmt]
        self._faces = block(ctx.faces)
        self._frame = ctx.options.mesh_frame
        self._vertex_count: int | None = None
        self.paths: list[Path] = []
        self.written = 0
        self.skipped_existing = 0

    def write(self, fit: FrameFitLike, image=None, detection=None) -> None:
        target = mesh_path(self.out_dir, fit.frame, self.fmt)
        if target.exists() and not self.ctx.options.overwrite:
            self.paths.append(target)
            self.skipped_existing += 1
            return
        v = check_vertices(fit, self.ctx, self._vertex_count)
        if v is None:
            return
        self._vertex_count = v.shape[0]
        if self._frame == "head":
            v = to_head_frame(v, fit.head_R, fit.head_t)
            where = "actor template (head) frame"
        else:
            where = "camera frame (OpenCV: x right, y down, z forward)"
        header = f"capture frame {int(fit.frame)} ({getattr(fit, 'status', 'fitted')}); mm; {where}"
        write_bytes(target, self._encode(v, self._faces, header))
        self.paths.append(target)
        self.written += 1

    def close(self) -> list[Path]:
        return list(self.paths)

    def abort(self) -> None:
        """Nothing is in flight between frames: each file is complete or absent."""
