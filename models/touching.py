"""Where a mesh touches itself: vertex pairs closer than ``TOUCH_MM`` that share no triangle.

On a registered face with a closed mouth these are mostly the lips, which expressions pull apart, and wherever
else the scan touches itself: on the ICT sample 5,376 pairs, from the lips (44 mm below the nose tip) to the
eyelids (37 mm above). Pure numpy and scipy; no torch, so the face frame can use it.
"""

from __future__ import annotations

import numpy as np

TOUCH_MM = 1.5
"""Vertices closer than this in the neutral, and not sharing a triangle, count as touching."""


def touching_pairs(neutral: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``(K, 2)`` vertex index pairs closer than ``TOUCH_MM`` in ``neutral (V, 3)`` mm that share no triangle
    (the lips of a closed mouth), each pair sorted."""
    from scipy.spatial import cKDTree

    pairs = cKDTree(np.asarray(neutral, dtype=np.float64)).query_pairs(TOUCH_MM, output_type="ndarray")
    if len(pairs):
        f = np.asarray(faces, dtype=np.int64)
        edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
        adjacent = {(int(a), int(b)) for a, b in np.sort(edges, axis=1)}  # a triangle's two vertices
        pairs = np.sort(pairs, axis=1)
        pairs = pairs[[(int(a), int(b)) not in adjacent for a, b in pairs]]
    return pairs.reshape(-1, 2)
