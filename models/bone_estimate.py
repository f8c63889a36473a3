"""A stand-in bone surface when the user gives no skull or jaw: an inward offset of the neutral skin.

Pure geometry: a ``trimesh.Trimesh`` and a :class:`~models.face_frame.FaceFrame` in, a mesh out.
Lengths are millimetres. The caller must report the result as an *estimate*: it encodes average
soft-tissue depths, not this actor's anatomy.

Typical facial soft-tissue thickness (adults, midline and paired landmarks; e.g. De Greef et al.
2006, Forensic Sci. Int. 159S, n = 967 Caucasian adults; Stephan & Simpson 2008 meta-analysis):

=====================  =========
landmark               depth, mm
=====================  =========
mid-forehead, glabella ~4.5-6
nasion                 ~6.5
rhinion (nose bridge)  ~2-3
mid-philtrum           ~11-12
upper/lower lip        ~11-13
chin (pogonion)        ~10-11
zygomatic/malar        ~6-12
mid-cheek (buccal)     ~15-20
mandibular angle/body  ~10-18
=====================  =========

Default profile (:func:`typical_tissue_thickness`): a piecewise-linear function of the height
``h`` along ``frame.up`` measured from the nose tip (the nose tip is the most forward vertex near
the symmetry plane, so the profile does not depend on how much neck or scalp the scan has):

    h >= +35 mm (brow and forehead)      5.5 mm
    h =  +10 mm (nose bridge, eyes, malar) 8 mm
    h = -10 mm (upper lip, mid-cheek)    12 mm
    h = -45 mm (lower lip, chin)         11 mm
    h <= -70 mm (under the chin, neck)   10 mm

It ignores the lateral variation (cheeks are thicker than the midline at the same height); a
callable gives full control.

Offset and smoothing: ``bone_i = x_i - d_i * m_i``, where ``m_i`` are the vertex normals diffused
over the mesh (a few umbrella-operator passes, chosen so that the diffusion radius is about the
largest thickness). The offset of a surface along its own normals self-intersects where the
thickness exceeds the local radius of curvature (the nose tip, the lips); smoothing the offset
directions over a neighbourhood of that size, then thickness, then a few Taubin passes on the result
(volume-preserving smoothing, lambda 0.5 / mu -0.53) removes most fold-overs without shrinking the
surface. The result has the skin's faces, so bone vertex i belongs to skin vertex i.
"""

from __future__ import annotations

from typing import Callable, Union

import numpy as np
import trimesh
from scipy.sparse import coo_matrix, diags

from capture.io.errors import CaptureError

__all__ = ["estimate_bone_surface", "typical_tissue_thickness", "TISSUE_PROFILE_MM"]

# (height above the nose tip along `up`, soft-tissue thickness), both mm; see the module docstring
TISSUE_PROFILE_MM = (
    (-70.0, 10.0),
    (-45.0, 11.0),
    (-10.0, 12.0),
    (10.0, 8.0),
    (35.0, 5.5),
)

Thickness = Union[float, Callable[[np.ndarray, object], np.ndarray]]


def typical_tissue_thickness(vertices: np.ndarray, frame) -> np.ndarray:
    """(V,3) mm -> (V,) mm: the default thickness profile along ``frame.up`` (module docstring)."""
    from models.face_frame import midline_landmarks

    v = np.asarray(vertices, dtype=np.float64)
    tip = midline_landmarks(v, frame).nose_tip
    h = (v - tip) @ frame.up
    xs, ys = zip(*TISSUE_PROFILE_MM)
    return np.interp(h, xs, ys)


def _umbrella(nv: int, edges: np.ndarray):
    """Row-normalised adjacency (uniform umbrella operator) as a sparse matrix."""
    e = np.concatenate([edges, edges[:, ::-1]])
    a = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(nv, nv)).tocsr()
    deg = np.asarray(a.sum(axis=1)).ravel()
    inv = np.where(deg > 0, 1.0 / np.maximum(deg, 1), 0.0)
    return diags(inv) @ a, deg > 0


def estimate_bone_surface(
    skin: trimesh.Trimesh,
    frame=None,
    thickness_mm: Thickness = typical_tissue_thickness,
    *,
    taubin_iterations: int = 10,
    max_normal_iterations: int = 200,
) -> trimesh.Trimesh:
    """An estimated bone surface: the neutral skin offset inward by a soft-tissue thickness.

    Args:
        skin: neutral skin mesh, outward normals, mm.
        frame: the face frame (needed by the default thickness profile; may be None for a number).
        thickness_mm: a number (uniform), a (V,) array, or a callable ``f(vertices, frame) -> (V,)``.
        taubin_iterations: Taubin smoothing passes on the offset surface.
        max_normal_iterations: cap on the normal-diffusion passes.

    Returns:
        trimesh.Trimesh with the skin's faces (vertex i under skin vertex i).

    Example:
        >>> bone = estimate_bone_surface(neutral, frame)            # default profile
        >>> bone = estimate_bone_surface(neutral, None, 8.0)        # uniform 8 mm
    """
    if not isinstance(skin, trimesh.Trimesh) or len(skin.faces) == 0:
        raise CaptureError("the skin must be a non-empty triangle mesh")
    v = np.asarray(skin.vertices, dtype=np.float64)
    if not np.all(np.isfinite(v)):
        raise CaptureError("the skin mesh has NaN or infinite vertex coordinates: fix or re-export it")
    nv = len(v)
    if callable(thickness_mm):
        if frame is None and thickness_mm is typical_tissue_thickness:
            raise CaptureError("the default thickness profile needs the face frame; give a frame or a number")
        d = np.asarray(thickness_mm(v, frame), dtype=np.float64)
    else:
        d = np.asarray(thickness_mm, dtype=np.float64)
    d = np.broadcast_to(d, (nv,)) if d.ndim == 0 else d
    if d.shape != (nv,) or not np.all(np.isfinite(d)) or np.any(d < 0):
        raise CaptureError(f"the soft-tissue thickness must be finite, >= 0 mm, one per vertex ({nv}); got shape {d.shape}")

    w, has_nb = _umbrella(nv, np.asarray(skin.edges_unique))
    normals = np.asarray(skin.vertex_normals, dtype=np.float64).copy()
    edge = float(skin.edges_unique_length.mean())
    # diffusion radius of k umbrella passes is about sqrt(k) edges; aim for the largest thickness
    k = int(min(max_normal_iterations, np.ceil((float(d.max()) / max(edge, 1e-9)) ** 2)))
    for _ in range(k):
        m = w @ normals
        m[~has_nb] = normals[~has_nb]
        normals = m / np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-12)
    bone = v - d[:, None] * normals
    out = trimesh.Trimesh(bone, np.asarray(skin.faces).copy(), process=False)
    if taubin_iterations > 0:
        trimesh.smoothing.filter_taubin(out, lamb=0.5, nu=0.53, iterations=taubin_iterations)
    return out
