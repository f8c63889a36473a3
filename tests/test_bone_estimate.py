"""Tests of models.bone_estimate: the inward offset of a sphere and of a synthetic face."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from capture.io.errors import CaptureError
from models.bone_estimate import TISSUE_PROFILE_MM, estimate_bone_surface, typical_tissue_thickness
from models.face_frame import estimate_face_frame, midline_landmarks
from tests.synthetic_face import synthetic_face


def test_offset_of_a_sphere_has_the_expected_radius():
    skin = trimesh.creation.icosphere(subdivisions=4, radius=100.0)
    bone = estimate_bone_surface(skin, None, 10.0)
    r = np.linalg.norm(bone.vertices, axis=1)
    # vertex normals of an icosphere are radial; Taubin smoothing moves vertices by well under
    # 0.1 mm at this tessellation (its Laplacian shrink and inflate nearly cancel)
    assert np.abs(r - 90.0).max() < 0.1, np.abs(r - 90.0).max()
    np.testing.assert_array_equal(bone.faces, skin.faces)
    # a callable thickness: thicker in the upper half
    bone2 = estimate_bone_surface(skin, None, lambda v, frame: np.where(v[:, 2] > 0, 20.0, 5.0))
    r2 = np.linalg.norm(bone2.vertices, axis=1)
    z = skin.vertices[:, 2]
    assert np.all(np.abs(r2[z > 30] - 80.0) < 0.5) and np.all(np.abs(r2[z < -30] - 95.0) < 0.5)


def test_default_profile_on_a_synthetic_face():
    v, f = synthetic_face()
    skin = trimesh.Trimesh(v, f, process=False)
    frame = estimate_face_frame(v, f)
    d = typical_tissue_thickness(v, frame)
    lo, hi = min(t for _, t in TISSUE_PROFILE_MM), max(t for _, t in TISSUE_PROFILE_MM)
    assert d.min() >= lo and d.max() <= hi
    tip = midline_landmarks(v, frame).nose_tip
    h = (v - tip) @ frame.up
    assert np.allclose(d[h > 40], 5.5) and np.all(d[np.abs(h + 10) < 1] > 11.0)
    bone = estimate_bone_surface(skin, frame)
    depth = np.einsum("ij,ij->i", v - bone.vertices, skin.vertex_normals)
    # on the forehead (smooth, away from the border) the bone lies ~5.5 mm under the skin
    fore = (h > 50) & (h < 80) & (np.abs(v[:, 0]) < 30)
    assert np.all(np.abs(depth[fore] - 5.5) < 1.0)
    # nowhere above the skin, and no non-finite values
    assert np.all(np.isfinite(bone.vertices)) and np.percentile(depth, 1) > 0.0


def test_bad_thickness_raises():
    skin = trimesh.creation.icosphere(subdivisions=2, radius=100.0)
    with pytest.raises(CaptureError, match="thickness"):
        estimate_bone_surface(skin, None, -1.0)
    with pytest.raises(CaptureError, match="frame"):
        estimate_bone_surface(skin, None)
