"""Sparse skin-to-bone anatomical constraints (AIM supplement, "Anatomy Constraints").

Pure geometry: a neutral skin ``trimesh.Trimesh`` and bone meshes in, :class:`AnatomyConstraints`
out; no file I/O. Lengths are millimetres.

Algorithm (vectorised over all rays; Embree when available)
-----------------------------------------------------------
For every skin vertex ``v`` in the trusted region, with outward unit vertex normal ``s``:

1. **Inward ray.** Cast from ``v + eps s`` along ``-s`` against all bone meshes at once (they are
   concatenated, ``bone_label`` remembers which one a triangle came from) and take the first hit
   ``b``. The origin is backed off by ``eps`` (1e-4 of the mean skin edge, far above Embree's float32
   resolution) so a bone touching the skin is still found; the distance is measured from ``v``.
2. **Occlusion.** The same ray, started at ``v - eps s`` so it does not hit its own vertex, is cast
   against the skin: if it leaves the skin before reaching the bone (the ray crosses air, e.g. through
   a nostril or between the lips) the candidate is dropped.
3. **Same facing.** Keep ``b`` only if the angle between the outward bone normal at ``b`` and ``s`` is
   below ``max_angle_deg`` and ``|b - v| <= max_thickness``.
4. **Back ray.** Cast from ``b`` (backed off by ``eps`` into the bone) along the bone normal ``n``
   against the skin. Its first hit ``p`` (possibly another skin point) is the constrained skin point:
   its triangle, barycentric coordinates (``trimesh.triangles.points_to_barycentric``), thickness
   ``|p - b|`` and the bone normal are stored. Back rays that miss the skin, are longer than
   ``max_thickness`` or pass through a bone on the way are dropped.
5. **Deduplicate.** Back rays of neighbouring vertices can land on nearly the same skin spot; points
   are hashed into cubes of ``dedup_mm`` (default a quarter of the mean skin edge) and one constraint
   per cube is kept (the one whose back ray landed closest to its own source vertex), so the
   constraints do not over-weight a spot and the coverage does not count one spot twice.

Bone normals: orientation assumption
------------------------------------
Template skull/jaw meshes are often open (cut at the back or around the teeth) and made of several
components, so ``trimesh.repair.fix_normals`` (which only decides the sign of watertight meshes) is
not enough, and orienting each triangle independently toward the skin would be wrong (it would make
the inner surface of an orbit or the back of a thin bone look like it faces the skin, accepting
exactly the constraints the "same facing" test is meant to reject). Instead, per connected component:

* winding is first made consistent (``trimesh.repair.fix_winding``) if it is not;
* a **watertight** component takes its sign from its signed volume (outward = positive volume);
* an **open** component takes one sign for the whole component from an area-weighted vote of its
  triangles within ``max_thickness`` of the skin: the normal should point toward the nearest skin
  vertex (weight: area / (1 + distance)). The surface of a bone that underlies skin faces that skin
  on most of its area, so the vote is decided by the outer surface even when inner surfaces
  (e.g. the inner table of the skull) are near.

Set ``orient_bones=False`` to trust the normals of the input as they are. Reported bone normals are
the barycentric interpolation of the (oriented) vertex normals, which are smooth and closer to the
true surface normal than the facet normal (second-order versus first-order error in the edge length);
the facet normal is used instead where the interpolated one is degenerate or disagrees with it.

Skin normals must point out of the face; an open skin whose area-weighted normals point toward the
bones on average is flipped (with a warning), a watertight skin with negative volume too.

Trusted region
--------------
:func:`default_trusted_region` is an automatic stand-in for the paper's hand-painted region; see its
docstring. With ``trusted=None`` every vertex is tried and the angle, thickness and occlusion tests do
the filtering.
"""

from __future__ import annotations

import logging
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from capture.io.errors import CaptureError

log = logging.getLogger(__name__)

__all__ = [
    "AnatomyConstraints",
    "compute_anatomy_constraints",
    "default_trusted_region",
    "orient_bone_normals",
    "make_ray_intersector",
]

_FIELDS = ("face_index", "barycentric", "skin_point", "bone_point", "thickness", "bone_normal", "bone_label")


@dataclass(frozen=True)
class AnatomyConstraints:
    """M sparse skin-to-bone constraints on the neutral skin (mm).

    face_index: (M,) int64 skin triangle holding the constrained skin point.
    barycentric: (M,3) float64 barycentric coordinates of that point in its triangle.
    skin_point: (M,3) on the neutral skin. bone_point: (M,3). thickness: (M,) = |skin - bone|.
    bone_normal: (M,3) unit, outward bone normal at bone_point (skin_point ~ bone_point + thickness *
    bone_normal). bone_label: (M,) int8 index of the bone mesh hit, in the order given (0 = skull,
    1 = jaw by convention). n_vertices: skin vertex count. n_candidates: skin vertices tried.
    """

    face_index: np.ndarray
    barycentric: np.ndarray
    skin_point: np.ndarray
    bone_point: np.ndarray
    thickness: np.ndarray
    bone_normal: np.ndarray
    bone_label: np.ndarray
    n_vertices: int
    n_candidates: int

    def __post_init__(self) -> None:
        m = len(self.face_index)
        expect = {
            "face_index": (m,),
            "barycentric": (m, 3),
            "skin_point": (m, 3),
            "bone_point": (m, 3),
            "thickness": (m,),
            "bone_normal": (m, 3),
            "bone_label": (m,),
        }
        for name, shape in expect.items():
            a = np.asarray(getattr(self, name))
            if a.shape != shape:
                raise ValueError(f"AnatomyConstraints.{name} has shape {a.shape}, expected {shape}")

    def __len__(self) -> int:
        return len(self.face_index)

    @property
    def coverage(self) -> float:
        """Constraints per skin vertex (M / n_vertices); the paper reports 0.05-0.10."""
        return len(self) / self.n_vertices if self.n_vertices else 0.0

    def summary(self) -> dict[str, float]:
        """Plain figures for reports: count, coverage, thickness statistics (mm)."""
        t = self.thickness
        out = {"count": float(len(self)), "coverage": self.coverage, "n_candidates": float(self.n_candidates)}
        if len(t):
            out.update(
                thickness_min=float(t.min()),
                thickness_median=float(np.median(t)),
                thickness_mean=float(t.mean()),
                thickness_max=float(t.max()),
            )
        return out

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays for npz/safetensors storage (no pickled objects)."""
        d = {name: np.ascontiguousarray(getattr(self, name)) for name in _FIELDS}
        d["n_vertices"] = np.array(self.n_vertices, dtype=np.int64)
        d["n_candidates"] = np.array(self.n_candidates, dtype=np.int64)
        return d

    @classmethod
    def from_arrays(cls, d: dict[str, np.ndarray]) -> "AnatomyConstraints":
        missing = [k for k in (*_FIELDS, "n_vertices", "n_candidates") if k not in d]
        if missing:
            raise CaptureError(f"anatomy constraints are missing {missing}: recompute them")
        return cls(
            face_index=np.asarray(d["face_index"], dtype=np.int64),
            barycentric=np.asarray(d["barycentric"], dtype=np.float64),
            skin_point=np.asarray(d["skin_point"], dtype=np.float64),
            bone_point=np.asarray(d["bone_point"], dtype=np.float64),
            thickness=np.asarray(d["thickness"], dtype=np.float64),
            bone_normal=np.asarray(d["bone_normal"], dtype=np.float64),
            bone_label=np.asarray(d["bone_label"], dtype=np.int8),
            n_vertices=int(np.asarray(d["n_vertices"])),
            n_candidates=int(np.asarray(d["n_candidates"])),
        )


# ----------------------------------------------------------------------------------------------
# ray casting


def make_ray_intersector(mesh: trimesh.Trimesh):
    """trimesh's fastest ray backend for ``mesh``: Embree if importable, else the triangle backend."""
    try:
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        return RayMeshIntersector(mesh)
    except Exception as exc:  # embreex missing or broken
        warnings.warn(
            f"Embree ray backend unavailable ({exc}); using trimesh's slow triangle backend. "
            "Install it with: pip install embreex",
            RuntimeWarning,
            stacklevel=2,
        )
        from trimesh.ray.ray_triangle import RayMeshIntersector

        return RayMeshIntersector(mesh)


def _first_hits(
    intersector, mesh: trimesh.Trimesh, origins: np.ndarray, directions: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First hit of each ray: (triangle (R,) int64, -1 = miss; distance (R,) along the unit direction;
    location (R,3)), recomputed in float64 on the hit triangle's plane."""
    r = len(origins)
    tri = np.full(r, -1, dtype=np.int64)
    dist = np.full(r, np.inf)
    loc = np.full((r, 3), np.nan)
    if r == 0:
        return tri, dist, loc
    tri = np.asarray(intersector.intersects_first(origins, directions), dtype=np.int64)
    hit = np.flatnonzero(tri >= 0)
    if len(hit):
        p0 = mesh.triangles[tri[hit], 0]
        fn = mesh.face_normals[tri[hit]]
        denom = np.einsum("ij,ij->i", directions[hit], fn)
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.einsum("ij,ij->i", p0 - origins[hit], fn) / denom
        ok = np.isfinite(t) & (np.abs(denom) > 1e-12)
        t = np.where(ok, t, np.nan)
        dist[hit] = t
        loc[hit] = origins[hit] + t[:, None] * directions[hit]
        bad = hit[~ok]
        tri[bad] = -1
        dist[bad] = np.inf
    return tri, dist, loc


# ----------------------------------------------------------------------------------------------
# orientation


def _face_components(mesh: trimesh.Trimesh) -> np.ndarray:
    """(F,) connected component label per face (through shared edges)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nf = len(mesh.faces)
    adj = mesh.face_adjacency
    if len(adj) == 0:
        return np.arange(nf)
    g = coo_matrix((np.ones(len(adj)), (adj[:, 0], adj[:, 1])), shape=(nf, nf))
    _, labels = connected_components(g, directed=False)
    return labels


def orient_bone_normals(bone: trimesh.Trimesh, skin_vertices: np.ndarray, max_distance: float) -> trimesh.Trimesh:
    """A copy of ``bone`` whose face winding makes every normal point out of the bone.

    Per connected component: watertight -> sign of the signed volume; open -> area-weighted vote of
    triangles within ``max_distance`` of the skin for pointing toward the nearest skin vertex (see
    the module docstring). Components with no triangle near the skin keep their input orientation.
    """
    mesh = trimesh.Trimesh(bone.vertices.copy(), bone.faces.copy(), process=False)
    if len(mesh.faces) == 0:
        return mesh
    if not mesh.is_winding_consistent:
        try:
            trimesh.repair.fix_winding(mesh)
        except ImportError as exc:  # networkx missing
            log.warning("cannot make bone winding consistent (%s); pip install networkx", exc)
    labels = _face_components(mesh)
    n_comp = labels.max() + 1
    tri = mesh.triangles
    # signed volume per component (divergence theorem; exact for closed components)
    vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])) / 6.0
    vol_c = np.bincount(labels, weights=vol, minlength=n_comp)
    # watertight per component: every edge shared by exactly two faces of it
    edges = np.sort(mesh.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, inv, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    open_edge_face = counts[inv.ravel()] != 2
    not_closed = np.bincount(labels[np.repeat(np.arange(len(mesh.faces)), 3)[open_edge_face]], minlength=n_comp) > 0
    # skin-facing vote for every component
    centres = tri.mean(axis=1)
    dist, idx = cKDTree(skin_vertices).query(centres, workers=-1)
    to_skin = skin_vertices[idx] - centres
    area = mesh.area_faces
    near = dist <= max_distance
    vote = np.sign(np.einsum("ij,ij->i", mesh.face_normals, to_skin)) * area / (1.0 + dist)
    vote_c = np.bincount(labels[near], weights=vote[near], minlength=n_comp)
    flip_c = np.where(~not_closed, vol_c < 0, vote_c < 0)
    flip = flip_c[labels]
    if flip.any():
        faces = mesh.faces.copy()
        faces[flip] = faces[flip][:, ::-1]
        mesh = trimesh.Trimesh(mesh.vertices, faces, process=False)
    return mesh


def _orient_skin(skin: trimesh.Trimesh, bone_centre: np.ndarray) -> trimesh.Trimesh:
    mesh = trimesh.Trimesh(skin.vertices.copy(), skin.faces.copy(), process=False)
    if mesh.is_watertight:
        flip = mesh.volume < 0
    else:
        away = mesh.triangles_center - bone_centre
        flip = float(np.sum(np.einsum("ij,ij->i", mesh.face_normals, away) * mesh.area_faces)) < 0
    if flip:
        log.warning("the skin normals point inward; flipping them for the constraint computation")
        mesh = trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)
    return mesh


def _check_mesh(mesh: trimesh.Trimesh, what: str) -> None:
    if not isinstance(mesh, trimesh.Trimesh):
        raise CaptureError(f"the {what} must be a triangle mesh, got {type(mesh).__name__}")
    if len(mesh.faces) == 0 or len(mesh.vertices) < 3:
        raise CaptureError(f"the {what} mesh is empty: check the file")
    if not np.all(np.isfinite(mesh.vertices)):
        raise CaptureError(f"the {what} mesh has NaN or infinite vertex coordinates: fix or re-export it")


def _interp_normals(mesh: trimesh.Trimesh, tri: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Unit normals at points on triangles: barycentric blend of vertex normals, facet fallback."""
    fn = mesh.face_normals[tri]
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[tri], points)
    vn = mesh.vertex_normals[mesh.faces[tri]]  # (R,3,3)
    n = np.einsum("ij,ijk->ik", bary, vn)
    norm = np.linalg.norm(n, axis=1)
    ok = (norm > 0.5) & (np.einsum("ij,ij->i", n, fn) > 0.5 * np.maximum(norm, 1e-12))
    out = fn.copy()
    out[ok] = n[ok] / norm[ok, None]
    return out


# ----------------------------------------------------------------------------------------------
# public API


def compute_anatomy_constraints(
    skin: trimesh.Trimesh,
    bones: Sequence[trimesh.Trimesh],
    trusted: np.ndarray | None = None,
    max_thickness: float = 15.0,
    max_angle_deg: float = 30.0,
    *,
    orient_bones: bool = True,
    check_occlusion: bool = True,
    dedup_mm: float | None = None,
    consistency_radius_mm: float = 6.0,
    max_thickness_jump_mm: float = 2.0,
    smooth_mm: float = 4.0,
) -> AnatomyConstraints:
    """Sparse skin-to-bone constraints by ray casting (see the module docstring).

    Args:
        skin: neutral skin, V vertices, outward normals, mm.
        bones: bone meshes in mm (e.g. [skull, jaw]); their order defines ``bone_label``.
        trusted: (V,) bool mask of skin vertices to try; None = all.
        max_thickness: longest accepted skin-to-bone distance, mm (both rays).
        max_angle_deg: largest accepted angle between the bone normal and the skin normal.
        orient_bones: make bone normals outward (module docstring); False trusts the input winding.
        check_occlusion: drop inward rays that leave the skin before reaching the bone.
        dedup_mm: cube size for merging back-ray hits on the same spot; default 1/4 mean skin edge,
            0 disables.
        consistency_radius_mm, max_thickness_jump_mm: a constraint whose thickness differs by more
            than the jump from the median thickness of the constraints within the radius is dropped
            (:func:`consistent_constraints`); radius 0 disables.
        smooth_mm: Gaussian width (on the skin) over which bone normals and thicknesses are
            averaged, the bone point then re-derived as ``skin_point - thickness * normal`` so the
            three targets stay consistent (:func:`smooth_constraint_fields`); 0 disables.

    Returns:
        AnatomyConstraints with M rows.

    Raises:
        CaptureError: NaN in the inputs, a wrong mask, or no constraint found at all.

    Example:
        >>> c = compute_anatomy_constraints(neutral, [skull, jaw])
        >>> c.coverage, np.median(c.thickness)
    """
    _check_mesh(skin, "skin")
    bones = list(bones)
    if not bones:
        raise CaptureError("no bone mesh given: pass --skull and/or --jaw, or use the estimated bone surface")
    for i, b in enumerate(bones):
        _check_mesh(b, f"bone #{i}")
    if not (np.isfinite(max_thickness) and max_thickness > 0):
        raise CaptureError(f"max_thickness must be a positive number of mm, got {max_thickness}")
    nv = len(skin.vertices)
    if trusted is None:
        trusted_mask = np.ones(nv, dtype=bool)
    else:
        trusted_mask = np.asarray(trusted)
        if trusted_mask.shape != (nv,) or trusted_mask.dtype != bool:
            raise CaptureError(
                f"the trusted region must be a boolean mask over the {nv} skin vertices, "
                f"got shape {trusted_mask.shape} and dtype {trusted_mask.dtype}"
            )

    # one mesh for all bones; face -> bone label
    bone_all = trimesh.util.concatenate(
        [trimesh.Trimesh(b.vertices, b.faces, process=False) for b in bones]
    )
    label_of_face = np.repeat(np.arange(len(bones), dtype=np.int8), [len(b.faces) for b in bones])
    skin = _orient_skin(skin, bone_all.vertices.mean(axis=0))
    if orient_bones:
        bone_all = orient_bone_normals(bone_all, np.asarray(skin.vertices), max_thickness)

    edge = float(skin.edges_unique_length.mean())
    eps = 1e-4 * edge
    if dedup_mm is None:
        dedup_mm = 0.25 * edge
    skin_rays = make_ray_intersector(skin)
    bone_rays = make_ray_intersector(bone_all)

    cand = np.flatnonzero(trusted_mask)
    v = np.asarray(skin.vertices)[cand]
    s = np.asarray(skin.vertex_normals)[cand]
    good_n = np.linalg.norm(s, axis=1) > 0.5
    cand, v, s = cand[good_n], v[good_n], s[good_n]

    # 1. inward ray to the bones
    btri, bdist, bloc = _first_hits(bone_rays, bone_all, v + eps * s, -s)
    thick_in = bdist - eps
    keep = (btri >= 0) & (thick_in <= max_thickness)
    # 2. the inward ray must stay inside the skin until it reaches the bone
    if check_occlusion and keep.any():
        k = np.flatnonzero(keep)
        stri, sdist, _ = _first_hits(skin_rays, skin, v[k] - eps * s[k], -s[k])
        occluded = (stri >= 0) & (sdist + eps < thick_in[k])
        keep[k[occluded]] = False
    # 3. same facing
    k = np.flatnonzero(keep)
    bn = _interp_normals(bone_all, btri[k], bloc[k])
    cos = np.einsum("ij,ij->i", bn, s[k])
    facing = cos >= np.cos(np.radians(max_angle_deg))
    k, bn = k[facing], bn[facing]
    bpt, blab = bloc[k], label_of_face[btri[k]]
    src = v[k]

    # 4. back ray along the bone normal to the skin
    ftri, fdist, floc = _first_hits(skin_rays, skin, bpt - eps * bn, bn)
    thick = fdist - eps
    ok = (ftri >= 0) & (thick <= max_thickness) & (thick >= 0)
    if ok.any():
        # the back ray must not cross a bone on its way out
        j = np.flatnonzero(ok)
        otri, odist, _ = _first_hits(bone_rays, bone_all, bpt[j] + eps * bn[j], bn[j])
        blocked = (otri >= 0) & (odist + eps < thick[j])
        ok[j[blocked]] = False
    ftri, floc, thick, bpt, bn, blab, src = (a[ok] for a in (ftri, floc, thick, bpt, bn, blab, src))

    # 5. one constraint per small cube of skin
    if dedup_mm and dedup_mm > 0 and len(ftri):
        key = np.floor(floc / dedup_mm).astype(np.int64)
        slide = np.linalg.norm(floc - src, axis=1)
        order = np.lexsort((slide, key[:, 2], key[:, 1], key[:, 0]))
        ks = key[order]
        first = np.ones(len(order), dtype=bool)
        first[1:] = np.any(ks[1:] != ks[:-1], axis=1)
        sel = np.sort(order[first])
        ftri, floc, thick, bpt, bn, blab = (a[sel] for a in (ftri, floc, thick, bpt, bn, blab))

    # 6. drop constraints that disagree with their neighbourhood (layer jumps, teeth, closed orbits)
    if consistency_radius_mm > 0 and len(ftri):
        keep = consistent_constraints(floc, thick, consistency_radius_mm, max_thickness_jump_mm)
        ftri, floc, thick, bpt, bn, blab = (a[keep] for a in (ftri, floc, thick, bpt, bn, blab))

    if smooth_mm > 0 and len(ftri):
        thick, bn = smooth_constraint_fields(floc, thick, bn, smooth_mm)
        bpt = floc - thick[:, None] * bn

    if len(ftri) == 0:
        raise CaptureError(
            "the bones do not underlie the skin: no skin-to-bone constraint found; "
            "check units and placement of --skull/--jaw"
        )
    bary = trimesh.triangles.points_to_barycentric(skin.triangles[ftri], floc)
    return AnatomyConstraints(
        face_index=ftri.astype(np.int64),
        barycentric=bary.astype(np.float64),
        skin_point=floc.astype(np.float64),
        bone_point=bpt.astype(np.float64),
        thickness=thick.astype(np.float64),
        bone_normal=bn.astype(np.float64),
        bone_label=blab.astype(np.int8),
        n_vertices=int(nv),
        n_candidates=int(trusted_mask.sum()),
    )


def smooth_constraint_fields(skin_points: np.ndarray, thickness: np.ndarray, normals: np.ndarray,
                             sigma_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Gaussian-weighted averages (width ``sigma_mm`` on the skin, cut at 3 sigma) of the constraints'
    thickness ``(M,)`` and bone normals ``(M, 3)`` (renormalised).

    A fitted template skull is a rough estimate whose triangles tilt from one to the next; the
    neutral is rebuilt as ``b + d n``, so a normal target off by 1 degree under 10 mm of tissue
    asks for 0.17 mm of skin error, and a normal field that flickers at the bone mesh's resolution
    cannot be learned by a smooth network. Averaging over a few millimetres keeps the anatomy's
    shape and removes that flicker; the caller re-derives the bone point so that
    ``bone + thickness * normal`` is still the skin point.
    """
    tree = cKDTree(skin_points)
    pairs = tree.query_pairs(r=3.0 * sigma_mm, output_type="ndarray")
    i = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(len(skin_points))])
    j = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(len(skin_points))])
    w = np.exp(-np.sum((skin_points[i] - skin_points[j]) ** 2, axis=1) / (2 * sigma_mm ** 2))
    wsum = np.bincount(i, weights=w, minlength=len(skin_points))
    d = np.bincount(i, weights=w * thickness[j], minlength=len(skin_points)) / wsum
    n = np.stack([np.bincount(i, weights=w * normals[j, k], minlength=len(skin_points)) for k in range(3)], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return d, n


def consistent_constraints(skin_points: np.ndarray, thickness: np.ndarray, radius_mm: float,
                           max_jump_mm: float) -> np.ndarray:
    """(M,) bool: constraints whose thickness is within ``max_jump_mm`` of the median thickness of
    the constraints within ``radius_mm`` on the skin (itself included).

    The supplement keeps constraints only inside a hand-painted trusted region. This is its
    automatic counterpart: where neighbouring rays land on different bone layers (overlapping
    shells, teeth behind the lips, a closed orbit plate behind the eyelid) the thickness field
    jumps, and such targets would ask the smooth networks for a discontinuity. A smooth bone
    under smooth skin passes: over 6 mm the thickness of a face changes by far less than 2 mm.
    """
    tree = cKDTree(skin_points)
    groups = tree.query_ball_point(skin_points, r=radius_mm)
    med = np.array([np.median(thickness[g]) for g in groups])
    return np.abs(thickness - med) <= max_jump_mm


def default_trusted_region(skin: trimesh.Trimesh, frame=None, *, boundary_margin_mm: float = 10.0) -> np.ndarray:
    """(V,) bool: skin vertices whose bone fit can be trusted, an automatic stand-in for a painted mask.

    Rule: drop vertices within ``boundary_margin_mm`` (shortest path along mesh edges) of an open
    boundary: the rims of the eye and mouth openings (eyelids and lips have no bone beneath them at a
    stable depth) and the cut border of the scan (neck, scalp, ears). The rest is left to the
    thickness, angle and occlusion tests of :func:`compute_anatomy_constraints`. ``frame`` is
    accepted for a future anatomical rule and is not used yet.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    _check_mesh(skin, "skin")
    nv = len(skin.vertices)
    edges = skin.edges_sorted
    _, inv, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    boundary_vertices = np.unique(edges[counts[inv.ravel()] == 1])
    if len(boundary_vertices) == 0:
        return np.ones(nv, dtype=bool)
    eu = skin.edges_unique
    w = skin.edges_unique_length
    g = coo_matrix((w, (eu[:, 0], eu[:, 1])), shape=(nv, nv)).tocsr()
    dist = dijkstra(g, directed=False, indices=boundary_vertices, min_only=True, limit=boundary_margin_mm * 1.01)
    return ~(dist <= boundary_margin_mm)
