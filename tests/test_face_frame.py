"""Tests of models.face_frame on a synthetic face with known axes (and the sample actor)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from capture.io.errors import CaptureError
from tests.synthetic_face import synthetic_face
from models.face_frame import (
    FaceFrame,
    estimate_face_frame,
    estimate_jaw_pivot,
    forehead_region,
    midline_landmarks,
    plane_from_user,
)

SAMPLE = Path(__file__).resolve().parents[1] / "capture" / "data" / "sample_actor"


def angle_deg(a, b) -> float:
    return float(np.degrees(np.arccos(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def crop_right_side(v, f, x_min):
    """Drop faces on the face's right beyond x_min (an asymmetric crop, as scans often are)."""
    keep = np.all(v[f][:, :, 0] > x_min, axis=1)
    return trimesh.Trimesh(v, f[keep], process=True)  # process drops the unused vertices


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_frame_recovered_after_a_known_rotation(seed):
    v, f = synthetic_face(noise=0.2, seed=seed)
    mesh = crop_right_side(v, f, -55.0)  # the left side reaches 75 mm, the right only 55
    rot = Rotation.random(random_state=seed).as_matrix()
    shift = np.array([12.0, -30.0, 400.0])
    vr = mesh.vertices @ rot.T + shift
    fr = estimate_face_frame(vr, mesh.faces)
    ex, ey, ez = rot[:, 0], rot[:, 1], rot[:, 2]
    assert angle_deg(fr.symmetry_normal, ex) < 1.0  # also checks the sign: the face's left
    # the plane passes through the rotated x = 0 plane: offset = shift . ex
    assert abs(fr.symmetry_offset - shift @ ex) < 1.0
    # the mean normal of this mask tilts ~4 degrees upward (forehead > chin), so allow 8
    assert angle_deg(fr.up, ey) < 8.0
    assert angle_deg(fr.forward, ez) < 8.0
    np.testing.assert_allclose(np.cross(fr.up, fr.forward), fr.symmetry_normal, atol=1e-9)


def test_reflect_is_an_involution_and_maps_the_face_onto_itself():
    v, f = synthetic_face(noise=0.1)
    rot = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    vr = v @ rot.T
    fr = estimate_face_frame(vr, f)
    pts = np.random.default_rng(0).normal(size=(4, 5, 3)) * 50
    np.testing.assert_allclose(fr.reflect(fr.reflect(pts)), pts, atol=1e-9)
    assert fr.reflect(pts).shape == pts.shape
    d, _ = cKDTree(vr).query(fr.reflect(vr))
    assert np.median(d) < 1.0  # grid spacing is ~2-3 mm
    # points on the plane are fixed
    on = vr - fr.signed_distance(vr)[:, None] * fr.symmetry_normal
    np.testing.assert_allclose(fr.reflect(on), on, atol=1e-9)


def test_landmarks_forehead_and_upside_down():
    v, f = synthetic_face()
    fr = estimate_face_frame(v, f)
    lm = midline_landmarks(v, fr)
    assert np.linalg.norm(lm.nose_tip - [0.0, 0.0, 117.0]) < 3.0
    assert lm.nasion_found and 35.0 < lm.nasion[1] < 52.0
    fh = forehead_region(v, f, fr)
    assert fh.sum() > 200
    assert v[fh, 1].min() > lm.nasion[1] + 15.0  # above the brows
    assert v[fh, 1].min() > 50.0
    # symmetric: the mirror image of the region is (almost) the region
    assert abs(int((v[fh, 0] > 0).sum()) - int((v[fh, 0] < 0).sum())) < 0.05 * fh.sum()
    # the same face upside down: up follows the forehead, not the world
    flip = Rotation.from_euler("z", 180, degrees=True).as_matrix()
    fr2 = estimate_face_frame(v @ flip.T, f)
    assert angle_deg(fr2.up, [0, -1, 0]) < 8.0
    fh2 = forehead_region(v @ flip.T, f, fr2)
    assert (fh2 == fh).mean() > 0.99


def test_round_trip_and_validation():
    fr = FaceFrame(symmetry_normal=np.array([2.0, 0, 0]), symmetry_offset=1.5, up=[0, 1, 0], forward=[0, 0, 1])
    np.testing.assert_allclose(fr.symmetry_normal, [1, 0, 0])  # normalised
    back = FaceFrame.from_dict(fr.to_dict())
    np.testing.assert_allclose(back.up, fr.up)
    assert back.symmetry_offset == 1.5
    with pytest.raises(CaptureError, match="unknown"):
        FaceFrame.from_dict({**fr.to_dict(), "upp": [0, 1, 0]})
    with pytest.raises(CaptureError, match="3 finite"):
        FaceFrame(symmetry_normal=[np.nan, 0, 0], symmetry_offset=0.0, up=[0, 1, 0], forward=[0, 0, 1])


def test_closed_head_and_bad_input_raise():
    ball = trimesh.creation.icosphere(subdivisions=3, radius=100.0)
    with pytest.raises(CaptureError, match="which way"):
        estimate_face_frame(ball.vertices, ball.faces)
    v, f = synthetic_face(n_th=21, n_ph=21)
    v[3] = np.nan
    with pytest.raises(CaptureError, match="NaN"):
        estimate_face_frame(v, f)


def test_plane_from_user_fixes_the_normal_sign():
    v, f = synthetic_face()
    fr = plane_from_user([0.0, 0.0, 0.0], [-1.0, 0.0, 0.0], v, f)  # user gave the right-pointing normal
    np.testing.assert_allclose(fr.symmetry_normal, [1, 0, 0], atol=1e-12)
    assert angle_deg(fr.up, [0, 1, 0]) < 8.0
    fr2 = plane_from_user([5.0, 0, 0], [1, 0, 0], up=[0, 1, 0.1], forward=[0, 0, 1])
    assert fr2.symmetry_offset == 5.0 and abs(fr2.up @ fr2.forward) < 1e-12


def test_jaw_pivot_at_the_condyles():
    v, f = synthetic_face()
    fr = FaceFrame(symmetry_normal=[1, 0, 0], symmetry_offset=0.0, up=[0, 1, 0], forward=[0, 0, 1])
    # a U-shaped jaw of boxes: chin bar in front, two rami going up at the back
    parts = [trimesh.creation.box(extents=[90, 15, 15]).apply_translation([0, -70, 60])]
    for side in (-1, 1):
        parts.append(trimesh.creation.box(extents=[10, 15, 80]).apply_translation([side * 45, -70, 20]))
        parts.append(trimesh.creation.box(extents=[10, 60, 12]).apply_translation([side * 45, -40, -14]))
    jaw = trimesh.util.concatenate(parts)
    for _ in range(4):
        jaw = jaw.subdivide()
    pivot = estimate_jaw_pivot(fr, v, jaw)
    # the rami's top-back corners are at y = -10, z = -20
    assert np.linalg.norm(pivot - [0.0, -10.0, -20.0]) < 4.0
    # without a jaw: on the plane, behind and a little below the nose tip (the axis of a wide opening)
    est = estimate_jaw_pivot(fr, v, None)
    tip = midline_landmarks(v, fr).nose_tip
    assert abs(est[0]) < 1e-9 and est[2] < tip[2] - 80.0 and -40.0 < est[1] - tip[1] < 0.0


def test_sample_actor_frame():
    skin = trimesh.load(SAMPLE / "shapes" / "neutral.ply", process=False)
    fr = estimate_face_frame(skin.vertices, skin.faces)
    # the sample is built in a y-up, z-forward frame and is nearly symmetric about x = 0
    assert angle_deg(fr.symmetry_normal, [1, 0, 0]) < 2.0
    assert abs(fr.symmetry_offset) < 3.0
    assert angle_deg(fr.up, [0, 1, 0]) < 15.0  # the neck tilts the mean normal by ~8 degrees
    assert angle_deg(fr.forward, [0, 0, 1]) < 15.0
    fh = forehead_region(skin.vertices, skin.faces, fr)
    lm = midline_landmarks(skin.vertices, fr)
    assert fh.sum() > 100
    assert np.all(skin.vertices[fh, 1] > lm.nose_tip[1] + 40.0)


def test_closed_lips_tell_up_from_down_where_the_nose_cannot(caplog):
    """ICT's identity B (the committed test actor's template, y up in ICT's frame): its nose profile differs by
    0.53 mm between the two sides, under the 1 mm that decides, and its chin and neck reach farther from the nose
    tip than its forehead, so the mesh's extent would put the forehead at the chin. The closed lips on the midline,
    34 mm from the tip, say which side is down. Without the triangles (no lips to read) the old fallback is
    upside down, which is what the lips correct."""
    from models.face_frame import _up_sign_from_nose

    skin = trimesh.load(Path(__file__).resolve().parent / "data" / "ict_b_actor" / "template.ply", process=False)
    with caplog.at_level("WARNING", logger="models.face_frame"):
        fr = estimate_face_frame(skin.vertices, skin.faces)
    assert angle_deg(fr.up, [0, 1, 0]) < 10.0 and angle_deg(fr.forward, [0, 0, 1]) < 10.0
    assert "closed lips" in caplog.text
    v = np.asarray(skin.vertices, dtype=np.float64)
    up0 = np.cross(fr.forward, fr.symmetry_normal)
    sign, evidence = _up_sign_from_nose(v, fr.symmetry_normal, fr.symmetry_offset, up0, fr.forward, 4.0)
    assert abs(evidence) < 1.0 and sign * up0 @ [0, 1, 0] < 0
