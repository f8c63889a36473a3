#!/usr/bin/env python
"""Build the bundled sample actor (capture/data/sample_actor) from the public assets.

    python scripts/make_sample_actor.py [--assets ../shared/assets] [--out capture/data/sample_actor]

What it makes (everything in millimetres, ICT frame: y up, z towards the face front):

* ``shapes/neutral.ply`` + 19 ``shapes/<expression>.ply``: one ICT FaceKit identity
  (``sample_identity_coeffs`` on the 100 identity modes of the Light model) and single ARKit
  expression deltas at full weight, face region only (vertices 0..9408, polygons 0..9229, quads
  split along the a-c diagonal, winding checked to point away from the head centre).
* ``bones/skull.ply`` and ``bones/jaw.ply``: skull = ArtiSynth dynjaw maxilla (+ upper teeth) and
  the upper part of the odedstein CC-BY skull (vault, forehead, orbits, nasal bones, zygomas);
  jaw = ArtiSynth mandible. They start in the ICT generic neutral frame (teeth-matched placement),
  are carried to this actor by the identity deformation of the ICT model (thin-plate-spline
  interpolation of the displacement of ICT vertices on the face, head, sockets, gums, teeth and
  eyeballs), pushed at least ``MIN_THICKNESS_MM`` behind the skin along the skin normal, moved
  under forehead / nasion / chin / cheeks towards typical adult soft-tissue thicknesses (smooth
  bumps, teeth fixed) and pushed again. Winding fixed per connected component (normals outward).
* ``sample.json``: provenance, shape lists (training / held out), landmarks and the fit report.
* ``preview.png``, ``README.md`` and ``LICENSES/``.

Choice of the 19 training expressions (the paper trains on a neutral + 19 expressions). ICT splits
almost every expression into a left and a right shape; the product fits spatially varying
coefficients, so a motion is only available on a side of the face if some training shape moves
that side. We therefore take
  * the 4 jaw shapes (jawOpen, jawLeft, jawRight, jawForward): the rigid jaw motion the model's
    skinning must explain; the ICT lower teeth give their ground truth,
  * the 2 symmetric lip shapes mouthPucker and mouthFunnel,
  * both sides of the most frequent expressions in speech and emotion: mouthSmile, eyeBlink,
    browInnerUp, browDown (8 shapes),
  * one side of browOuterUp, cheekPuff, mouthStretch, mouthFrown, noseSneer, alternating sides
    (L, R, L, R, L) so that each half of the face gets every kind of motion at least in one
    region; the mirrored shape is held out and tests generalisation.
The other 34 (eye gaze, squints, eyeWide, cheekSquint, dimples, press, roll, shrug, upper-up,
lower-down, mouthLeft/Right, mouthClose and the mirrored halves) are held out for benchmarks.
mouthClose is a corrective shape (lips together while the jaw is open) and is only meaningful in
combination with jawOpen.

Choice of the skull: hybrid. The ArtiSynth maxilla comes from the same CT subject as the mandible
and is aligned to the ICT upper teeth, so it is kept. The ArtiSynth cranium is only a coarse cap
(no lower forehead, orbit rims or nasion), which left the upper face without bone; the odedstein
skull is complete there and, similarity-placed on the ArtiSynth bones by ICP (median 2.4 mm),
lies right under the ICT forehead and scalp. Its fused mandible and its copy of the maxilla are
cut away; the cranium cap only serves as an ICP reference. (The odedstein orbits are capped,
which is harmless: rays from the eyelids hit the cap deep behind the skin.)
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import trimesh
from scipy.interpolate import RBFInterpolator
from scipy.sparse import coo_matrix
from scipy.spatial import cKDTree

REPO = Path(__file__).resolve().parents[1]
DEFAULT_ASSETS = REPO.parent / "shared" / "assets"
DEFAULT_OUT = REPO / "capture" / "data" / "sample_actor"

CM_TO_MM = 10.0
FACE_NV = 9409          # face region vertices 0..9408
FACE_NF = 9230          # face region polygons 0..9229
HEAD_NV = 11248         # face + head & neck vertices 0..11247
HEAD_NF = 11144         # face + head & neck polygons 0..11143
UPPER_TEETH = (17039, 19246)
LOWER_TEETH = (19247, 21450)
MIN_THICKNESS_MM = 2.5
N_IDENTITY = 100

TRAINING_EXPRESSIONS = [
    "jawOpen", "jawLeft", "jawRight", "jawForward",
    "mouthPucker", "mouthFunnel",
    "mouthSmile_L", "mouthSmile_R",
    "eyeBlink_L", "eyeBlink_R",
    "browInnerUp_L", "browInnerUp_R",
    "browDown_L", "browDown_R",
    "browOuterUp_L", "cheekPuff_R", "mouthStretch_L", "mouthFrown_R", "noseSneer_L",
]

# ICT regions used to carry the bones from the generic neutral to the actor (inclusive ranges).
# Eyelashes, lacrimal, eye-blend and occlusion shells are thin cosmetic layers and are left out.
DEFORMATION_SOURCE_RANGES = [
    (0, 11247),       # face, head and neck
    (11248, 13293),   # mouth socket
    (13294, 14061),   # eye sockets
    (14062, 17038),   # gums and tongue
    (17039, 21450),   # teeth
    (21451, 24590),   # eyeballs
]


def log(msg: str) -> None:
    print(msg, flush=True)


def sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


# --------------------------------------------------------------------------------------------
# ICT model
# --------------------------------------------------------------------------------------------

def load_ict(assets: Path) -> dict:
    path = assets / "ict_facekit" / "derived" / "ict_facekit_light.npz"
    if not path.is_file():
        sys.exit(f"error: ICT FaceKit arrays not found at {path} (pass --assets)")
    d = np.load(path, allow_pickle=False)
    return {k: d[k] for k in d.files} | {"_path": path}


def actor_neutral_cm(ict: dict) -> np.ndarray:
    """Generic neutral + the sample identity on the 100 identity modes of the Light model (cm)."""
    coeffs = ict["sample_identity_coeffs"][:N_IDENTITY].astype(np.float64)
    deltas = ict["identity_deltas"][:N_IDENTITY].astype(np.float64)
    return ict["neutral"] + np.tensordot(coeffs, deltas, axes=1)


def triangulate(polys: np.ndarray) -> np.ndarray:
    """(F,4) polygons with -1 padding for triangles -> triangles; quads split a-b-c / a-c-d."""
    polys = np.asarray(polys)
    is_tri = polys[:, 3] < 0
    tris = [polys[is_tri, :3], polys[~is_tri][:, [0, 1, 2]], polys[~is_tri][:, [0, 2, 3]]]
    # Keep the two halves of a quad next to each other: order by source polygon.
    src = np.concatenate([np.flatnonzero(is_tri), np.flatnonzero(~is_tri), np.flatnonzero(~is_tri)])
    order = np.argsort(src, kind="stable")
    return np.concatenate(tris)[order].astype(np.int64)


def outward_fraction(verts: np.ndarray, tris: np.ndarray, centre: np.ndarray) -> float:
    """Area-weighted fraction of triangles whose normal points away from ``centre``."""
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    cross = np.cross(b - a, c - a)
    dots = np.einsum("ij,ij->i", cross, (a + b + c) / 3.0 - centre)
    area = np.linalg.norm(cross, axis=1)
    return float(area[dots > 0].sum() / area.sum())


def head_centre(verts_head: np.ndarray) -> np.ndarray:
    """A point inside the head: centre of the bounding box of face + head & neck vertices,
    taken at the height of the eyes' bounding box middle (avoids the neck pulling it down)."""
    lo, hi = verts_head.min(0), verts_head.max(0)
    return (lo + hi) / 2.0


# --------------------------------------------------------------------------------------------
# Bones
# --------------------------------------------------------------------------------------------

def load_obj_cm(path: Path) -> trimesh.Trimesh:
    if not path.is_file():
        sys.exit(f"error: bone mesh not found: {path}")
    return trimesh.load(path, process=False, force="mesh")


def clean_mesh(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    mesh = trimesh.Trimesh(mesh.vertices.copy(), mesh.faces.copy(), process=True)  # merges duplicates
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    return mesh


def fix_winding_per_component(mesh: trimesh.Trimesh, centre: np.ndarray) -> tuple[trimesh.Trimesh, int]:
    """Make triangles consistently wound inside each connected component and outward facing.

    Closed components: sign of the enclosed volume. Open components (fragments of the maxilla):
    area-weighted vote of the normals against the direction from the component's own centroid,
    or from ``centre`` (a point inside the head) when that vote is clearer (thin curved shells).
    Returns the fixed mesh and the number of flipped components."""
    parts = mesh.split(only_watertight=False)
    fixed, flipped = [], 0
    for part in parts:
        part = trimesh.Trimesh(part.vertices, part.faces, process=False)
        trimesh.repair.fix_winding(part)           # consistent winding inside the component
        if part.is_watertight:
            outward = part.volume > 0
        else:
            tc, n, w = part.triangles_center, part.face_normals, part.area_faces
            own = float(np.sum(w * np.einsum("ij,ij->i", n, tc - part.vertices.mean(0))))
            glob = float(np.sum(w * np.einsum("ij,ij->i", n, tc - centre)))
            outward = glob > 0 if abs(glob) > abs(own) else own > 0
        if not outward:
            part.invert()
            flipped += 1
        fixed.append(part)
    out = trimesh.util.concatenate(fixed)
    return trimesh.Trimesh(out.vertices, out.faces, process=False), flipped


def load_odedstein_upper_skull(path: Path, maxilla: trimesh.Trimesh, jaw: trimesh.Trimesh,
                               cranium: trimesh.Trimesh) -> tuple[trimesh.Trimesh, dict]:
    """The odedstein skull (watertight, outward, arbitrary units) placed on the ArtiSynth bones
    in the ICT generic frame (cm) and cut to what ArtiSynth lacks: vault, forehead, orbits,
    nasal bones, zygomas and skull base. Faces near the ArtiSynth maxilla (< 4 mm) or mandible
    (< 8 mm), and the fused mandible below the occlusal level, are removed; small fragments
    (< 150 triangles) are dropped. The original outward winding is kept.

    Placement: scale from the skull width, top and front aligned to the ArtiSynth bones' bounding
    box, then similarity ICP of the ArtiSynth vertices (maxilla, cranium cap, mandible) onto it."""
    raw = trimesh.load(path, process=False, force="mesh")
    oded = trimesh.Trimesh(raw.vertices, raw.faces, process=True)   # merge per-face-normal splits
    assert oded.is_watertight and oded.volume > 0
    art = np.concatenate([maxilla.vertices, cranium.vertices, jaw.vertices])
    lo, hi = art.min(0), art.max(0)
    ob = oded.bounds
    s = (hi[0] - lo[0]) / (ob[1, 0] - ob[0, 0])
    init = np.eye(4)
    init[:3, :3] *= s
    init[:3, 3] = [(hi[0] + lo[0]) / 2 - s * (ob[0, 0] + ob[1, 0]) / 2,
                   hi[1] - s * ob[1, 1], hi[2] - s * ob[1, 2]]
    oded.apply_transform(init)
    m, _, cost = trimesh.registration.icp(art[::3], oded, initial=np.eye(4), max_iterations=60,
                                          scale=True, reflection=False, translation=True)
    oded.apply_transform(np.linalg.inv(m))
    _, d_fit, _ = trimesh.proximity.closest_point(oded, art[::5])
    tc = oded.triangles_center
    _, dm, _ = trimesh.proximity.closest_point(maxilla, tc)
    _, dj, _ = trimesh.proximity.closest_point(jaw, tc)
    occlusal_y = maxilla.vertices[:, 1].min()
    keep = (dm > 0.4) & (dj > 0.8) & ~((tc[:, 1] < occlusal_y + 0.3) & (dj < dm))
    cut = oded.submesh([np.flatnonzero(keep)], append=True)
    parts = [p for p in cut.split(only_watertight=False) if len(p.faces) >= 150]
    upper = trimesh.util.concatenate(parts)
    upper = trimesh.Trimesh(upper.vertices, upper.faces, process=False)
    info = {"scale_cm_per_unit": round(float(s / np.cbrt(abs(np.linalg.det(m[:3, :3])))), 4),
            "artisynth_to_odedstein_distance_cm": {"median": round(float(np.median(d_fit)), 3),
                                                   "p90": round(float(np.percentile(d_fit, 90)), 3)},
            "triangles_kept": int(len(upper.faces)), "triangles_total": int(len(oded.faces))}
    return upper, info


def identity_transfer(points_cm: np.ndarray, generic_cm: np.ndarray, actor_cm: np.ndarray,
                      spacing_cm: float = 0.4) -> np.ndarray:
    """Carry points from the ICT generic neutral to the actor with the identity deformation field.

    The displacement actor - generic of ICT vertices (face, head, sockets, gums, teeth, eyeballs)
    is interpolated by a global thin-plate spline on a voxel-thinned subset of them (one vertex
    per ``spacing_cm`` cell), which is smooth and extrapolates affinely to the cranium."""
    idx = np.concatenate([np.arange(a, b + 1) for a, b in DEFORMATION_SOURCE_RANGES])
    src = generic_cm[idx]
    keys = np.floor(src / spacing_cm).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    sel = idx[np.sort(first)]
    disp = actor_cm[sel] - generic_cm[sel]
    rbf = RBFInterpolator(generic_cm[sel], disp, kernel="thin_plate_spline", smoothing=1e-3)
    out = np.empty_like(points_cm)
    for i in range(0, len(points_cm), 4000):
        out[i:i + 4000] = points_cm[i:i + 4000] + rbf(points_cm[i:i + 4000])
    log(f"  identity transfer: {len(sel)} ICT control points, "
        f"|displacement| median {np.median(np.linalg.norm(out - points_cm, axis=1)) * 10:.2f} mm")
    return out


class Skin:
    """The actor's outer skin (face + head & neck) for distances and inside tests."""

    def __init__(self, verts_mm: np.ndarray, tris: np.ndarray, face_nv: int = FACE_NV):
        self.mesh = trimesh.Trimesh(verts_mm, tris, process=False)
        self.vn = np.asarray(self.mesh.vertex_normals)
        self.face_nv = face_nv

    def closest(self, points: np.ndarray):
        """Closest skin point, signed distance (>0 outside) and interpolated skin normal."""
        q, dist, tri = trimesh.proximity.closest_point(self.mesh, points)
        corners = self.mesh.triangles[tri]
        bary = trimesh.triangles.points_to_barycentric(corners, q)
        bary = np.clip(bary, 0, None)
        bary /= bary.sum(1, keepdims=True)
        n = np.einsum("ij,ijk->ik", bary, self.vn[self.mesh.faces[tri]])
        n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
        side = np.sign(np.einsum("ij,ij->i", points - q, n))
        return q, dist * side, n, tri


def mesh_neighbours(mesh: trimesh.Trimesh):
    edges = mesh.edges_unique
    n = len(mesh.vertices)
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    a = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n)).tocsr()
    deg = np.asarray(a.sum(1)).ravel()
    deg[deg == 0] = 1
    return a, deg


def enforce_min_thickness(bones: list[trimesh.Trimesh], skin: Skin, exempt: list[np.ndarray],
                          dmin: float, iters: int = 30) -> dict:
    """Push bone vertices that are outside the skin or closer than ``dmin`` to it inward along the
    local skin normal. The corrections are smoothed over each bone mesh (so the bone is moved as
    a patch, not as spikes) and the process is repeated until no vertex violates the bound; a
    final exact pass makes it hold for every vertex. ``exempt`` masks vertices whose closest skin
    is not outer skin (teeth behind the lips, which face the mouth cavity)."""
    stats = {}
    for bi, (bone, ex) in enumerate(zip(bones, exempt)):
        adj, deg = mesh_neighbours(bone)
        v = bone.vertices.copy()
        moved = np.zeros(len(v), bool)
        first = None
        for it in range(iters):
            _, sd, n, _ = skin.closest(v)
            viol = (sd > -dmin) & ~ex
            if first is None:
                first = {"outside": int(((sd > 0) & ~ex).sum()), "closer_than_min": int(viol.sum())}
            if not viol.any():
                break
            corr = np.zeros_like(v)
            corr[viol] = -(sd[viol] + dmin + 0.25)[:, None] * n[viol]
            moved |= viol
            if it < iters - 1:
                # spread the correction to the neighbourhood (5 Jacobi smoothing steps keeping
                # the violating vertices' own correction as a floor)
                c = corr.copy()
                for _ in range(5):
                    c = (adj @ c) / deg[:, None]
                    c[viol] = corr[viol]
                corr = c
                moved |= np.linalg.norm(corr, axis=1) > 1e-3
            v = v + corr
        bone.vertices = v
        _, sd, _, _ = skin.closest(v)
        stats[bi] = {
            "before": first,
            "vertices_moved": int(moved.sum()),
            "after_violations": int(((sd > -dmin + 1e-6) & ~ex).sum()),
            "iterations": it + 1,
        }
    return stats


# --------------------------------------------------------------------------------------------
# Measurements
# --------------------------------------------------------------------------------------------

def ray_thickness(skin_verts: np.ndarray, skin_normals: np.ndarray, bones: trimesh.Trimesh):
    """Product-style constraint: ray from each skin vertex along -normal; keep a hit only where
    the bone faces the same way as the skin. Returns thickness (nan where no valid hit)."""
    origins = skin_verts + skin_normals * 1e-3
    dirs = -skin_normals
    loc, ray_idx, tri_idx = bones.ray.intersects_location(origins, dirs, multiple_hits=False)
    thick = np.full(len(skin_verts), np.nan)
    if len(ray_idx):
        facing = np.einsum("ij,ij->i", bones.face_normals[tri_idx], skin_normals[ray_idx]) > 0
        d = np.linalg.norm(loc - origins[ray_idx], axis=1)
        thick[ray_idx[facing]] = d[facing]
    return thick


def region_masks(face_mm: np.ndarray, normals: np.ndarray, lm: np.ndarray) -> dict:
    """Skin vertex sets of typical soft-tissue-thickness landmarks, from the 68 ICT landmarks
    (ibug numbering, 0-based): 27 = top of the nose bridge, 8 = menton, 57 = lower lip,
    36/45 = outer eye corners, 19/24 = brow peaks."""
    P = face_mm[lm]
    tree = cKDTree(face_mm)
    front = normals[:, 2] > 0.3

    def ball(centre, radius, extra=None):
        m = np.zeros(len(face_mm), bool)
        m[tree.query_ball_point(centre, radius)] = True
        return m & (front if extra is None else extra)

    brow = (P[19] + P[24]) / 2
    eyes_mid = (P[36] + P[45]) / 2
    up = np.array([0.0, 1.0, 0.0])
    forehead_c = brow + 30.0 * up
    forehead_c = face_mm[tree.query(forehead_c)[1]]
    # soft nasion: the deepest point of the profile between brows and nose bridge
    mid = np.abs(face_mm[:, 0] - eyes_mid[0]) < 3.0
    cand = mid & (face_mm[:, 1] > P[27][1] - 5) & (face_mm[:, 1] < brow[1]) & front
    nasion_c = face_mm[cand][np.argmin(face_mm[cand][:, 2])] if cand.any() else P[27]
    pogonion_c = face_mm[tree.query(P[8] + (P[57] - P[8]) * 0.35 + np.array([0, 0, 5.0]))[1]]
    cheek = {}
    for side, k in (("right", 36), ("left", 45)):
        c = P[k] + np.array([0.0, -20.0, 0.0])
        cheek[side] = face_mm[tree.query(c)[1]]
    return {
        "forehead": ball(forehead_c, 12.0),
        "nasion": ball(nasion_c, 5.0, np.ones(len(face_mm), bool)),
        "chin (pogonion)": ball(pogonion_c, 7.0),
        "cheek over zygoma": ball(cheek["right"], 7.0) | ball(cheek["left"], 7.0),
        "whole face (valid rays)": np.ones(len(face_mm), bool),
    }


def describe(values: np.ndarray) -> dict:
    v = values[np.isfinite(values)]
    if len(v) == 0:
        return {"n": 0}
    return {"n": int(len(v)), "median_mm": round(float(np.median(v)), 2),
            "p10_mm": round(float(np.percentile(v, 10)), 2),
            "p90_mm": round(float(np.percentile(v, 90)), 2),
            "min_mm": round(float(v.min()), 2)}


TARGET_THICKNESS_MM = {"forehead": 5.5, "nasion": 6.5, "chin (pogonion)": 10.5,
                       "cheek over zygoma": 7.0}


def regional_thickness_prior(skull, jaw, exempt, face_mm, normals, regions, sigma=14.0,
                             tolerance=1.0, rounds=3) -> dict:
    """Move the bone under each landmark region towards a typical adult soft-tissue thickness
    (TARGET_THICKNESS_MM) with a smooth Gaussian bump (``sigma`` mm) along the region's mean skin
    normal; dental vertices stay put. A region whose median is off by more than ``tolerance`` is
    corrected fully, a bone already within tolerance is untouched."""
    log_rounds = []
    for _ in range(rounds):
        bones = trimesh.util.concatenate([skull, jaw])
        thick = ray_thickness(face_mm, normals, bones)
        moves = {}
        for name, target in TARGET_THICKNESS_MM.items():
            m = regions[name] & np.isfinite(thick)
            if m.sum() < 3:
                continue
            # regions made of two patches (both cheeks) are corrected per side
            sides = [m & (face_mm[:, 0] > 0), m & (face_mm[:, 0] <= 0)] if name.startswith("cheek") else [m]
            for part in sides:
                if part.sum() < 3:
                    continue
                med = float(np.median(thick[part]))
                err = med - target
                if abs(err) <= tolerance:
                    continue
                step = float(err)
                n = normals[part].mean(0)
                n /= np.linalg.norm(n)
                c = face_mm[part].mean(0) - n * med
                for bone, ex in zip((skull, jaw), exempt):
                    w = np.exp(-np.sum((bone.vertices - c) ** 2, axis=1) / (2 * sigma ** 2))
                    w[ex] = 0.0
                    bone.vertices = bone.vertices + (w * step)[:, None] * n
                moves[name] = moves.get(name, []) + [round(step, 2)]
        log_rounds.append(moves)
        if not moves:
            break
    log(f"  regional thickness prior moves (mm, outward +): {log_rounds}")
    return {"targets_mm": TARGET_THICKNESS_MM, "sigma_mm": sigma, "tolerance_mm": tolerance,
            "moves_mm_per_round": log_rounds}


# --------------------------------------------------------------------------------------------
# Output helpers
# --------------------------------------------------------------------------------------------

def write_ply(path: Path, verts: np.ndarray, tris: np.ndarray) -> None:
    mesh = trimesh.Trimesh(verts.astype(np.float32), tris, process=False)
    data = trimesh.exchange.ply.export_ply(mesh, encoding="binary", vertex_normal=False,
                                           include_attributes=False)
    path.write_bytes(data)


def preview(path: Path, face_mm, tris, skull: trimesh.Trimesh, jaw: trimesh.Trimesh,
            thickness: np.ndarray) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    def draw(ax, layers, axes, view_dir, title):
        polys, colors = [], []
        for verts, faces, rgba, shade in layers:
            tri = verts[faces]
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
            vis = n @ view_dir > 0
            depth = tri.mean(1) @ view_dir
            light = np.clip(0.35 + 0.65 * (n @ view_dir), 0, 1)
            for k in np.flatnonzero(vis):
                polys.append((depth[k], tri[k][:, axes]))
                col = np.array(rgba[k] if rgba.ndim == 2 else rgba, float)
                if shade:
                    col[:3] *= light[k]
                colors.append(col)
        order = np.argsort([p[0] for p in polys])
        pc = PolyCollection([polys[i][1] for i in order], facecolors=[colors[i] for i in order],
                            edgecolors="none")
        ax.add_collection(pc)
        allv = np.concatenate([layer[0][:, axes] for layer in layers])
        ax.set_xlim(allv[:, 0].min() - 5, allv[:, 0].max() + 5)
        ax.set_ylim(allv[:, 1].min() - 5, allv[:, 1].max() + 5)
        ax.set_aspect("equal")
        ax.set_title(title, fontsize=9)
        ax.tick_params(labelsize=7)

    fig, axs = plt.subplots(1, 4, figsize=(17, 5.2))
    skin_rgba = np.array([0.93, 0.78, 0.68, 0.28])
    bone_rgba = np.array([0.95, 0.93, 0.82, 1.0])
    jaw_rgba = np.array([0.62, 0.80, 0.62, 1.0])
    front = np.array([0.0, 0.0, 1.0])
    side = np.array([1.0, 0.0, 0.0])
    draw(axs[0], [(skull.vertices, skull.faces, bone_rgba, True),
                  (jaw.vertices, jaw.faces, jaw_rgba, True)], [0, 1], front, "bones, front (mm)")
    draw(axs[1], [(skull.vertices, skull.faces, bone_rgba, True),
                  (jaw.vertices, jaw.faces, jaw_rgba, True),
                  (face_mm, tris, skin_rgba, False)], [0, 1], front, "skin over bones, front")
    # side view from the actor's left (+x): horizontal axis = -z so the face looks right
    flip = np.array([1.0, 1.0, -1.0])
    draw(axs[2], [(skull.vertices * flip, skull.faces, bone_rgba, True),
                  (jaw.vertices * flip, jaw.faces, jaw_rgba, True),
                  (face_mm * flip, tris, skin_rgba, False)], [2, 1], side,
         "skin over bones, left side (horizontal = -z)")
    axs[2].invert_xaxis()
    cmap = plt.get_cmap("viridis")
    t = np.where(np.isfinite(thickness), thickness, np.nan)
    tt = t[tris]
    cnt = np.isfinite(tt).sum(1)
    tf = np.where(cnt > 0, np.nansum(tt, axis=1) / np.maximum(cnt, 1), np.nan)
    norm = np.clip(tf / 20.0, 0, 1)
    rgba = cmap(norm)
    rgba[~np.isfinite(tf)] = [0.8, 0.8, 0.8, 1.0]
    draw(axs[3], [(face_mm, tris, rgba, False)], [0, 1], front,
         "ray thickness skin->bone (0..20 mm, grey: no bone)")
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, 20))
    fig.colorbar(sm, ax=axs[3], fraction=0.046, pad=0.02)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# --------------------------------------------------------------------------------------------

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--assets", type=Path, default=DEFAULT_ASSETS)
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT)
    ap.add_argument("--min-thickness", type=float, default=MIN_THICKNESS_MM)
    args = ap.parse_args(argv)
    t0 = time.time()
    assets, out = args.assets.resolve(), args.out.resolve()

    # ---- actor and shapes ---------------------------------------------------------------
    log("loading ICT FaceKit light model")
    ict = load_ict(assets)
    names = [str(n) for n in ict["expression_names"]]
    missing = [n for n in TRAINING_EXPRESSIONS if n not in names]
    if missing:
        sys.exit(f"error: expressions not in the ICT model: {missing}")
    held_out = [n for n in names if n not in TRAINING_EXPRESSIONS]
    assert len(TRAINING_EXPRESSIONS) == 19 and len(held_out) == 34

    generic_cm = ict["neutral"].astype(np.float64)
    actor_cm = actor_neutral_cm(ict)
    polys = ict["faces"]
    assert polys[:FACE_NF].max() < FACE_NV, "face polygons must only use face vertices"
    face_tris = triangulate(polys[:FACE_NF])
    head_tris = triangulate(polys[:HEAD_NF])
    assert head_tris.max() < HEAD_NV

    centre = head_centre(actor_cm[:HEAD_NV])
    frac = outward_fraction(actor_cm[:FACE_NV], face_tris, centre)
    if frac < 0.5:
        face_tris = face_tris[:, ::-1].copy()
        head_tris = head_tris[:, ::-1].copy()
        frac = 1 - frac
    log(f"  face: {FACE_NV} vertices, {len(face_tris)} triangles, "
        f"{frac * 100:.1f} % of area facing away from the head centre")

    if out.exists():
        shutil.rmtree(out)
    (out / "shapes").mkdir(parents=True)
    (out / "bones").mkdir()
    (out / "LICENSES").mkdir()

    actor_mm = actor_cm * CM_TO_MM
    face_mm = actor_mm[:FACE_NV]
    write_ply(out / "shapes" / "neutral.ply", face_mm, face_tris)
    expr_stats = {}
    for name in TRAINING_EXPRESSIONS:
        k = names.index(name)
        shape = (actor_cm[:FACE_NV] + ict["expression_deltas"][k, :FACE_NV]) * CM_TO_MM
        write_ply(out / "shapes" / f"{name}.ply", shape, face_tris)
        disp = np.linalg.norm(shape - face_mm, axis=1)
        expr_stats[name] = {"max_displacement_mm": round(float(disp.max()), 2),
                            "vertices_moved_over_1mm": int((disp > 1.0).sum())}
    log(f"  wrote neutral + {len(TRAINING_EXPRESSIONS)} expressions")

    # ---- bones ----------------------------------------------------------------------------
    log("fitting skull and jaw")
    dj = assets / "skull_jaw" / "artisynth_dynjaw" / "derived"
    src_files = {n: dj / f"{n}_in_ict_neutral_frame_cm.obj" for n in ("maxilla", "cranium", "jaw")}
    src_files["odedstein"] = assets / "skull_jaw" / "odedstein_skull_cc-by" / "skull_low_resolution.obj"
    raw = {n: clean_mesh(load_obj_cm(src_files[n])) for n in ("maxilla", "cranium", "jaw")}
    centre_g = head_centre(generic_cm[:HEAD_NV])
    maxilla_g, flips_s = fix_winding_per_component(raw["maxilla"], centre_g)
    jaw_g, flips_j = fix_winding_per_component(raw["jaw"], centre_g)
    log(f"  winding: flipped {flips_s} maxilla / {flips_j} jaw components")
    upper_g, oded_info = load_odedstein_upper_skull(src_files["odedstein"], maxilla_g, jaw_g,
                                                    raw["cranium"])
    log(f"  odedstein upper skull: {oded_info}")
    skull_g = trimesh.util.concatenate([maxilla_g, upper_g])

    skull_v = identity_transfer(skull_g.vertices, generic_cm, actor_cm) * CM_TO_MM
    jaw_v = identity_transfer(jaw_g.vertices, generic_cm, actor_cm) * CM_TO_MM
    skull = trimesh.Trimesh(skull_v, skull_g.faces, process=False)
    jaw = trimesh.Trimesh(jaw_v, jaw_g.faces, process=False)

    skin = Skin(actor_mm[:HEAD_NV], head_tris)
    face_mesh = trimesh.Trimesh(face_mm, face_tris, process=False)
    fn = np.asarray(face_mesh.vertex_normals)
    lm = ict["landmarks_multipie68"].astype(int)
    assert lm.max() < FACE_NV
    regions = region_masks(face_mm, fn, lm)
    # teeth are exempt from the skin test and the regional prior: behind the lips their closest
    # skin is the inner lip, which faces the mouth cavity, and the ICT teeth anchor them.
    # A bone vertex is "dental" when it is within 4 mm of ICT teeth.
    teeth_tree = cKDTree(actor_mm[UPPER_TEETH[0]:LOWER_TEETH[1] + 1])
    exempt = [teeth_tree.query(b.vertices)[0] < 4.0 for b in (skull, jaw)]
    pre = {}
    for nm, b in (("skull", skull), ("jaw", jaw)):
        _, sd, _, _ = skin.closest(b.vertices)
        pre[nm] = {"outside_skin": int((sd > 0).sum()),
                   "closer_than_min": int((sd > -args.min_thickness).sum()),
                   "vertices": len(sd)}
    log(f"  after identity transfer: {pre}")
    before_prior = {name: describe(ray_thickness(face_mm, fn, trimesh.util.concatenate([skull, jaw]))[m])
                    for name, m in regions.items()}
    log(f"  ray thickness before the regional prior: { {k: v.get('median_mm') for k, v in before_prior.items()} }")
    # push first (bone poking through the skin gives no valid ray), then the regional prior,
    # then push again so the minimum holds everywhere after the prior's smooth moves
    push0 = enforce_min_thickness([skull, jaw], skin, exempt, args.min_thickness)
    log(f"  min-thickness push: {push0}")
    prior = regional_thickness_prior(skull, jaw, exempt, face_mm, fn, regions)
    push = enforce_min_thickness([skull, jaw], skin, exempt, args.min_thickness)
    log(f"  min-thickness push after the prior: {push}")
    write_ply(out / "bones" / "skull.ply", skull.vertices, skull.faces)
    write_ply(out / "bones" / "jaw.ply", jaw.vertices, jaw.faces)

    # ---- report ---------------------------------------------------------------------------
    bones = trimesh.util.concatenate([skull, jaw])
    thick = ray_thickness(face_mm, fn, bones)
    thickness_report = {name: describe(thick[m]) for name, m in regions.items()}
    thickness_report["whole face (valid rays)"]["fraction_with_bone"] = round(
        float(np.isfinite(thick).mean()), 3)
    for name, r in thickness_report.items():
        log(f"  thickness {name:26s} {r}")

    # nearest skin distance of all bone vertices (positive = behind the skin)
    _, sd_all, _, _ = skin.closest(bones.vertices)
    depth = -sd_all[~np.concatenate(exempt)]   # teeth excluded: their nearest skin is the inner lip

    def teeth_dist(rng, mesh):
        pts = actor_mm[rng[0]:rng[1] + 1]
        _, d, _ = trimesh.proximity.closest_point(mesh, pts)
        return {"median_mm": round(float(np.median(d)), 2),
                "p90_mm": round(float(np.percentile(d, 90)), 2),
                "max_mm": round(float(d.max()), 2)}

    teeth = {"ict_upper_teeth_to_skull": teeth_dist(UPPER_TEETH, skull),
             "ict_lower_teeth_to_jaw": teeth_dist(LOWER_TEETH, jaw),
             "ict_lower_teeth_to_skull": teeth_dist(LOWER_TEETH, skull)}
    for k, r in teeth.items():
        log(f"  {k:28s} {r}")

    preview(out / "preview.png", face_mm, face_tris, skull, jaw, thick)

    # ---- metadata, licences ---------------------------------------------------------------
    ict_dir = assets / "ict_facekit"
    art_dir = assets / "skull_jaw" / "artisynth_dynjaw"
    shutil.copyfile(ict_dir / "LICENSE", out / "LICENSES" / "ICT-FaceKit-MIT.txt")
    shutil.copyfile(art_dir / "LICENSE", out / "LICENSES" / "ArtiSynth-Models.txt")
    (out / "LICENSES" / "Skull-CC-BY-3.0.txt").write_text(
        "bones/skull.ply contains a modified part (vault, forehead, orbits, nasal bones, zygomas,\n"
        "skull base; cut, scaled, placed and deformed to this actor) of:\n\n"
        "  \"Skull\" by YahooJAPAN (https://www.thingiverse.com/thing:182365),\n"
        "  remeshed version from https://github.com/odedstein/meshes (objects/skull,\n"
        "  commit 835213277571d625722d25880c9c3010c6f45a5a), licensed under the\n"
        "  Creative Commons Attribution 3.0 Unported licence (CC BY 3.0),\n"
        "  https://creativecommons.org/licenses/by/3.0/\n\n"
        "Changes: low-resolution mesh cut to the upper skull, similarity-placed on the ArtiSynth\n"
        "dynjaw bones, deformed by the ICT FaceKit identity field and pushed behind the skin.\n")

    jaw_json = ict_dir / "derived" / "jaw_rigid_from_lower_teeth.json"
    jaw_truth = json.loads(jaw_json.read_text())["shapes"]
    jaw_truth_mm = {k: {"R": v["R"], "t_mm": [round(x * CM_TO_MM, 5) for x in v["t_cm"]],
                        "rotation_deg": v["rotation_deg"]}
                    for k, v in jaw_truth.items()}

    info = {
        "format": "aim-capture sample actor",
        "format_version": 1,
        "name": "ict_sample_identity",
        "units": "mm",
        "frame": "ICT FaceKit: x = actor's left, y up, z towards the face front (mm)",
        "neutral": "neutral",
        "training_shapes": TRAINING_EXPRESSIONS,
        "held_out_expressions": held_out,
        "shapes_dir": "shapes",
        "shape_files": {n: f"shapes/{n}.ply" for n in ["neutral"] + TRAINING_EXPRESSIONS},
        "bones": {"skull": "bones/skull.ply", "jaw": "bones/jaw.ply"},
        "topology": {"vertices": FACE_NV, "triangles": int(len(face_tris)),
                     "source": "ICT FaceKit face region: vertices 0..9408, polygons 0..9229; "
                               "quads (a,b,c,d) split into (a,b,c),(a,c,d); "
                               "winding outward (normals away from the head centre)",
                     "outward_area_fraction": round(frac, 4)},
        "landmarks_multipie68": lm.tolist(),
        "landmarks_note": "ibug/Multi-PIE 68-point order, 0-based; vertex ids of the face region "
                          "(identical to ICT vertex ids)",
        "jaw_ground_truth_from_lower_teeth": {
            "note": "rigid transform of the ICT lower teeth (X_expr = R X_neutral + t, mm, in "
                    "this actor's frame the rotation is the same; the translation is the generic "
                    "model's and is exact only up to the identity offset of the jaw pivot)",
            "shapes": jaw_truth_mm},
        "expression_stats": expr_stats,
        "provenance": {
            "script": "scripts/make_sample_actor.py",
            "command": "python scripts/make_sample_actor.py --assets ../shared/assets "
                       "--out capture/data/sample_actor",
            "identity": f"ICT FaceKit sample_identity_coeffs[:{N_IDENTITY}] (from "
                        "sample_data/sample_identity_coeffs.json of the ICT repository) on the "
                        "100 identity modes of the Light model",
            "expressions": "actor neutral + one ICT expression delta at weight 1.0",
            "unit_conversion": "ICT and placed bones are in cm; multiplied by 10 to mm; shapes "
                               "stored as float32",
            "skull_source": "ArtiSynth dynjaw maxilla.obj (maxilla, zygomatic arches, nasal "
                            "aperture, upper teeth) as placed in the ICT generic neutral frame by "
                            "derived/artisynth_dynjaw_to_ict_neutral_4x4.txt, plus the odedstein "
                            "low-resolution skull (similarity-ICP placed on the ArtiSynth bones) "
                            "cut to vault, forehead, orbits, nasal bones, zygomas and skull base. "
                            "The ArtiSynth cranium cap is used only as an ICP reference.",
            "jaw_source": "ArtiSynth dynjaw jaw.obj (mandible with lower teeth), same placement",
            "skull_choice": "Hybrid. The ArtiSynth maxilla comes from the same CT subject as "
                            "the mandible and is aligned to the ICT teeth (upper-teeth check), so "
                            "it is kept; but the ArtiSynth cranium is a coarse cap without "
                            "forehead base, orbit rims or nasion, leaving the upper face without "
                            "bone. The odedstein skull is complete there and, once placed, lies "
                            "under the ICT forehead and scalp; its fused mandible and its copy of "
                            "the maxilla are cut away.",
            "bone_fit": "identity deformation of the ICT model (thin-plate spline of the "
                        "generic->actor displacement of ICT face, head, socket, gum, teeth and "
                        "eyeball vertices) applied to the bones; a regional prior moves the bone "
                        "under forehead, nasion, chin and cheeks towards typical adult "
                        "soft-tissue thicknesses (smooth Gaussian bumps, teeth fixed); then every "
                        "bone vertex is pushed "
                        f"at least {args.min_thickness} mm behind the skin (face + head & neck) "
                        "along the skin normal, corrections smoothed over the bone; teeth within "
                        "4 mm of ICT teeth exempt. Winding made outward per connected component.",
            "sources": [
                {"file": str(p.relative_to(assets)), "sha256": sha256(p),
                 "licence": lic}
                for p, lic in [
                    (ict["_path"], "MIT (ICT FaceKit, (c) 2020 USC Institute for Creative "
                                   "Technologies) - LICENSES/ICT-FaceKit-MIT.txt"),
                    (jaw_json, "MIT (derived from ICT FaceKit)"),
                    (src_files["maxilla"], "ArtiSynth Models licence (c) 2014 ArtiSynth, "
                                           "A. G. Hannam - LICENSES/ArtiSynth-Models.txt"),
                    (src_files["cranium"], "ArtiSynth Models licence - LICENSES/ArtiSynth-Models.txt"),
                    (src_files["jaw"], "ArtiSynth Models licence - LICENSES/ArtiSynth-Models.txt"),
                    (src_files["odedstein"], "CC BY 3.0: Skull by YahooJAPAN (thingiverse.com/"
                                             "thing:182365), remeshed version from github.com/"
                                             "odedstein/meshes - LICENSES/Skull-CC-BY-3.0.txt"),
                ]],
            "citations": [
                "Li et al., Learning Formation of Physically-Based Face Attributes, CVPR 2020 "
                "(ICT FaceKit)",
                "Hannam et al., A dynamic model of jaw and hyoid biomechanics during chewing, "
                "J. Biomech. 2008 (ArtiSynth dynjaw model)",
            ],
        },
        "fit_report": {
            "min_thickness_mm": args.min_thickness,
            "after_identity_transfer": pre,
            "ray_thickness_before_regional_prior": before_prior,
            "regional_thickness_prior": prior,
            "min_thickness_push": {"skull": push0[0], "jaw": push0[1]},
            "min_thickness_push_after_prior": {"skull": push[0], "jaw": push[1]},
            "odedstein_upper_skull": oded_info,
            "winding_components_flipped": {"skull": flips_s, "jaw": flips_j},
            "bone_vertices": {"skull": len(skull.vertices), "jaw": len(jaw.vertices)},
            "bone_depth_behind_skin_nearest_mm": describe(depth),
            "bone_depth_note": "distance from each non-dental bone vertex to the nearest skin "
                               "(face + head & neck), positive behind the skin",
            "ray_thickness_by_region": thickness_report,
            "ray_thickness_method": "ray from each face vertex along the inverse vertex normal "
                                    "to skull+jaw, hit kept only where the bone faces the same "
                                    "way as the skin (as the product's sparse constraints)",
            "typical_adult_medians_mm": {"forehead": "5-6", "nasion": "6", "chin": "10-11",
                                         "cheek over zygoma": "7"},
            "teeth_to_bone": teeth,
        },
    }
    (out / "sample.json").write_text(json.dumps(info, indent=1))

    (out / "README.md").write_text(f"""# Sample actor (generated)

One synthetic actor for the demo, tests and benchmarks of aim-capture: the ICT FaceKit Light
model with its sample identity, a neutral and 19 single-expression shapes (face region, 9,409
vertices, same triangles, binary PLY, mm), plus a skull (ArtiSynth dynjaw maxilla + upper part
of the odedstein CC-BY skull) and a jaw (ArtiSynth dynjaw mandible) fitted to the neutral. `sample.json` lists the shapes, the 34 held-out expressions, the 68
landmark vertex ids, provenance and the bone fit report; `preview.png` shows skin and bones.

Do not edit by hand. Regenerate from the repository root with

    python scripts/make_sample_actor.py --assets ../shared/assets --out capture/data/sample_actor

Licences (kept beside the data, see `LICENSES/`):
- ICT FaceKit (shapes, landmarks): MIT, (c) 2020 USC Institute for Creative Technologies.
  Cite Li et al., "Learning Formation of Physically-Based Face Attributes", CVPR 2020.
- ArtiSynth dynjaw maxilla and jaw geometry: ArtiSynth Models licence (BSD-style), (c) 2014
  ArtiSynth, A. G. Hannam. Academic publications must cite the original work (Hannam et al.,
  dynamic jaw model, 2008). The bones here are modified (deformed to this actor).
- Upper skull (vault, forehead, orbits, nasal bones, zygomas): "Skull" by YahooJAPAN
  (thingiverse.com/thing:182365), remeshed version from github.com/odedstein/meshes, CC BY 3.0;
  modified (cut, placed, deformed). See `LICENSES/Skull-CC-BY-3.0.txt`.
""")
    size = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    log(f"done in {time.time() - t0:.0f} s; {out} holds {size / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
