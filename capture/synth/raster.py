"""A vectorised z-buffer triangle rasteriser (numpy), with a slow reference beside it.

Conventions (the project's, see :mod:`calib.camera`): pixel centres sit at integer coordinates, so
pixel ``(u, v)`` (column, row) is covered by a triangle when its centre ``(u, v)`` lies inside the
triangle's 2D projection. Vertices come in already projected: ``uv (V, 2)`` pixels (through any lens
model, e.g. with OpenCV distortion applied) and ``z (V,)`` camera depth in mm (z forward, > 0).

Triangle edges are straight lines between the projected vertices (with lens distortion a triangle's
interior is linearised; for triangles a few pixels wide the error is far below a pixel). Barycentric
coordinates are perspective-correct: the returned ``bary`` are the 3D barycentric coordinates of the
visible surface point, so any attribute that is linear on the 3D triangle (position, a position
colour code) is interpolated exactly. No face culling: the z-buffer resolves which surface is seen.

Example:
    >>> uv = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 4.0]]); z = np.ones(3)
    >>> r = rasterize(uv, z, np.array([[0, 1, 2]]), (5, 5))
    >>> int((r.face >= 0).sum())
    15
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: Tolerance of the inside test, in units of barycentric coordinates: shared edges are covered by
#: both triangles (the z-buffer then picks one), so there are no cracks between triangles.
INSIDE_EPS = 1e-7

#: Upper bound on candidate pixels held in memory at once (pixels x triangles of one chunk).
CHUNK_CANDIDATES = 4_000_000


@dataclass
class Raster:
    """Per-pixel result of :func:`rasterize` for an image of ``(height, width)``."""

    face: np.ndarray    # (H, W) int64 triangle index, -1 where no triangle covers the pixel
    bary: np.ndarray    # (H, W, 3) float32 perspective-correct barycentric coordinates (0 on background)
    depth: np.ndarray   # (H, W) float32 camera depth z in mm, +inf on background

    def interpolate(self, vertex_values: np.ndarray, faces: np.ndarray, background) -> np.ndarray:
        """Interpolate per-vertex values ``(V, C)`` over the image -> ``(H, W, C)`` float32."""
        vertex_values = np.asarray(vertex_values)
        out = np.empty(self.face.shape + vertex_values.shape[1:], np.float32)
        out[...] = np.asarray(background, dtype=np.float32)
        covered = self.face >= 0
        vals = vertex_values[faces[self.face[covered]]]         # (N, 3, C): covered pixels only
        out[covered] = np.einsum("nk,nkc->nc", self.bary[covered], vals)
        return out


def _check(uv: np.ndarray, z: np.ndarray, faces: np.ndarray) -> None:
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"uv: expected shape (V,2), got {uv.shape}")
    if z.shape != (uv.shape[0],):
        raise ValueError(f"z: expected shape ({uv.shape[0]},) matching uv, got {z.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3:
        raise ValueError(f"faces: expected shape (F,3), got {faces.shape}")


def _fragments(uv: np.ndarray, z: np.ndarray, faces: np.ndarray, size: tuple[int, int]):
    """All covered (pixel, triangle) pairs: flat pixel index, triangle, perspective bary, depth."""
    w, h = size
    f0, f1, f2 = faces[:, 0], faces[:, 1], faces[:, 2]
    a, b, c = uv[f0], uv[f1], uv[f2]                           # (F, 2) each
    tz = z[faces]                                              # (F, 3)
    # min / max of three (F, 2) arrays: element-wise, far faster than a reduction over an axis of 3
    lo = np.maximum(np.ceil(np.minimum(np.minimum(a, b), c)), 0).astype(np.int64)
    hi = np.minimum(np.floor(np.maximum(np.maximum(a, b), c)), [w - 1, h - 1]).astype(np.int64)
    area = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])
    good = np.isfinite(uv).all(1) & (z > 1e-6)                # per vertex
    ok = ((hi[:, 0] >= lo[:, 0]) & (hi[:, 1] >= lo[:, 1]) & (np.abs(area) > 1e-12)
          & good[f0] & good[f1] & good[f2])
    ext = np.where(ok, np.maximum(hi[:, 0] - lo[:, 0], hi[:, 1] - lo[:, 1]) + 1, 0)
    outs = []
    # Bucket triangles by bounding-box size (powers of two) so candidates stay dense.
    bucket = np.where(ext > 0, np.ceil(np.log2(np.maximum(ext, 1))).astype(np.int64), -1)
    for k in np.unique(bucket[bucket >= 0]):
        s = 1 << int(k)
        idx_all = np.flatnonzero(bucket == k)
        oy, ox = np.divmod(np.arange(s * s, dtype=np.float64), s)   # pixel offsets (exact in float64)
        step = max(1, CHUNK_CANDIDATES // (s * s))
        for start in range(0, len(idx_all), step):
            idx = idx_all[start:start + step]
            px = lo[idx, 0, None] + ox[None]                   # (n, s*s) float64 pixel centres
            py = lo[idx, 1, None] + oy[None]
            inb = (px <= hi[idx, 0, None]) & (py <= hi[idx, 1, None])
            ta, tb, tc = a[idx], b[idx], c[idx]
            inv = 1.0 / area[idx, None]
            # Edge functions: l0 weights vertex a (opposite edge b-c), etc.
            l0 = ((tb[:, 0, None] - px) * (tc[:, 1, None] - py) - (tb[:, 1, None] - py) * (tc[:, 0, None] - px)) * inv
            l1 = ((tc[:, 0, None] - px) * (ta[:, 1, None] - py) - (tc[:, 1, None] - py) * (ta[:, 0, None] - px)) * inv
            l2 = 1.0 - l0 - l1
            inside = inb & (l0 >= -INSIDE_EPS) & (l1 >= -INSIDE_EPS) & (l2 >= -INSIDE_EPS)
            r, col = np.nonzero(inside)
            if r.size == 0:
                continue
            lz = np.stack([l0[r, col], l1[r, col], l2[r, col]], 1).clip(0.0, None)
            q = lz / tz[idx[r]]                               # perspective correction
            qs = (q[:, 0] + q[:, 1] + q[:, 2])[:, None]
            outs.append(((py[r, col] * w + px[r, col]).astype(np.int64), idx[r], q / qs, 1.0 / qs[:, 0]))
    if not outs:
        e = np.zeros(0)
        return e.astype(np.int64), e.astype(np.int64), np.zeros((0, 3)), e
    return tuple(np.concatenate(x) for x in zip(*outs))


def rasterize(uv: np.ndarray, z: np.ndarray, faces: np.ndarray, size: tuple[int, int]) -> Raster:
    """Rasterise triangles with a z-buffer (nearest surface wins).

    Args:
        uv: ``(V, 2)`` projected vertex positions in pixels (pixel centres at integers).
        z: ``(V,)`` vertex depths (mm, > 0); triangles with a vertex at z <= 0 are skipped.
        faces: ``(F, 3)`` vertex indices.
        size: ``(width, height)`` of the image.

    Returns:
        :class:`Raster` with the visible triangle, its perspective-correct barycentric coordinates
        and the depth per pixel.
    """
    uv = np.asarray(uv, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    _check(uv, z, faces)
    w, h = int(size[0]), int(size[1])
    pix, fid, bary, depth = _fragments(uv, z, faces, (w, h))
    face = np.full(h * w, -1, dtype=np.int64)
    out_bary = np.zeros((h * w, 3), dtype=np.float32)
    out_depth = np.full(h * w, np.inf, dtype=np.float32)
    if pix.size:
        zbuf = np.full(h * w, np.inf)
        np.minimum.at(zbuf, pix, depth)                        # the nearest depth per pixel
        win = np.flatnonzero(depth <= zbuf[pix])[::-1]         # nearest fragments; on a tie, the first
        # (assigned last: with repeated indices the last assignment is the one kept)
        face[pix[win]] = fid[win]
        out_bary[pix[win]] = bary[win]
        out_depth[pix[win]] = depth[win]
    return Raster(face.reshape(h, w), out_bary.reshape(h, w, 3), out_depth.reshape(h, w))


def rasterize_reference(uv: np.ndarray, z: np.ndarray, faces: np.ndarray, size: tuple[int, int]) -> Raster:
    """Slow, readable reference of :func:`rasterize` (a loop over triangles and their pixels)."""
    uv = np.asarray(uv, dtype=np.float64)
    z = np.asarray(z, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    _check(uv, z, faces)
    w, h = int(size[0]), int(size[1])
    face = np.full((h, w), -1, dtype=np.int64)
    bary = np.zeros((h, w, 3), dtype=np.float32)
    depth = np.full((h, w), np.inf, dtype=np.float32)
    best = np.full((h, w), np.inf)
    for f, (i, j, k) in enumerate(faces):
        (ax, ay), (bx, by), (cx, cy) = uv[i], uv[j], uv[k]
        zs = np.array([z[i], z[j], z[k]])
        area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        if abs(area) <= 1e-12 or (zs <= 1e-6).any():
            continue
        for v in range(max(0, int(np.ceil(min(ay, by, cy)))), min(h - 1, int(np.floor(max(ay, by, cy)))) + 1):
            for u in range(max(0, int(np.ceil(min(ax, bx, cx)))), min(w - 1, int(np.floor(max(ax, bx, cx)))) + 1):
                l0 = ((bx - u) * (cy - v) - (by - v) * (cx - u)) / area
                l1 = ((cx - u) * (ay - v) - (cy - v) * (ax - u)) / area
                l2 = 1.0 - l0 - l1
                if min(l0, l1, l2) < -INSIDE_EPS:
                    continue
                q = np.clip([l0, l1, l2], 0.0, None) / zs
                d = 1.0 / q.sum()
                if d < best[v, u]:
                    best[v, u] = d
                    face[v, u] = f
                    bary[v, u] = q * d
                    depth[v, u] = d
    return Raster(face, bary, depth)


def sample_nearest(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Values of ``image (H, W, ...)`` at the pixels nearest to ``uv (N, 2)``; NaN-safe (clamped)."""
    h, w = image.shape[:2]
    uv = np.nan_to_num(np.asarray(uv, dtype=np.float64), nan=-1.0)
    u = np.clip(np.rint(uv[:, 0]).astype(np.int64), 0, w - 1)
    v = np.clip(np.rint(uv[:, 1]).astype(np.int64), 0, h - 1)
    return image[v, u]
