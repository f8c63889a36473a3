"""Mirrored expression shapes: the other side of one-sided training shapes, across the face's symmetry plane.

Actors are learned from ~20 scans, and a capture session often records only one side of an asymmetric
expression (``mouthStretch_L`` but not ``mouthStretch_R``). A face is close to bilaterally symmetric, so
the other side is the scan's displacement reflected across the symmetry plane. Without it the fit has no
way to express that side except by its per-point freedom, which 2D landmarks cannot guide in depth
(BENCHMARKS.md, "2D fit out of the actor's span").

A mirrored shape moves the actor's OWN neutral (its asymmetries stay) by the reflected displacement of
the source shape, read at each vertex's mirror point:

    S'(v) = N(v) + M (S - N)(m(v)),    m(v) = the point of the neutral surface closest to P(N(v)),

with ``P(x) = x - 2 (n . x - d) n`` the reflection across the plane ``n . x = d`` and ``M = I - 2 n n^T``
its linear part (``(S - N)(m)``: the displacement interpolated barycentrically on m's triangle).

Only shapes whose mirror the training set does not already hold are added: a shape is *one-sided* when
the part of its mirrored displacement that the other shapes' displacements cannot express by least
squares is more than ``threshold`` of its norm (on ICT FaceKit's 19 training shapes: the L/R pairs and
symmetric shapes 0.01-0.14, one-sided shapes 0.37-0.60). A shape whose other side was scanned under the
other side's name (:func:`other_side`) never gets a mirror: a real face's two sides differ, and the scan
of the other side is the better shape.

The closest points come from the caller (:func:`mirror_points` takes a closest-point function, e.g.
trimesh's); their barycentric coordinates are trimesh's.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

#: Default relative residual above which a mirrored shape is new (see the module docstring).
ONE_SIDED_THRESHOLD = 0.3

_SIDE_SWAPS = (("_L", "_R"), ("_l", "_r"), (".L", ".R"), ("Left", "Right"), ("left", "right"))


@dataclass(frozen=True)
class MirrorMap:
    """Each vertex's mirror point on the neutral surface: triangle ``faces[face_index[v]]`` at ``barycentric[v]``.

    ``distance[v]`` (mm) is how far the reflected vertex lies from the surface: the face's asymmetry there.
    """

    face_index: np.ndarray     # (V,) int
    barycentric: np.ndarray    # (V, 3)
    distance: np.ndarray       # (V,) mm


def reflection(normal, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """``(M (3, 3), o (3,))`` with ``P(x) = M x + o`` the reflection across ``n . x = offset`` (n made unit)."""
    n = np.asarray(normal, np.float64).reshape(3)
    norm = np.linalg.norm(n)
    if not np.isfinite(norm) or norm < 1e-12:
        raise ValueError(f"the symmetry plane needs a non-zero normal, got {n}")
    n = n / norm
    return np.eye(3) - 2.0 * np.outer(n, n), 2.0 * (float(offset) / norm) * n


def mirror_points(vertices: np.ndarray, faces: np.ndarray, normal, offset: float,
                  closest: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]) -> MirrorMap:
    """The :class:`MirrorMap` of ``vertices (V, 3)`` on their own surface ``faces (F, 3)``.

    ``closest(points (V, 3)) -> (closest points (V, 3), triangle index (V,))`` on that surface.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"vertices (V, 3) and faces (F, 3) expected, got {v.shape}, {f.shape}")
    M, o = reflection(normal, offset)
    reflected = v @ M.T + o
    pts, tri = closest(reflected)
    pts, tri = np.asarray(pts, np.float64), np.asarray(tri, np.int64)
    bary = trimesh.triangles.points_to_barycentric(v[f[tri]], pts)
    return MirrorMap(tri, bary, np.linalg.norm(pts - reflected, axis=1))


def mirror_displacements(displacements: np.ndarray, faces: np.ndarray, mirror: MirrorMap, normal) -> np.ndarray:
    """``(K, V, 3)``: displacements ``(K, V, 3)`` of the neutral, reflected: ``M d(m(v))`` at every vertex v."""
    d = np.asarray(displacements, np.float64)
    M, _ = reflection(normal, 0.0)
    corners = np.asarray(faces, np.int64)[mirror.face_index]                  # (V, 3)
    at_mirror = np.einsum("vc,kvcx->kvx", mirror.barycentric, d[:, corners])   # (K, V, 3)
    return at_mirror @ M.T


def one_sided(displacements: np.ndarray, mirrored: np.ndarray, threshold: float = ONE_SIDED_THRESHOLD) -> np.ndarray:
    """``(K,)`` relative residual of each mirrored displacement against the span of all ``displacements``.

    Both ``(K, V, 3)``. The residual of shape k is ``|r_k| / |mirrored_k|`` with ``r_k`` what least squares
    over the K original displacements leaves of ``mirrored_k``; shapes above ``threshold`` are one-sided.
    """
    A = np.asarray(displacements, np.float64).reshape(len(displacements), -1).T      # (3V, K)
    B = np.asarray(mirrored, np.float64).reshape(len(mirrored), -1).T                # (3V, K)
    coef, *_ = np.linalg.lstsq(A, B, rcond=None)
    norm = np.linalg.norm(B, axis=0)
    return np.linalg.norm(B - A @ coef, axis=0) / np.where(norm > 0, norm, 1.0)


def other_side(name: str) -> str | None:
    """The other side's name of ``name`` (``mouthStretch_L`` -> ``mouthStretch_R``, ``eyeLeft`` -> ``eyeRight``,
    ``lip_l_corner`` -> ``lip_r_corner``), or None when the name has no side."""
    for a, b in _SIDE_SWAPS:
        for x, y in ((a, b), (b, a)):
            if name.endswith(x):
                return name[: -len(x)] + y
            if re.search(re.escape(x) + r"(?=[_.\d]|$)", name):
                return re.sub(re.escape(x) + r"(?=[_.\d]|$)", y, name, count=1)
    return None


def mirrored_name(name: str, taken: set[str]) -> str:
    """:func:`other_side` of ``name``, or ``name + "_mirrored"`` when it has no side or that name is ``taken``;
    made unique against ``taken``."""
    out = other_side(name)
    if out is None or out in taken:
        out = f"{name}_mirrored"
    base, i = out, 2
    while out in taken:
        out, i = f"{base}{i}", i + 1
    return out
