"""Mirrored expression shapes (models/mirror.py, capture.actor.training.with_mirrored_shapes).

The geometry is checked against a readable reference on a mesh that is symmetric by construction (each
vertex's mirror is another vertex, so the mirrored field is known exactly), with trimesh's closest points;
the whole step against real scans: the bundled ICT sample holds both sides of several expressions
(mouthSmile_L/_R, eyeBlink_L/_R, browDown_L/_R, browInnerUp_L/_R), so the mirror of one side must be the
other side's scan.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from models.mirror import (ONE_SIDED_THRESHOLD, mirror_displacements, mirror_points, mirrored_name,
                           one_sided, reflection)


def _closest(mesh):
    def f(points):
        pts, _, tri = trimesh.proximity.closest_point(mesh, points)
        return pts, tri
    return f


def _symmetric_sheet(n: int = 21):
    """A curved sheet over x, y in [-30, 30] mm, symmetric about x = 0, with a mirror-symmetric triangulation."""
    xs = np.linspace(-30, 30, n)
    X, Y = np.meshgrid(xs, xs, indexing="ij")
    Z = 20.0 - 0.01 * X ** 2 - 0.005 * Y ** 2
    v = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    faces = []
    for i in range(n - 1):
        for j in range(n - 1):
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            # split along the diagonal that mirrors onto itself: left half one way, right half the other
            faces += [[a, b, c], [a, c, d]] if xs[i] >= 0 else [[a, b, d], [b, c, d]]
    return v, np.array(faces)


def test_reflection_is_an_involution_that_fixes_its_plane():
    rng = np.random.default_rng(0)
    n, d = np.array([2.0, 0.1, -0.2]), 3.0
    M, o = reflection(n, d)
    x = rng.normal(size=(50, 3)) * 20
    P = lambda p: p @ M.T + o
    np.testing.assert_allclose(P(P(x)), x, atol=1e-12)
    u = n / np.linalg.norm(n)
    on_plane = x - ((x @ u) - d / np.linalg.norm(n))[:, None] * u
    np.testing.assert_allclose(P(on_plane), on_plane, atol=1e-12)
    # the distance to the plane changes sign, and the point moves along the normal only
    dist = x @ u - d / np.linalg.norm(n)
    np.testing.assert_allclose(P(x) @ u - d / np.linalg.norm(n), -dist, atol=1e-12)
    with pytest.raises(ValueError, match="non-zero normal"):
        reflection([0, 0, 0], 1.0)


def test_mirrored_field_on_a_symmetric_mesh_equals_the_reference():
    v, f = _symmetric_sheet()
    mesh = trimesh.Trimesh(v, f, process=False)
    mm = mirror_points(v, f, [1.0, 0.0, 0.0], 0.0, _closest(mesh))
    assert mm.distance.max() < 1e-9                       # every reflected vertex lies on the surface
    # an asymmetric displacement: the right half (x < 0) bulges sideways and back, the left half is still
    bump = np.exp(-((v[:, 0] + 12) ** 2 + v[:, 1] ** 2) / 60.0)
    d = np.stack([-2.0 * bump, 0.5 * bump, -1.0 * bump], 1)[None]
    got = mirror_displacements(d, f, mm, [1.0, 0.0, 0.0])[0]
    # slow reference: for each vertex find the vertex at (-x, y) and reflect its displacement's x
    ref = np.zeros_like(got)
    for i, p in enumerate(v):
        j = int(np.argmin(np.linalg.norm(v - p * [-1, 1, 1], axis=1)))
        ref[i] = d[0, j] * [-1, 1, 1]
    np.testing.assert_allclose(got, ref, atol=1e-9)
    assert np.abs(got[v[:, 0] < -5]).max() < 0.01 * np.abs(got[v[:, 0] > 5]).max()   # the bulge moved sides


def test_one_sided_separates_pairs_from_single_sides():
    rng = np.random.default_rng(2)
    L = rng.normal(size=(100, 3))
    R = rng.normal(size=(100, 3))
    sym = rng.normal(size=(100, 3))
    other = rng.normal(size=(100, 3))
    disp = np.stack([L, R, sym, other])
    mirrored = np.stack([R, L, sym, rng.normal(size=(100, 3))])   # the last one's mirror is new
    r = one_sided(disp, mirrored)
    np.testing.assert_allclose(r[:3], 0, atol=1e-12)
    assert r[3] > 0.9                                      # a random 300-vector is nearly outside a 4-D span
    assert (r > ONE_SIDED_THRESHOLD).tolist() == [False, False, False, True]


@pytest.mark.parametrize("name, taken, expected", [
    ("mouthStretch_L", set(), "mouthStretch_R"),
    ("cheekPuff_R", set(), "cheekPuff_L"),
    ("mouthLeft", set(), "mouthRight"),
    ("lip_l_corner", set(), "lip_r_corner"),
    ("smirk", set(), "smirk_mirrored"),
    ("mouthStretch_L", {"mouthStretch_R"}, "mouthStretch_L_mirrored"),
    ("smirk", {"smirk_mirrored"}, "smirk_mirrored2"),
    ("mouth_lowerDown", set(), "mouth_lowerDown_mirrored"),
])
def test_mirrored_names(name, taken, expected):
    assert mirrored_name(name, taken) == expected


def test_sample_mirrors_are_the_other_sides_scans():
    """On the bundled ICT sample: the mirror of each left scan is its right scan, and only the one-sided
    shapes are added, under the other side's name."""
    from capture.actor.sample import sample_shapes_dir
    from capture.actor.training import mirror_map, with_mirrored_shapes
    from capture.io.meshes import load_shape_dir
    from models.face_frame import estimate_face_frame

    shapes = load_shape_dir(sample_shapes_dir(), None, "mm")
    frame = estimate_face_frame(shapes.vertices[0], shapes.faces)
    mesh = trimesh.Trimesh(shapes.vertices[0], shapes.faces, process=False)
    mm = mirror_points(shapes.vertices[0], shapes.faces, frame.symmetry_normal, frame.symmetry_offset, _closest(mesh))
    idx = {n: i for i, n in enumerate(shapes.names)}
    for left, right in (("mouthSmile_L", "mouthSmile_R"), ("eyeBlink_L", "eyeBlink_R"),
                        ("browDown_L", "browDown_R"), ("browInnerUp_L", "browInnerUp_R")):
        d_left = shapes.vertices[idx[left]] - shapes.vertices[0]
        d_right = shapes.vertices[idx[right]] - shapes.vertices[0]
        got = mirror_displacements(d_left[None], shapes.faces, mm, frame.symmetry_normal)[0]
        err = np.linalg.norm(got - d_right, axis=1)
        size = np.linalg.norm(d_right, axis=1)
        # ICT's identity is nearly symmetric (mirror distance median ~0.8 mm): the other side within 10 % of its motion
        assert err.mean() < 0.1 * size.mean(), (left, err.mean(), size.mean())
    # Matched where the lips are apart (training.mirror_map), the lip corners get their own side's motion: the
    # mirrors of the scanned mouthSmile_L and jawLeft are within 0.5 mm of the scanned right sides at every
    # vertex; matched at the closed neutral, the lower lip's motion lands on the upper lip (2.6 / 3.6 mm).
    opened = mirror_map(shapes, frame)
    for left, right in (("mouthSmile_L", "mouthSmile_R"), ("jawLeft", "jawRight")):
        d_left = shapes.vertices[idx[left]] - shapes.vertices[0]
        d_right = shapes.vertices[idx[right]] - shapes.vertices[0]
        worst = {name: np.linalg.norm(mirror_displacements(d_left[None], shapes.faces, m, frame.symmetry_normal)[0]
                                      - d_right, axis=1).max() for name, m in (("open", opened), ("closed", mm))}
        assert worst["open"] < 0.5 < 2.0 < worst["closed"], (left, worst)
    out, added, asym = with_mirrored_shapes(shapes, frame)
    assert 0 < asym["median_mm"] < 0.5 and asym["median_mm"] <= asym["p90_mm"] < 1.5   # ICT: 0.2 / 0.7 mm
    assert set(added) == {"browOuterUp_R", "cheekPuff_L", "mouthFrown_L", "mouthStretch_R", "noseSneer_R"}
    assert {a["from"] for a in added.values()} == {"browOuterUp_L", "cheekPuff_R", "mouthFrown_R",
                                                   "mouthStretch_L", "noseSneer_L"}
    assert out.names[: len(shapes.names)] == shapes.names
    np.testing.assert_array_equal(out.vertices[: len(shapes.names)], shapes.vertices)
    assert out.vertices.shape == (len(shapes.names) + 5,) + shapes.vertices.shape[1:]
    # the added stretch moves the right mouth corner as the scanned left stretch moves the left one
    left_corner_motion = np.linalg.norm(shapes.vertices[idx["mouthStretch_L"]] - shapes.vertices[0], axis=1)
    right = out.vertices[out.names.index("mouthStretch_R")] - shapes.vertices[0]
    side = shapes.vertices[0] @ frame.symmetry_normal - frame.symmetry_offset      # > 0: the face's left
    assert np.linalg.norm(right, axis=1)[side < -10].mean() > 5 * np.linalg.norm(right, axis=1)[side > 10].mean()
    assert np.isclose(np.linalg.norm(right, axis=1).max(), left_corner_motion.max(), rtol=0.1)
