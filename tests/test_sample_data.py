"""The bundled sample actor: files, units, topology, bones behind the skin, licences."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from capture.actor import sample as sample_data
from capture.io.errors import CaptureError

FACE_VERTICES = 9409


@pytest.fixture(scope="module")
def info():
    return sample_data.load_sample_info()


@pytest.fixture(scope="module")
def shapes(info):
    d = sample_data.sample_shapes_dir()
    names = [info["neutral"]] + info["training_shapes"]
    return {n: trimesh.load(d / f"{n}.ply", process=False) for n in names}


@pytest.fixture(scope="module")
def bones():
    skull, jaw = sample_data.sample_bones()
    return (trimesh.load(skull, process=False), trimesh.load(jaw, process=False))


def test_shape_lists(info):
    train, held = info["training_shapes"], info["held_out_expressions"]
    assert info["neutral"] == "neutral"
    assert len(train) == 19 and len(held) == 34
    assert not set(train) & set(held)
    assert len(set(train) | set(held)) == 53
    on_disk = {p.stem for p in sample_data.sample_shapes_dir().glob("*.ply")}
    assert on_disk == {"neutral", *train}
    lm = info["landmarks_multipie68"]
    assert len(lm) == 68 and all(0 <= i < FACE_VERTICES for i in lm)


def test_shapes_share_topology_in_mm(shapes, info):
    neutral = shapes["neutral"]
    assert neutral.vertices.shape == (FACE_VERTICES, 3)
    for name, mesh in shapes.items():
        assert mesh.vertices.shape == (FACE_VERTICES, 3), name
        np.testing.assert_array_equal(mesh.faces, neutral.faces, err_msg=name)
        assert np.isfinite(mesh.vertices).all(), name
    # no unused vertex: every vertex belongs to a triangle
    assert len(np.unique(neutral.faces)) == FACE_VERTICES
    # face width between the ends of the 68-landmark jaw contour (the face region also holds
    # the ears, so its bounding box is wider than the face)
    lm = info["landmarks_multipie68"]
    width = np.linalg.norm(neutral.vertices[lm[0]] - neutral.vertices[lm[16]])
    assert 120.0 < width < 180.0, f"face width {width:.1f} is not in mm"
    assert 150.0 < np.ptp(neutral.vertices[:, 0]) < 250.0


def test_expressions_differ_from_neutral(shapes):
    neutral = shapes["neutral"].vertices
    for name, mesh in shapes.items():
        if name == "neutral":
            continue
        disp = np.linalg.norm(mesh.vertices - neutral, axis=1)
        assert disp.max() > 2.0, f"{name} barely differs from the neutral"
        assert disp.max() < 60.0, f"{name} moves a vertex implausibly far"


def test_skin_normals_point_outward(shapes):
    neutral = shapes["neutral"]
    # normals of the front of the face point towards +z (the ICT face looks along +z)
    nose_tip = neutral.vertices[:, 2].argmax()
    assert neutral.vertex_normals[nose_tip][2] > 0.5
    assert np.mean(neutral.face_normals[:, 2] > 0) > 0.6


def test_bones_behind_skin(shapes, bones):
    face = shapes["neutral"]
    bone = trimesh.util.concatenate(list(bones))
    q, dist, tri = trimesh.proximity.closest_point(face, bone.vertices)
    # side of the skin, from the normal interpolated at the closest point; only where that point
    # lies inside the face region (at its border - eyes, mouth, outline - the side is undefined)
    bary = trimesh.triangles.points_to_barycentric(face.triangles[tri], q)
    n = np.einsum("ij,ijk->ik", bary, face.vertex_normals[face.faces[tri]])
    side = np.einsum("ij,ij->i", bone.vertices - q, n)
    edges = face.edges_sorted
    border = np.zeros(len(face.vertices), bool)
    border[edges[trimesh.grouping.group_rows(edges, require_count=1)].ravel()] = True
    covered = (dist < 40.0) & ~border[face.faces[tri]].any(axis=1)
    assert covered.sum() > 3000
    behind = side[covered] < 0
    assert behind.mean() > 0.95, f"only {behind.mean():.1%} of bone vertices behind the skin"
    # soft-tissue thickness from the skin to the nearest bone: plausible for an adult face
    _, d_skin, _ = trimesh.proximity.closest_point(bone, face.vertices)
    assert 4.0 < np.median(d_skin) < 25.0
    assert np.percentile(d_skin, 1) > 1.5, "bone touches the skin"


def test_bone_normals_face_the_skin(shapes, bones):
    """The product keeps a ray hit only where the bone faces the same way as the skin."""
    face = shapes["neutral"]
    bone = trimesh.util.concatenate(list(bones))
    idx = np.arange(0, FACE_VERTICES, 5)
    n = face.vertex_normals[idx]
    loc, ray, tri = bone.ray.intersects_location(face.vertices[idx], -n, multiple_hits=False)
    assert len(ray) > 0.3 * len(idx)
    same_way = np.einsum("ij,ij->i", bone.face_normals[tri], n[ray]) > 0
    assert same_way.mean() > 0.8


def test_teeth_anchor_in_report(info):
    rep = info["fit_report"]["teeth_to_bone"]
    assert rep["ict_lower_teeth_to_jaw"]["median_mm"] < 4.0
    assert rep["ict_upper_teeth_to_skull"]["median_mm"] < 4.0


def test_licences_and_size():
    root = sample_data.sample_actor_dir()
    lic = root / "LICENSES"
    assert "MIT License" in (lic / "ICT-FaceKit-MIT.txt").read_text()
    assert "ArtiSynth" in (lic / "ArtiSynth-Models.txt").read_text()
    assert (root / "README.md").is_file()
    for name in ("skull.ply", "jaw.ply"):
        assert (root / "bones" / name).stat().st_size < 1.1e6
    total = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    assert total < 10e6


def test_missing_data_is_a_capture_error(tmp_path, monkeypatch):
    monkeypatch.setattr(sample_data, "sample_actor_dir", lambda: tmp_path)
    with pytest.raises(CaptureError):
        sample_data.sample_bones()
    with pytest.raises(CaptureError):
        sample_data.sample_shapes_dir()
    with pytest.raises(CaptureError):
        sample_data.load_sample_info()
