"""Where the networks read a template point: the input chart that opens the mouth.

The five networks are functions of a template point's position. Where two parts of the surface touch
in the neutral - the lips of a closed mouth - points a fraction of a millimetre apart move
centimetres apart when the jaw opens (on the ICT sample 1,478 of the 5,376 pairs within 1.5 mm of each
other separate by more than 5x their distance in jawOpen; one pair 0.08 mm -> 5.3 mm). No smooth
function of position separates them, so the networks blur the two lips into each other: before the
chart, jawOpen's inner lip was the actor's worst vertex by 6.4 mm.

The chart moves every template point by a fraction of the displacement of the shape that tears the
surface most (the mouth-opening shape) before the networks read it, ``x = c + f (s_k(c) - s_0(c))``:
a smooth deformation of the face everywhere, which puts the lips a few millimetres apart. It changes
only where the networks are sampled; their outputs stay attached to ``c`` (the bone point is still
``c + offset``) and the losses, constraints and networks are the paper's.

A point ``c`` is charted through the triangle of its closest surface point: the barycentric blend of the
triangle's vertex offsets at ``c``'s projection onto its plane. On the surface that is the point's own
triangle (0 mm away, against the other lip's 0.08 mm or more), so the chart is exact for vertices,
landmarks and constraint points; points off the surface (the mirror images of the symmetry term) take
the blend of the surface point below them.

Pure math and one torch module, no file I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from models.checks import check_shape
from models.touching import touching_pairs

TEAR_FACTOR = 5.0
"""A touching pair tears in a shape where its distance grows past this factor (and past ``TEAR_MIN_MM``)."""
TEAR_MIN_MM = 2.0
MIN_TEARING_PAIRS = 20
"""Fewer tearing pairs than this in every shape: no chart (the identity)."""


@dataclass(frozen=True)
class Tearing:
    """The shape that tears the neutral's surface most, from :func:`tearing_shape`."""

    shape: int | None          # index into the shapes (neutral first), None when no shape tears
    pairs: int                 # touching pairs that tear in that shape
    touching: int              # touching pairs in the neutral
    worst_mm: tuple[float, float]  # the most torn pair: distance in the neutral and in the shape


def parted_vertices(shapes: np.ndarray, pairs: np.ndarray) -> list[np.ndarray]:
    """For each shape of ``shapes (N, V, 3)`` mm (neutral first), the vertex indices of the touching ``pairs``
    (:func:`touching_pairs`) that tear in it (move apart past ``TEAR_FACTOR`` times and ``TEAR_MIN_MM``)."""
    s = np.asarray(shapes, dtype=np.float64)
    if not len(pairs):
        return [np.zeros(0, dtype=np.int64) for _ in s]
    return [np.unique(pairs[row]) for row in _tears(s[0], s, pairs)[2]]


def _tears(neutral: np.ndarray, shapes: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The ``pairs``' distances in the neutral ``(K,)`` and in each shape ``(N, K)``, and which tear ``(N, K)``."""
    d0 = np.linalg.norm(neutral[pairs[:, 0]] - neutral[pairs[:, 1]], axis=-1)
    dk = np.linalg.norm(shapes[:, pairs[:, 0]] - shapes[:, pairs[:, 1]], axis=-1)
    return d0, dk, (dk > TEAR_FACTOR * d0) & (dk > TEAR_MIN_MM)


def tearing_shape(neutral: np.ndarray, faces: np.ndarray, shapes: np.ndarray) -> Tearing:
    """The shape in which most touching vertex pairs of the neutral move apart.

    Args:
        neutral: ``(V, 3)`` mm; faces: ``(F, 3)`` vertex indices; shapes: ``(N, V, 3)`` mm, neutral first.
    """
    neutral = np.asarray(neutral, dtype=np.float64)
    pairs = touching_pairs(neutral, faces)
    if not len(pairs):
        return Tearing(None, 0, 0, (0.0, 0.0))
    d0, dk, torn = _tears(neutral, np.asarray(shapes, dtype=np.float64), pairs)
    counts = torn.sum(1)
    counts[0] = 0
    k = int(np.argmax(counts))
    if counts[k] < MIN_TEARING_PAIRS:
        return Tearing(None, int(counts[k]), len(pairs), (0.0, 0.0))
    worst = int(np.argmax(np.where(torn[k], dk[k] / np.maximum(d0, 1e-6), -np.inf)))
    return Tearing(k, int(counts[k]), len(pairs), (float(d0[worst]), float(dk[k, worst])))


def opened(shapes: np.ndarray, tear: Tearing, fraction: float) -> np.ndarray:
    """``(V, 3)`` mm: the neutral ``shapes[0]`` moved ``fraction`` of the way to the tearing shape (the neutral
    itself when no shape tears). ``shapes (N, V, 3)``, neutral first; ``tear`` from :func:`tearing_shape`."""
    s0 = np.asarray(shapes[0], dtype=np.float64)
    return s0 if tear.shape is None else s0 + fraction * (np.asarray(shapes[tear.shape], np.float64) - s0)


class InputChart(nn.Module):
    """``x(c) = c + offset(c)``: the network input of template point ``c`` (mm in, mm out).

    Buffers (saved with the model): ``vertices (V, 3)`` the template, mm; ``faces (F, 3)``;
    ``offset (V, 3)`` mm, each vertex's move (a fraction of the tearing shape's displacement).
    """

    def __init__(self, vertices: torch.Tensor, faces: torch.Tensor, offset: torch.Tensor):
        super().__init__()
        check_shape(vertices, "V,3", "chart template vertices")
        check_shape(offset, f"{vertices.shape[0]},3", "chart offsets")
        check_shape(faces, "F,3", "chart faces")
        self.register_buffer("vertices", vertices.detach().float().clone())
        self.register_buffer("faces", faces.detach().long().clone())
        self.register_buffer("offset", offset.detach().float().clone())
        self._lookup = None

    CANDIDATES = 6

    @classmethod
    def from_shape(cls, neutral: np.ndarray, faces: np.ndarray, shape: np.ndarray, fraction: float) -> "InputChart":
        """The chart that moves the neutral ``fraction`` of the way to ``shape`` (both ``(V, 3)`` mm)."""
        t = lambda a: torch.as_tensor(np.asarray(a))
        return cls(t(neutral).float(), t(faces), t(fraction * (np.asarray(shape) - np.asarray(neutral))).float())

    def _surface(self):
        if self._lookup is None:
            v = self.vertices.detach().cpu().double().numpy()
            f = self.faces.detach().cpu().numpy()
            area = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
            good = np.flatnonzero(area > 1e-9 * max(float(area.max()), 1e-300))   # no plane: never a chart triangle
            corners = f[good].ravel()
            incident = np.full((len(v), max(1, np.bincount(corners, minlength=len(v)).max())), -1)  # faces at each vertex
            order = np.argsort(corners, kind="stable")
            vert = corners[order]
            slot = np.arange(len(order)) - np.searchsorted(vert, vert)
            incident[vert, slot] = good[order // 3]
            rows = {r.tobytes(): i for i, r in enumerate(v) if incident[i, 0] >= 0}
            self._lookup = (rows, torch.as_tensor(v, dtype=torch.float32), incident, v, f)
        return self._lookup

    def locate(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(triangle index (P,), closest point (P, 3))`` of each point's closest surface point.

        A template vertex takes one of its triangles. Other points search the triangles at their ``CANDIDATES``
        nearest vertices (exact point-triangle distances): on a registered face mesh that holds the closest
        triangle (checked against trimesh's exact query in the tests, on the face, off it and mirrored).
        Brute-force neighbours in torch, no spatial index: trimesh's took 1.4 s to build per actor, and the
        streamed fit process imports neither scipy nor trimesh."""
        rows, vt, incident, v, f = self._surface()
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        at = np.array([rows.get(r.tobytes(), -1) for r in p], dtype=np.int64)
        tri = np.where(at >= 0, incident[np.maximum(at, 0), 0], -1)
        closest = p.copy()
        off = np.flatnonzero(at < 0)
        if len(off):
            cand = incident[_nearest(p[off], vt, self.CANDIDATES)].reshape(len(off), -1)
            row = np.repeat(np.arange(len(off)), cand.shape[1])
            pair = np.unique((row * len(f) + cand.ravel())[cand.ravel() >= 0])   # each (point, triangle) once
            row, pair_tri = pair // len(f), pair % len(f)
            pts = closest_on_triangles(v[f[pair_tri]], p[off][row])
            order = np.lexsort((np.linalg.norm(pts - p[off][row], axis=-1), row))   # by point, nearest first
            first = order[np.searchsorted(row[order], np.arange(len(off)))]
            tri[off], closest[off] = pair_tri[first], pts[first]
        return tri, closest

    def forward(self, c: torch.Tensor, triangles: np.ndarray | None = None) -> torch.Tensor:
        """Chart points ``(*, P, 3)`` mm of template points ``c (*, P, 3)`` mm.

        Each point takes the barycentric blend of its triangle's vertex offsets at its projection onto the
        triangle's plane: exact on the surface, the closest surface point's blend just off it, and affine in
        ``c`` (so its derivative is the true one). ``triangles (P,)``: the points' triangles from
        :meth:`locate`, for callers under ``torch.func`` transforms (the search runs in numpy)."""
        flat = c.reshape(-1, 3)
        if triangles is None:
            triangles, _ = self.locate(flat.detach().cpu().numpy())
        corners = self.faces[torch.as_tensor(np.asarray(triangles), device=self.faces.device)]   # (P, 3)
        a, b, d = (self.vertices.to(c.dtype)[corners[:, k]] for k in range(3))
        e0, e1, e2 = b - a, d - a, flat - a
        d00, d01, d11 = (e0 * e0).sum(-1), (e0 * e1).sum(-1), (e1 * e1).sum(-1)
        d20, d21 = (e2 * e0).sum(-1), (e2 * e1).sum(-1)
        den = d00 * d11 - d01 * d01
        wb, wc = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
        w = torch.stack([1 - wb - wc, wb, wc], -1)
        moved = (w.unsqueeze(-1) * self.offset.to(c.dtype)[corners]).sum(1)
        return c + moved.reshape(c.shape)


def _nearest(points: np.ndarray, sites: torch.Tensor, k: int, chunk: int = 2048) -> np.ndarray:
    """``(P, k)`` indices of the ``k`` nearest of ``sites (S, 3)`` to each of ``points (P, 3)`` (brute force)."""
    k = min(k, sites.shape[0])
    out = []
    for s in range(0, len(points), chunk):
        d = torch.cdist(torch.as_tensor(points[s:s + chunk], dtype=sites.dtype), sites)
        out.append(d.topk(k, dim=1, largest=False).indices.numpy())
    return np.concatenate(out)


def closest_on_triangles(triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``(P, 3)``: the closest point of triangle ``triangles[p] (P, 3, 3)`` to ``points[p] (P, 3)``.

    The projection onto the triangle's plane where it falls inside, else the nearest point of its three
    edges (as ``trimesh.triangles.closest_point``, which the tests compare; here without importing trimesh)."""
    a, b, c = triangles[:, 0], triangles[:, 1], triangles[:, 2]
    e0, e1, e2 = b - a, c - a, points - a
    d00, d01, d11 = (e0 * e0).sum(-1), (e0 * e1).sum(-1), (e1 * e1).sum(-1)
    d20, d21 = (e2 * e0).sum(-1), (e2 * e1).sum(-1)
    den = np.where(np.abs(d00 * d11 - d01 * d01) > 0, d00 * d11 - d01 * d01, 1.0)
    wb, wc = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    best = a + wb[:, None] * e0 + wc[:, None] * e1
    inside = (wb >= 0) & (wc >= 0) & (wb + wc <= 1)
    edge_best, edge_d = None, np.full(len(points), np.inf)
    for s, t in ((a, b), (b, c), (c, a)):
        seg = t - s
        u = np.clip(((points - s) * seg).sum(-1) / np.maximum((seg * seg).sum(-1), 1e-300), 0.0, 1.0)
        q = s + u[:, None] * seg
        dq = np.linalg.norm(points - q, axis=-1)
        better = dq < edge_d
        edge_d = np.where(better, dq, edge_d)
        edge_best = q if edge_best is None else np.where(better[:, None], q, edge_best)
    return np.where(inside[:, None], best, edge_best)


def chart_from_state(state: dict[str, torch.Tensor]) -> InputChart | None:
    """The chart saved in a model's ``state_dict`` (keys ``chart.*``), or None (actors before the chart)."""
    if "chart.offset" not in state:
        return None
    return InputChart(state["chart.vertices"], state["chart.faces"], state["chart.offset"])
