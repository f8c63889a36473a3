"""Landmark embeddings: where each of a detector's landmarks sits on the actor's template mesh.

File ``A/landmarks/<detector name>.json`` (format 1)::

    {"format": "capture-landmark-embedding", "version": 1, "detector": "face68", "count": 68,
     "face_index": [L ints], "barycentric": [[b0, b1, b2] x L], "source": "how it was made"}

Landmark ``l`` is the point ``sum_k barycentric[l][k] * V[F[face_index[l]][k]]`` of ``template.ply``
(vertices ``V`` in mm, triangles ``F``). Helpers make an embedding from vertex ids
(:func:`embedding_from_vertices`) or from 3D points near the template (:func:`embedding_from_points`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from capture.io.atomic import write_json
from capture.io.errors import CaptureError

FORMAT = "capture-landmark-embedding"
VERSION = 1
LANDMARKS_DIR = "landmarks"
BARY_TOL = 1e-6


@dataclass(frozen=True)
class LandmarkEmbedding:
    detector: str
    face_index: np.ndarray   # (L,) int64 triangle of the template
    barycentric: np.ndarray  # (L, 3) float64, rows sum to 1
    source: str = ""

    @property
    def count(self) -> int:
        return len(self.face_index)

    def to_json(self) -> dict:
        return {"format": FORMAT, "version": VERSION, "detector": self.detector, "count": self.count,
                "face_index": [int(i) for i in self.face_index],
                "barycentric": [[float(v) for v in row] for row in self.barycentric], "source": self.source}


def embedding_path(actor_path: str | Path, detector: str) -> Path:
    return Path(actor_path) / LANDMARKS_DIR / f"{detector}.json"


def parse_embedding(obj, label: str = "<embedding>") -> LandmarkEmbedding:
    """Validate the JSON of an embedding (keys, types, lengths, rows summing to 1)."""
    if not isinstance(obj, dict):
        raise CaptureError(f"landmark embedding {label} is not a JSON object; see docs/detector_spec.md")
    allowed = {"format", "version", "detector", "count", "face_index", "barycentric", "source"}
    unknown = sorted(set(obj) - allowed)
    if unknown:
        raise CaptureError(f"landmark embedding {label}: unknown key '{unknown[0]}'; allowed keys: "
                           f"{', '.join(sorted(allowed))}")
    for k in ("detector", "count", "face_index", "barycentric"):
        if k not in obj:
            raise CaptureError(f"landmark embedding {label}: missing key '{k}'")
    if obj.get("format", FORMAT) != FORMAT or obj.get("version", VERSION) != VERSION:
        raise CaptureError(f"landmark embedding {label}: format {obj.get('format')!r} version "
                           f"{obj.get('version')!r}; expected {FORMAT!r} version {VERSION}")
    count = obj["count"]
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise CaptureError(f"landmark embedding {label}: count is {count!r}; expected a positive integer")
    try:
        fi = np.asarray(obj["face_index"])
        bc = np.asarray(obj["barycentric"], dtype=np.float64)
    except (TypeError, ValueError):
        raise CaptureError(f"landmark embedding {label}: face_index/barycentric are not numeric lists") from None
    if fi.shape != (count,) or not (np.issubdtype(fi.dtype, np.integer)):
        raise CaptureError(f"landmark embedding {label}: face_index should be {count} integers "
                           f"but it has shape {fi.shape} and type {fi.dtype}")
    if bc.shape != (count, 3):
        raise CaptureError(f"landmark embedding {label}: barycentric should be ({count}, 3) but it is {bc.shape}")
    if not np.isfinite(bc).all():
        raise CaptureError(f"landmark embedding {label}: barycentric holds NaN or infinite values")
    bad = np.abs(bc.sum(axis=1) - 1.0) > BARY_TOL
    if bad.any():
        i = int(np.argmax(bad))
        raise CaptureError(f"landmark embedding {label}: barycentric row {i} sums to {bc[i].sum():.6g}; "
                           f"each row must sum to 1")
    src = obj.get("source", "")
    return LandmarkEmbedding(str(obj["detector"]), fi.astype(np.int64), bc, str(src))


def validate_embedding(emb: LandmarkEmbedding, template, label: str = "<embedding>",
                       detector_count: int | None = None) -> None:
    """Check an embedding against the template (triangle indices in range) and the detector's L."""
    n_faces = len(template.faces)
    bad = (emb.face_index < 0) | (emb.face_index >= n_faces)
    if bad.any():
        i = int(np.argmax(bad))
        raise CaptureError(f"landmark embedding {label}: face_index[{i}] = {int(emb.face_index[i])} but the "
                           f"template has triangles 0..{n_faces - 1}; remake the embedding for this template")
    if np.any(emb.barycentric < -BARY_TOL):
        i = int(np.argmax((emb.barycentric < -BARY_TOL).any(axis=1)))
        raise CaptureError(f"landmark embedding {label}: barycentric row {i} has a negative weight "
                           f"{emb.barycentric[i].tolist()}; the point must lie inside its triangle")
    if detector_count is not None and emb.count != detector_count:
        raise CaptureError(f"landmark embedding {label} has {emb.count} landmarks but the detector gives "
                           f"{detector_count}; remake it for this detector")


def read_embedding(actor_path: str | Path, detector: str, template=None,
                   detector_count: int | None = None) -> LandmarkEmbedding:
    """Read ``A/landmarks/<detector>.json``; validated against ``template`` when given."""
    import json

    path = embedding_path(actor_path, detector)
    if not path.is_file():
        raise CaptureError(f"actor {Path(actor_path).name} has no landmark embedding for detector '{detector}' "
                           f"({path} is missing); make one as docs/detector_spec.md describes")
    try:
        obj = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CaptureError(f"landmark embedding {path} is not valid JSON ({exc}); fix the file") from None
    emb = parse_embedding(obj, str(path))
    if emb.detector != detector:
        raise CaptureError(f"landmark embedding {path} is for detector '{emb.detector}', not '{detector}'; "
                           f"rename the file or fix its 'detector' field")
    if template is not None:
        validate_embedding(emb, template, str(path), detector_count)
    return emb


def write_embedding(actor_path: str | Path, emb: LandmarkEmbedding, template=None) -> Path:
    """Validate (against ``template`` when given) and write ``A/landmarks/<detector>.json`` atomically."""
    parse_embedding(emb.to_json(), emb.detector)
    if template is not None:
        validate_embedding(emb, template, emb.detector)
    return write_json(embedding_path(actor_path, emb.detector), emb.to_json())


def embedded_points(emb: LandmarkEmbedding, template) -> np.ndarray:
    """The landmarks' positions (L, 3) on the template (mm)."""
    v = np.asarray(template.vertices, dtype=np.float64)
    f = np.asarray(template.faces, dtype=np.int64)
    tri = v[f[emb.face_index]]  # (L, 3, 3)
    return np.einsum("lk,lkd->ld", emb.barycentric, tri)


def embedding_from_vertices(template, vertex_ids, detector: str, source: str = "vertex ids") -> LandmarkEmbedding:
    """Landmark l at template vertex ``vertex_ids[l]``: a triangle using it, barycentric one-hot."""
    f = np.asarray(template.faces, dtype=np.int64)
    vid = np.asarray(vertex_ids, dtype=np.int64).reshape(-1)
    n_v = len(template.vertices)
    if vid.size == 0 or vid.min() < 0 or vid.max() >= n_v:
        raise CaptureError(f"landmark vertex ids must be in 0..{n_v - 1}; got {vid.min()}..{vid.max()}")
    face_index = np.empty(len(vid), np.int64)
    bary = np.zeros((len(vid), 3))
    for l, v in enumerate(vid):
        rows, cols = np.nonzero(f == v)
        if len(rows) == 0:
            raise CaptureError(f"template vertex {v} (landmark {l}) is in no triangle; choose another vertex")
        face_index[l] = rows[0]
        bary[l, cols[0]] = 1.0
    return LandmarkEmbedding(detector, face_index, bary, source)


def embedding_from_points(template, points_mm, detector: str, source: str = "closest points",
                          max_distance_mm: float | None = 10.0) -> LandmarkEmbedding:
    """Landmark l at the template point closest to ``points_mm[l]`` (L, 3), e.g. clicked in a viewer."""
    import trimesh

    p = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    closest, dist, tri = trimesh.proximity.closest_point(template, p)
    if max_distance_mm is not None and np.any(dist > max_distance_mm):
        i = int(np.argmax(dist))
        raise CaptureError(f"landmark point {i} is {dist[i]:.1f} mm from the template (more than "
                           f"{max_distance_mm} mm); are the points in the template's frame and in mm?")
    tri = np.asarray(tri, dtype=np.int64)
    bary = trimesh.triangles.points_to_barycentric(template.triangles[tri], closest)
    bary = np.clip(bary, 0.0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    return LandmarkEmbedding(detector, tri, bary, source)
