"""A frame's mesh from its map of the actor's features, in numpy (no torch: the run's own process uses it).

Where every vertex of a frame has the same expression coefficients (the 2D fit's default, F_W at zero), the
posed mesh is linear in each vertex's features ``f = [s0, k s0, k, E_1 .. E_E, 1]``
(:func:`models.fit_state.pose_features`): vertex ``= M f`` with one ``(3, 8 + 3E)`` matrix ``M`` per frame
(:func:`models.fit_state.shared_pose_maps`). A fit can then hand over ``M`` instead of the mesh.
"""

from __future__ import annotations

import numpy as np


def map_vertices(mesh_map: np.ndarray, basis: np.ndarray) -> np.ndarray:
    """One frame's ``(P, 3)`` float32 posed points from its ``mesh_map (3, K)``
    (:func:`models.fit_state.shared_pose_maps`, as float32) and ``basis (K, P)`` float32
    (:func:`models.fit_state.mesh_basis`). Every consumer of a frame's map
    (the fit, the run's process that receives it, a stored fit) computes its vertices with this one function,
    so they agree to the bit."""
    if mesh_map.dtype != np.float32 or basis.dtype != np.float32 or mesh_map.shape != (3, basis.shape[0]):
        raise ValueError(f"map_vertices takes a float32 (3, K) map and a float32 (K, P) basis, got "
                         f"{mesh_map.dtype} {mesh_map.shape} and {basis.dtype} {basis.shape}")
    return np.ascontiguousarray(np.dot(mesh_map, basis).T)
