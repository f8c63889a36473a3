"""Feature lines of a face template for the overlay: the mesh's border, its openings (lids, lips), brows.

All lines are vertex-index paths on the actor's template, so they follow the fitted mesh frame by frame:

* **Boundary loops** (pure topology): edges used by one triangle, chained into closed loops. The
  longest loop is the template's outer *border* (drawn like the silhouette); the others are its
  *openings*: on a face mask the eye openings (the lid margins) and the mouth opening (the inner lip line).
* **Brows** (from the actor's named expression shapes, where it has them): the vertices that the
  ``brow*`` shapes move most (more than half the largest brow displacement), split into the actor's
  left and right half at the template's median x, and on each side one point per slice along x (of
  ``bins``): the displacement-weighted mean of the slice's most-moved vertices, kept as fixed vertex
  weights so the line follows the mesh: a smooth line along the brow. An actor without brow shapes
  has no brow lines.

Template frame (the actor's): x the actor's left, y up, z out of the face.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class FaceFeatures:
    """``border`` and ``openings``: closed loops of vertex indices; ``brows``: :class:`WeightedLine` s."""

    border: list[np.ndarray] = field(default_factory=list)
    openings: list[np.ndarray] = field(default_factory=list)
    brows: list = field(default_factory=list)


def boundary_loops(faces: np.ndarray) -> list[np.ndarray]:
    """Closed loops of boundary edges (edges of exactly one triangle), longest first.

    A vertex where several loops touch is followed along the first free edge; every boundary edge is
    used once."""
    f = np.asarray(faces, np.int64)
    directed = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1).reshape(-1, 2)
    und = np.sort(directed, 1)
    _, inv, counts = np.unique(und, axis=0, return_inverse=True, return_counts=True)
    boundary = directed[counts[inv.reshape(-1)] == 1]   # directed as the single face winds them
    nxt: dict[int, list[int]] = {}
    for a, b in boundary.tolist():
        nxt.setdefault(a, []).append(b)
    loops = []
    while nxt:
        start = next(iter(nxt))
        loop = [start]
        cur = start
        while True:
            outs = nxt.get(cur)
            if not outs:
                break
            b = outs.pop()
            if not outs:
                del nxt[cur]
            if b == start:
                break
            loop.append(b)
            cur = b
        if len(loop) >= 3:
            loops.append(np.asarray(loop, np.int64))
    loops.sort(key=len, reverse=True)
    return loops


def brow_lines(vertices: np.ndarray, expressions: np.ndarray, names, bins: int = 10, threshold: float = 0.5,
               per_point: int = 8) -> list["WeightedLine"]:
    """The actor's left and right brow lines from its ``brow*`` shapes (see the module docstring).

    Each point of a line is a fixed convex combination of up to ``per_point`` vertices of one slice
    (weighted by how far the brow shapes move them), so the line is smooth and follows the mesh.

    Args: vertices ``(V, 3)`` template; expressions ``(E, V, 3)`` offsets; names ``E`` shape names.
    """
    v = np.asarray(vertices, np.float64)
    idx = [i for i, n in enumerate(names) if str(n).lower().startswith("brow")]
    if not idx:
        return []
    m = np.linalg.norm(np.asarray(expressions, np.float64)[idx], axis=2).max(0)      # (V,)
    if not m.max() > 0:
        return []
    region = m > threshold * m.max()
    mid = np.median(v[:, 0])
    lines = []
    for side in (v[:, 0] < mid, v[:, 0] >= mid):
        sel = np.flatnonzero(region & side)
        if len(sel) < bins:
            continue
        x = v[sel, 0]
        edges = np.linspace(x.min(), x.max(), bins + 1)
        ids, wts = [], []
        for lo, hi in zip(edges[:-1], edges[1:]):
            s = sel[(x >= lo) & (x <= hi)]
            if len(s) == 0:
                continue
            s = s[np.argsort(-m[s], kind="stable")][:per_point]
            row_i = np.zeros(per_point, np.int64)
            row_w = np.zeros(per_point)
            row_i[:len(s)], row_w[:len(s)] = s, m[s] / m[s].sum()
            ids.append(row_i)
            wts.append(row_w)
        if len(ids) >= 2:
            lines.append(WeightedLine(np.stack(ids), np.stack(wts)))
    return lines


@dataclass(frozen=True)
class WeightedLine:
    """An open line whose points are convex combinations of vertices: ``point_p = sum_k w[p, k] v[i[p, k]]``."""

    indices: np.ndarray   # (P, K) vertex indices
    weights: np.ndarray   # (P, K) non-negative, rows sum to 1

    def points(self, vertices: np.ndarray, smooth: int = 2) -> np.ndarray:
        """``(P, 3)`` the line's points on a mesh ``vertices (V, 3)``, smoothed ``smooth`` times with
        weights (1/4, 1/2, 1/4) along the line (end points kept)."""
        p = np.einsum("pk,pkc->pc", self.weights, np.asarray(vertices, np.float64)[self.indices])
        for _ in range(smooth if len(p) > 2 else 0):
            p[1:-1] = 0.25 * p[:-2] + 0.5 * p[1:-1] + 0.25 * p[2:]
        return p


def face_features(faces: np.ndarray, vertices: np.ndarray | None = None, expressions: np.ndarray | None = None,
                  names=None) -> FaceFeatures:
    """The template's feature lines: boundary loops from ``faces``; brows when the shapes are given."""
    loops = boundary_loops(faces)
    brows = [] if vertices is None or expressions is None or names is None else brow_lines(vertices, expressions,
                                                                                           names)
    return FaceFeatures(border=loops[:1], openings=loops[1:], brows=brows)
