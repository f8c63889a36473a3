"""Making a detector's landmark embedding on an actor's template from the forms it is published in.

* vertex ids (:func:`capture.detector.embedding.embedding_from_vertices`);
* triangle ids + barycentrics (:func:`embedding_from_triangles`), of the template or of another mesh
  with the same vertices (its triangles are matched to the template's by their vertex ids);
* 3D points near the template (:func:`capture.detector.embedding.embedding_from_points`);
* the detector's canonical mesh, one vertex per landmark (:func:`embedding_from_canonical_mesh`): a
  similarity transform (scale, rotation, translation; no reflection) aligns it to the template, from
  vertex-id pairs (``trimesh.registration.procrustes``) or automatically (ICP with scale against the
  template surface, ``trimesh.registration.icp``, from a start that matches the meshes' widths, their
  x/y centres and their front-most z, so both must be roughly upright and face +z like the template),
  and each aligned landmark is then moved to the closest point of the template surface.

Every maker returns the embedding and a residual report (mm): how far the input points were from
the surface, and for pairs how well the similarity fits them. Readers of the input files are here
too (:func:`read_ints`, :func:`read_triangles`, :func:`read_points`, :func:`read_pairs`); errors are one line.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from capture.detector.embedding import LandmarkEmbedding, embedding_from_points
from capture.io.errors import CaptureError

UNITS = {"mm": 1.0, "cm": 10.0, "m": 1000.0, "in": 25.4}
SURFACE_WARN_MM = 3.0


# ----------------------------------------------------------------------------------------------
# input files


def _load_numbers(path: Path, what: str) -> np.ndarray | dict:
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"{what} file {path} does not exist; check the path")
    if path.suffix == ".npy":
        try:
            return np.load(path, allow_pickle=False)
        except Exception as exc:
            raise CaptureError(f"{what} file {path} is not a readable .npy ({exc})") from None
    text = path.read_text()
    if path.suffix == ".json":
        try:
            obj = json.loads(text)
        except json.JSONDecodeError as exc:
            raise CaptureError(f"{what} file {path} is not valid JSON ({exc}); fix the file") from None
        return obj if isinstance(obj, dict) else np.asarray(obj, dtype=object)
    rows = []
    for line in text.splitlines():
        line = line.split("#")[0].replace(",", " ").strip()
        if line:
            try:
                rows.append([float(v) for v in line.split()])
            except ValueError:
                raise CaptureError(f"{what} file {path}: '{line[:40]}' is not a row of numbers") from None
    if len({len(r) for r in rows}) > 1:
        raise CaptureError(f"{what} file {path}: rows have different numbers of values")
    return np.asarray(rows, dtype=np.float64)


def _as_array(obj, path: Path, what: str, key: str | None = None) -> np.ndarray:
    if isinstance(obj, dict):
        if key is None or key not in obj:
            raise CaptureError(f"{what} file {path}: expected a list{f' or an object with key {key!r}' if key else ''}")
        obj = obj[key]
    try:
        return np.asarray(obj.tolist() if isinstance(obj, np.ndarray) and obj.dtype == object else obj,
                          dtype=np.float64)
    except (TypeError, ValueError):
        raise CaptureError(f"{what} file {path}: the values are not all numbers") from None


def _ints(a: np.ndarray, path: Path, what: str) -> np.ndarray:
    if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
        raise CaptureError(f"{what} file {path}: expected integers")
    return a.astype(np.int64)


def read_ints(path: Path, what: str = "vertex id", key: str = "vertex_ids") -> np.ndarray:
    """One integer per landmark: a JSON list (or {key: list}), a .npy, or text (any whitespace/commas)."""
    a = _as_array(_load_numbers(path, what), path, what, key)
    return _ints(a.reshape(-1), path, what)


def read_triangles(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Triangle ids and barycentrics: JSON {"face_index": [L], "barycentric": [[3] x L]} or text/.npy
    rows ``triangle b0 b1 b2``."""
    obj = _load_numbers(path, "triangle")
    if isinstance(obj, dict):
        fi = _ints(_as_array(obj, path, "triangle", "face_index").reshape(-1), path, "triangle")
        bc = _as_array(obj, path, "triangle", "barycentric")
    else:
        a = _as_array(obj, path, "triangle")
        if a.ndim != 2 or a.shape[1] != 4:
            raise CaptureError(f"triangle file {path}: expected rows 'triangle b0 b1 b2' but found shape {a.shape}")
        fi, bc = _ints(a[:, 0], path, "triangle"), a[:, 1:]
    if bc.shape != (len(fi), 3):
        raise CaptureError(f"triangle file {path}: {len(fi)} triangles but barycentrics of shape {bc.shape}; "
                           f"expected ({len(fi)}, 3)")
    return fi, bc


def read_points(path: Path, units: str = "mm") -> np.ndarray:
    """(L, 3) points: JSON list of [x, y, z] (or {"points": ...}), .npy or text rows; converted to mm."""
    if units not in UNITS:
        raise CaptureError(f"unknown --units '{units}'; use one of {', '.join(UNITS)}")
    a = _as_array(_load_numbers(path, "points"), path, "points", "points")
    if a.ndim != 2 or a.shape[1] != 3:
        raise CaptureError(f"points file {path}: expected (L, 3) x, y, z rows but found shape {a.shape}")
    return a * UNITS[units]


def read_pairs(path: Path) -> np.ndarray:
    """(K, 2) ``landmark_id template_vertex_id`` pairs (JSON [[l, v], ...] or text rows)."""
    a = _as_array(_load_numbers(path, "pairs"), path, "pairs", "pairs")
    if a.ndim != 2 or a.shape[1] != 2:
        raise CaptureError(f"pairs file {path}: expected rows 'landmark_id template_vertex_id' but found "
                           f"shape {a.shape}")
    return _ints(a, path, "pairs")


def read_mesh_vertices(path: Path, units: str = "mm") -> np.ndarray:
    """The vertices (in file order) of an OBJ/PLY mesh, in mm."""
    import trimesh

    if units not in UNITS:
        raise CaptureError(f"unknown --units '{units}'; use one of {', '.join(UNITS)}")
    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"mesh file {path} does not exist; check the path")
    try:
        m = trimesh.load(path, process=False, maintain_order=True)
    except Exception as exc:
        raise CaptureError(f"cannot read mesh {path}: {str(exc)[:120]}") from None
    if isinstance(m, trimesh.Scene):
        geoms = list(m.geometry.values())
        if len(geoms) != 1:
            raise CaptureError(f"mesh {path} holds {len(geoms)} objects; give a file with one mesh")
        m = geoms[0]
    v = np.asarray(getattr(m, "vertices", np.zeros((0, 3))), np.float64)
    if v.ndim != 2 or len(v) == 0:
        raise CaptureError(f"mesh {path} has no vertices")
    return v * UNITS[units]


# ----------------------------------------------------------------------------------------------
# makers


def surface_report(distances: np.ndarray, worst: int = 5) -> dict:
    d = np.asarray(distances, np.float64)
    order = np.argsort(-d)[:worst]
    return {"median_mm": float(np.median(d)), "p95_mm": float(np.percentile(d, 95)), "max_mm": float(d.max()),
            "worst": [{"landmark": int(i), "mm": float(d[i])} for i in order]}


def _closest(template, points: np.ndarray, detector: str, source: str) -> tuple[LandmarkEmbedding, np.ndarray]:
    import trimesh

    emb = embedding_from_points(template, points, detector, source, max_distance_mm=None)
    _, dist, _ = trimesh.proximity.closest_point(template, points)
    return emb, np.asarray(dist, np.float64)


def embedding_from_triangles(template, face_index, barycentric, detector: str, source: str = "triangles",
                             topology=None) -> tuple[LandmarkEmbedding, dict]:
    """Landmarks given as triangles + barycentrics of the template, or of ``topology`` (a mesh with the
    template's vertices in the same order, its own triangle list).

    Another mesh's triangle is matched to the template triangle with the same three vertex ids (the
    barycentrics follow the vertex order); a triangle the template does not have (a quad split along
    the other diagonal) gives the point on the template's vertices, moved to the closest surface point.
    """
    fi = np.asarray(face_index, np.int64).reshape(-1)
    bc = np.asarray(barycentric, np.float64).reshape(-1, 3)
    if len(fi) != len(bc):
        raise CaptureError(f"{len(fi)} triangle ids but {len(bc)} barycentric rows; give one of each per landmark")
    if not np.all(np.isfinite(bc)) or np.any(bc < -1e-6) or np.any(np.abs(bc.sum(axis=1) - 1) > 1e-4):
        i = int(np.argmax(~np.isfinite(bc).all(axis=1) | (bc < -1e-6).any(axis=1) | (np.abs(bc.sum(axis=1) - 1) > 1e-4)))
        raise CaptureError(f"barycentric row {i} is {bc[i].tolist()}; each row must be non-negative and sum to 1")
    bc = np.clip(bc, 0.0, None)
    bc /= bc.sum(axis=1, keepdims=True)
    tf = np.asarray(template.faces, np.int64)
    faces = tf if topology is None else np.asarray(topology.faces, np.int64)
    if topology is not None and len(topology.vertices) != len(template.vertices):
        raise CaptureError(f"the triangles' mesh has {len(topology.vertices)} vertices but the template has "
                           f"{len(template.vertices)}; it must have the template's topology (same vertices)")
    bad = (fi < 0) | (fi >= len(faces))
    if bad.any():
        i = int(np.argmax(bad))
        raise CaptureError(f"triangle id {int(fi[i])} (landmark {i}) is not a triangle of the "
                           f"{'template' if topology is None else 'given mesh'} (0..{len(faces) - 1})")
    if topology is None:
        return LandmarkEmbedding(detector, fi, bc, source), {"method": "triangles of the template", "moved": 0}
    lookup = {tuple(sorted(t)): k for k, t in enumerate(tf)}
    out_fi, out_bc = np.empty_like(fi), np.empty_like(bc)
    unmatched = []
    v = np.asarray(template.vertices, np.float64)
    for l, (t, b) in enumerate(zip(faces[fi], bc)):
        k = lookup.get(tuple(sorted(t)))
        if k is None:
            unmatched.append(l)
            continue
        weights = dict(zip(t.tolist(), b))
        out_fi[l] = k
        out_bc[l] = [weights[int(x)] for x in tf[k]]
    report: dict = {"method": "triangles of a mesh with the template's topology", "moved": len(unmatched)}
    if unmatched:
        idx = np.array(unmatched)
        pts = np.einsum("lk,lkd->ld", bc[idx], v[faces[fi[idx]]])
        e2, dist = _closest(template, pts, detector, source)
        out_fi[idx], out_bc[idx] = e2.face_index, e2.barycentric
        report["moved_to_surface"] = surface_report(dist)
    return LandmarkEmbedding(detector, out_fi, out_bc, source), report


def similarity_matrix(scale: float, rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = scale * np.asarray(rotation)
    m[:3, 3] = translation
    return m


def _apply(m: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ m[:3, :3].T + m[:3, 3]


def _decompose(m: np.ndarray) -> dict:
    s = float(np.cbrt(np.linalg.det(m[:3, :3])))
    return {"scale": s, "rotation": (m[:3, :3] / s).tolist(), "translation_mm": m[:3, 3].tolist()}


def auto_start(points: np.ndarray, template) -> np.ndarray:
    """A start for ICP: the widths (x extents) matched, x/y centres matched, front-most z matched."""
    v = np.asarray(template.vertices, np.float64)
    w_p = np.ptp(points[:, 0])
    s = np.ptp(v[:, 0]) / w_p if w_p > 0 else 1.0
    q = points * s
    t = np.array([(v[:, 0].max() + v[:, 0].min()) / 2 - (q[:, 0].max() + q[:, 0].min()) / 2,
                  v[:, 1].mean() - q[:, 1].mean(), v[:, 2].max() - q[:, 2].max()])
    return similarity_matrix(s, np.eye(3), t)


def embedding_from_canonical_mesh(template, mesh_points: np.ndarray, detector: str, pairs: np.ndarray | None = None,
                                  source: str = "canonical mesh", icp_iterations: int = 200
                                  ) -> tuple[LandmarkEmbedding, dict]:
    """Landmark l = vertex l of the detector's canonical mesh (L, 3), aligned to the template by a
    similarity and moved to the closest surface point (see the module docstring).

    ``pairs`` (K, 2): ``[landmark id, template vertex id]`` correspondences (at least 3, not collinear);
    None: automatic (ICP). Returns the embedding and the report (transform, pair and surface residuals).
    """
    import trimesh

    p = np.asarray(mesh_points, np.float64)
    v = np.asarray(template.vertices, np.float64)
    report: dict = {}
    if pairs is not None:
        pairs = np.asarray(pairs, np.int64).reshape(-1, 2)
        if len(pairs) < 3:
            raise CaptureError(f"a similarity needs at least 3 landmark/vertex pairs; got {len(pairs)}")
        bad_l = (pairs[:, 0] < 0) | (pairs[:, 0] >= len(p))
        bad_v = (pairs[:, 1] < 0) | (pairs[:, 1] >= len(v))
        if bad_l.any() or bad_v.any():
            i = int(np.argmax(bad_l | bad_v))
            raise CaptureError(f"pair {i} = {pairs[i].tolist()}: landmark ids are 0..{len(p) - 1} and template "
                               f"vertex ids 0..{len(v) - 1}")
        a, b = p[pairs[:, 0]], v[pairs[:, 1]]
        if np.linalg.matrix_rank(a - a.mean(0), tol=1e-6 * max(1.0, np.abs(a).max())) < 2:
            raise CaptureError("the paired landmarks are collinear; choose pairs spread over the face "
                               "(e.g. eye corners, nose tip, mouth corners)")
        m, _, _ = trimesh.registration.procrustes(a, b, reflection=False, translation=True, scale=True,
                                                  return_cost=True)
        res = np.linalg.norm(_apply(m, a) - b, axis=1)
        report["method"] = f"similarity from {len(pairs)} landmark/vertex pairs (procrustes)"
        report["pairs_residual"] = {"rms_mm": float(np.sqrt(np.mean(res ** 2))), "max_mm": float(res.max()),
                                    "per_pair_mm": [round(float(r), 4) for r in res]}
    else:
        start = auto_start(p, template)
        m, _, cost = trimesh.registration.icp(p, template, initial=start, threshold=1e-7,
                                              max_iterations=icp_iterations, reflection=False, translation=True,
                                              scale=True)
        report["method"] = "automatic: ICP with scale against the template surface"
    report["transform"] = _decompose(m)
    aligned = _apply(m, p)
    emb, dist = _closest(template, aligned, detector, source)
    report["surface_distance"] = surface_report(dist)
    if report["surface_distance"]["p95_mm"] > SURFACE_WARN_MM:
        report["warning"] = (f"5 % of the landmarks are more than {report['surface_distance']['p95_mm']:.1f} mm "
                             f"from the template after alignment: check the pairs, the units or the mesh")
    return emb, report
