"""Tests of models.anatomy_constraints on analytic sphere-in-sphere cases (and the sample actor)."""

from __future__ import annotations

import io
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from capture.io.errors import CaptureError
from models.anatomy_constraints import (
    AnatomyConstraints,
    compute_anatomy_constraints,
    default_trusted_region,
    make_ray_intersector,
)

SAMPLE = Path(__file__).resolve().parents[1] / "capture" / "data" / "sample_actor"


def sphere(radius: float, subdivisions: int, centre=(0.0, 0.0, 0.0), seed: int | None = None) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    if seed is not None:  # rotate so its vertices do not line up with another sphere's
        m.apply_transform(trimesh.transformations.random_rotation_matrix(np.random.default_rng(seed).random(3)))
    m.apply_translation(centre)
    return m


def sagitta(m: trimesh.Trimesh, centre=(0.0, 0.0, 0.0)) -> float:
    """Largest gap between a polyhedral sphere and its true sphere: radius minus the nearest
    triangle point (at most the in-centre of a face); bounds the tessellation error of a ray hit."""
    r = np.linalg.norm(m.vertices - centre, axis=1).mean()
    closest = m.triangles_center  # the face centre is (nearly) the deepest point of each facet
    return float(r - np.linalg.norm(closest - centre, axis=1).min())


def test_concentric_spheres_give_constant_thickness():
    skin = sphere(100.0, 5)
    bone = sphere(90.0, 4, seed=1)
    c = compute_anatomy_constraints(skin, [bone])
    tol = sagitta(skin) + sagitta(bone) + 1e-6  # ~0.02 + 0.07 mm
    assert c.coverage > 0.9
    assert np.all(np.abs(c.thickness - 10.0) <= tol), np.abs(c.thickness - 10.0).max()
    rb = np.linalg.norm(c.bone_point, axis=1)
    assert np.all(np.abs(rb - 90.0) <= sagitta(bone) + 1e-6)
    rs = np.linalg.norm(c.skin_point, axis=1)
    assert np.all(np.abs(rs - 100.0) <= sagitta(skin) + 1e-6)
    radial = c.bone_point / rb[:, None]
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", c.bone_normal, radial), -1, 1)))
    assert ang.max() < 1.0, ang.max()
    np.testing.assert_allclose(np.linalg.norm(c.bone_normal, axis=1), 1.0, atol=1e-9)
    # the stored relation of the paper: s0 = b0 + d n0
    np.testing.assert_allclose(c.bone_point + c.thickness[:, None] * c.bone_normal, c.skin_point, atol=1e-6)
    # face/barycentric reproduce the skin point
    bary_pts = np.einsum("ij,ijk->ik", c.barycentric, skin.triangles[c.face_index])
    np.testing.assert_allclose(bary_pts, c.skin_point, atol=1e-6)
    assert c.face_index.dtype == np.int64 and c.bone_label.dtype == np.int8
    assert np.all(c.bone_label == 0)


def test_offset_sphere_matches_analytic_ray_intersection():
    centre = np.array([8.0, 3.0, -2.0])
    r_bone, r_skin = 80.0, 100.0
    skin = sphere(r_skin, 5)
    bone = sphere(r_bone, 5, centre=centre, seed=2)
    # the ray casting itself: thickness up to 28 mm here, and no smoothing of the targets
    c = compute_anatomy_constraints(skin, [bone], max_thickness=30.0, max_angle_deg=45.0, smooth_mm=0.0,
                                    consistency_radius_mm=0.0)
    # analytic: from the exact bone point along the exact radial normal u, |b + t u| = R
    u = c.bone_point - centre
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    b = centre + r_bone * u
    bu = np.einsum("ij,ij->i", b, u)
    t_true = -bu + np.sqrt(bu**2 - np.einsum("ij,ij->i", b, b) + r_skin**2)
    # tessellation of both spheres plus a 0.1 degree normal error over <= 30 mm
    tol = sagitta(skin) + sagitta(bone) + 30.0 * np.radians(0.1)
    assert np.abs(c.thickness - t_true).max() <= tol, np.abs(c.thickness - t_true).max()
    assert c.thickness.max() - c.thickness.min() > 15.0  # really direction dependent (~10 to ~28 mm)
    assert c.coverage > 0.9


def test_bone_facing_away_is_rejected():
    skin = sphere(100.0, 4)
    full = sphere(90.0, 4, seed=3)
    # an open bowl: the upper half of the inner sphere. Rays from the lower skin cross the centre and
    # reach the bowl from inside, where its outward normal faces away from their skin normal.
    bowl = full.submesh([np.flatnonzero(full.triangles_center[:, 2] > 0)], append=True)
    for mesh in (bowl, trimesh.Trimesh(bowl.vertices, bowl.faces[:, ::-1], process=False)):
        c = compute_anatomy_constraints(skin, [mesh], max_thickness=1000.0)
        assert np.all(c.skin_point[:, 2] > -1.0)  # none from the lower half
        assert np.all(c.thickness < 11.0)
        assert c.coverage > 0.35  # about half the sphere minus the rim
    # trusting inverted normals rejects everything
    inverted = trimesh.Trimesh(full.vertices, full.faces[:, ::-1], process=False)
    with pytest.raises(CaptureError, match="do not underlie"):
        compute_anatomy_constraints(skin, [inverted], orient_bones=False)
    # ...and the orientation repair (watertight: signed volume) accepts it again
    assert compute_anatomy_constraints(skin, [inverted]).coverage > 0.9


def test_bone_labels_follow_the_order_given():
    skin = sphere(100.0, 4)
    full = sphere(90.0, 4, seed=4)
    up = full.submesh([np.flatnonzero(full.triangles_center[:, 2] > 0)], append=True)
    down = full.submesh([np.flatnonzero(full.triangles_center[:, 2] <= 0)], append=True)
    c = compute_anatomy_constraints(skin, [up, down])
    z = c.bone_point[:, 2]
    assert np.all(c.bone_label[z > 1.0] == 0) and np.all(c.bone_label[z < -1.0] == 1)
    assert set(np.unique(c.bone_label)) == {0, 1}


def test_thickness_limit_and_trusted_mask():
    skin = sphere(100.0, 4)
    bone = sphere(60.0, 4, seed=5)  # 40 mm deep
    with pytest.raises(CaptureError, match="do not underlie"):
        compute_anatomy_constraints(skin, [bone], max_thickness=30.0)
    assert compute_anatomy_constraints(skin, [bone], max_thickness=45.0).coverage > 0.9
    trusted = skin.vertices[:, 0] > 50.0
    c = compute_anatomy_constraints(skin, [sphere(90.0, 4, seed=5)], trusted=trusted)
    assert c.n_candidates == trusted.sum()
    assert np.all(c.skin_point[:, 0] > 45.0)
    assert 0.8 * trusted.sum() <= len(c) <= trusted.sum()
    with pytest.raises(CaptureError, match="boolean mask"):
        compute_anatomy_constraints(skin, [bone], trusted=np.ones(5, bool))


def test_bones_outside_the_skin_raise():
    skin = sphere(100.0, 3)
    far = sphere(90.0, 3, centre=(500.0, 0.0, 0.0))
    with pytest.raises(CaptureError, match="do not underlie the skin"):
        compute_anatomy_constraints(skin, [far])
    with pytest.raises(CaptureError, match="no bone mesh"):
        compute_anatomy_constraints(skin, [])


def test_nan_inputs_raise():
    skin = sphere(100.0, 3)
    bone = sphere(90.0, 3)
    bad = skin.copy()
    bad.vertices[7] = np.nan
    with pytest.raises(CaptureError, match="NaN"):
        compute_anatomy_constraints(bad, [bone])
    bad_bone = bone.copy()
    bad_bone.vertices[3, 1] = np.nan
    with pytest.raises(CaptureError, match="NaN"):
        compute_anatomy_constraints(skin, [bad_bone])


def test_occluding_skin_blocks_the_inward_ray():
    # an air pocket inside the tissue (like a nostril): a small sphere whose normals face the air
    outer = sphere(100.0, 4)
    pocket = sphere(8.0, 3, centre=(0.0, 0.0, 88.0))
    pocket = trimesh.Trimesh(pocket.vertices, pocket.faces[:, ::-1], process=False)
    skin = trimesh.util.concatenate([outer, pocket])
    bone = sphere(70.0, 4, seed=7)
    v = skin.vertices
    top = np.arange(len(v)) < len(outer.vertices)
    top &= v[:, 2] > 100.0 * np.cos(np.radians(4.0))  # outer vertices right above the pocket (5.2 deg)
    assert top.sum() >= 3
    # their inward rays cross the pocket's air before reaching the bone: no constraint
    with pytest.raises(CaptureError, match="do not underlie"):
        compute_anatomy_constraints(skin, [bone], trusted=top, max_thickness=40.0)
    # without the check they would pass (the back ray then lands on the pocket floor)
    c = compute_anatomy_constraints(skin, [bone], trusted=top, max_thickness=40.0, check_occlusion=False)
    assert len(c) > 0 and np.all(c.skin_point[:, 2] < 90.0)  # 80: the pocket floor
    # the pocket floor itself (tissue between pocket and bone) is a valid constraint
    c_all = compute_anatomy_constraints(skin, [bone])
    assert np.any(np.abs(np.linalg.norm(c_all.skin_point - (0, 0, 88.0), axis=1) - 8.0) < 0.5)


def test_round_trip_through_arrays_and_npz():
    c = compute_anatomy_constraints(sphere(100.0, 3), [sphere(90.0, 3, seed=8)])
    buf = io.BytesIO()
    np.savez(buf, **c.to_arrays())
    buf.seek(0)
    with np.load(buf, allow_pickle=False) as z:
        back = AnatomyConstraints.from_arrays(dict(z))
    for name in ("face_index", "barycentric", "skin_point", "bone_point", "thickness", "bone_normal", "bone_label"):
        np.testing.assert_array_equal(getattr(back, name), getattr(c, name))
        assert getattr(back, name).dtype == getattr(c, name).dtype
    assert back.n_vertices == c.n_vertices and back.coverage == c.coverage
    with pytest.raises(CaptureError, match="missing"):
        AnatomyConstraints.from_arrays({"face_index": c.face_index})


def test_triangle_backend_fallback_agrees_with_embree(monkeypatch):
    skin = sphere(100.0, 2)
    bone = sphere(92.0, 2, centre=(3.0, 0.0, 0.0), seed=9)
    fast = compute_anatomy_constraints(skin, [bone])
    monkeypatch.setitem(sys.modules, "trimesh.ray.ray_pyembree", None)  # import now fails
    with pytest.warns(RuntimeWarning, match="embreex"):
        make_ray_intersector(skin)
    with pytest.warns(RuntimeWarning):
        slow = compute_anatomy_constraints(skin, [bone])
    assert len(slow) == len(fast)
    np.testing.assert_allclose(slow.thickness, fast.thickness, atol=1e-4)
    np.testing.assert_array_equal(slow.face_index, fast.face_index)


def test_default_trusted_region_drops_boundary_band():
    full = sphere(100.0, 4)
    cap = full.submesh([np.flatnonzero(full.triangles_center[:, 2] > 0)], append=True)
    tr = default_trusted_region(cap, boundary_margin_mm=15.0)
    z = cap.vertices[:, 2]
    # the boundary is the equator (z = 0); 15 mm of arc ~ z < 15
    assert not tr[z < 5.0].any()
    assert tr[z > 20.0].all()
    assert default_trusted_region(full).all()  # closed: no boundary


@pytest.mark.skipif(
    not all((SAMPLE / f).exists() for f in ("shapes/neutral.ply", "bones/skull.ply", "bones/jaw.ply")),
    reason="sample actor (capture/data/sample_actor) not generated yet",
)
def test_sample_actor_constraints():
    skin = trimesh.load(SAMPLE / "shapes" / "neutral.ply", process=False)
    skull = trimesh.load(SAMPLE / "bones" / "skull.ply", process=False)
    jaw = trimesh.load(SAMPLE / "bones" / "jaw.ply", process=False)
    c = compute_anatomy_constraints(skin, [skull, jaw], trusted=default_trusted_region(skin))
    assert 0.03 < c.coverage < 0.6
    assert 2.0 < np.median(c.thickness) < 15.0  # adult facial soft tissue is ~3-20 mm
    assert c.thickness.max() <= 30.0 + 1e-6
    assert set(np.unique(c.bone_label)) == {0, 1}  # both skull and jaw carry constraints


def test_smoothing_removes_normal_flicker_and_keeps_targets_consistent():
    from models.anatomy_constraints import smooth_constraint_fields

    rng = np.random.default_rng(0)
    skin = sphere(100.0, 4)
    pts = np.asarray(skin.vertices)
    radial = pts / np.linalg.norm(pts, axis=1, keepdims=True)
    noisy = radial + rng.normal(scale=0.05, size=pts.shape)  # ~3 degrees of flicker
    noisy /= np.linalg.norm(noisy, axis=1, keepdims=True)
    thick = 10.0 + rng.normal(scale=0.5, size=len(pts))
    d, n = smooth_constraint_fields(pts, thick, noisy, sigma_mm=6.0)
    ang = lambda a: np.degrees(np.arccos(np.clip((a * radial).sum(1), -1, 1)))
    assert ang(n).mean() < 0.5 * ang(noisy).mean()
    assert np.abs(d - 10.0).mean() < 0.5 * np.abs(thick - 10.0).mean()
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)


def test_consistency_filter_drops_a_layer_jump():
    from models.anatomy_constraints import consistent_constraints

    xs, ys = np.meshgrid(np.arange(0, 30.0, 1.5), np.arange(0, 30.0, 1.5))
    pts = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], 1)
    thick = 5.0 + 0.02 * pts[:, 0]            # a gently varying thickness passes
    thick[50] += 8.0                           # one ray that hit a deeper layer
    keep = consistent_constraints(pts, thick, radius_mm=6.0, max_jump_mm=2.0)
    assert not keep[50] and keep.sum() == len(pts) - 1
