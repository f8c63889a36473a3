"""The jaw read from the shapes' motion (models/jaw_motion.py), against jaws whose truth is known: the tiny
actor's (an LBS turn with known weights and pivot) and the bundled sample's fitted mandible."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from capture.io.errors import CaptureError
from models.face_frame import estimate_face_frame, midline_landmarks
from models.jaw_motion import find_jaw_opening, following, rigid_turn
from tests.tiny_actor import JAW_DEG, JAW_PIVOT, tiny_shapes


@pytest.fixture(scope="module")
def tiny():
    shapes, faces = tiny_shapes()
    names = list(shapes)
    V = np.stack([shapes[n] for n in names])
    frame = estimate_face_frame(V[0], faces)
    y = V[0][:, 1]                                     # the jaw weight tiny_shapes gives jawOpen
    k = np.clip((-30.0 - y) / 25.0, 0.0, 1.0)
    return names, V, frame, midline_landmarks(V[0], frame).nose_tip, k * k * (3 - 2 * k)


def test_rigid_turn_and_following_against_a_known_motion():
    """A rotation and translation applied to random points come back (to float precision); a point moved by a
    share s of that motion reads s."""
    rng = np.random.default_rng(0)
    rest = rng.normal(size=(50, 3)) * 30.0
    R = Rotation.from_rotvec([0.3, -0.1, 0.2]).as_matrix()
    t = np.array([4.0, -2.0, 7.0])
    R2, t2 = rigid_turn(rest, rest @ R.T + t)
    np.testing.assert_allclose(R2, R, atol=1e-10)
    np.testing.assert_allclose(t2, t, atol=1e-8)
    s = rng.uniform(0, 1.2, 50)
    share, reach = following(rest, rest + s[:, None] * (rest @ R.T + t - rest), R, t)
    np.testing.assert_allclose(share, s, atol=1e-9)
    np.testing.assert_allclose(reach, np.linalg.norm(rest @ R.T + t - rest, axis=1))


def test_the_tiny_actors_jaw_is_found_with_its_weights(tiny):
    """jawOpen turns the points below the mouth by 12 degrees about a known pivot, with a smooth weight k. About
    that pivot the opening is jawOpen (not the smile or the brow), a turn of 12 degrees within 0.5 (the points
    that follow by k between 0.5 and 1 are fitted too and pull the least-squares turn down: 11.76), each
    point's share is its weight within 0.05 (the same 2 %), and the jaw is the points with k >= 0.5 (one in
    a hundred may differ at the boundary)."""
    names, V, frame, tip, k = tiny
    o = find_jaw_opening(V[0], V, frame, JAW_PIVOT, tip)
    assert o is not None and names[o.shape] == "jawOpen"
    assert abs(o.angle_deg - JAW_DEG) < 0.5
    assert o.axis @ frame.symmetry_normal > np.cos(np.radians(0.5))
    moving = k > 0.01
    assert np.abs(o.share - k)[moving].max() < 0.05
    assert (o.follows != (k >= 0.5)).mean() < 0.01 and o.follows.sum() > 100


def test_no_opening_no_jaw(tiny):
    """Without the jawOpen shape, or with a jaw that closes (the same turn backwards), no shape opens a jaw."""
    names, V, frame, tip, k = tiny
    without = np.delete(V, names.index("jawOpen"), axis=0)
    assert find_jaw_opening(without[0], without, frame, JAW_PIVOT, tip) is None
    closing = V.copy()
    R = Rotation.from_rotvec(np.radians(-JAW_DEG) * frame.symmetry_normal).as_matrix()
    closing[names.index("jawOpen")] = V[0] + k[:, None] * ((V[0] - JAW_PIVOT) @ R.T + JAW_PIVOT - V[0])
    assert find_jaw_opening(closing[0], closing, frame, JAW_PIVOT, tip) is None


def test_bad_arrays_are_refused(tiny):
    names, V, frame, tip, _ = tiny
    with pytest.raises(CaptureError, match=r"\(N, M, 3\)"):
        find_jaw_opening(V[0], V[:, :10], frame, JAW_PIVOT, tip)
    with pytest.raises(CaptureError, match="lips of each"):
        find_jaw_opening(V[0], V, frame, JAW_PIVOT, tip, lips=[np.zeros((0, 3))])


@pytest.fixture(scope="module")
def sample_prepared():
    """The sample's shapes prepared as `capture actor train` does, with its fitted skull and jaw and without."""
    from capture.actor.sample import sample_bones, sample_shapes_dir
    from capture.actor.training import TrainOptions, prepare
    from capture.io.meshes import load_shape_dir

    skull, jaw = sample_bones()
    out = {}
    for what, bones in (("fitted", dict(skull=skull, jaw=jaw)), ("estimated", {})):
        shapes = load_shape_dir(sample_shapes_dir())
        out[what] = prepare(TrainOptions(actor="x", shapes=sample_shapes_dir(), **bones), shapes, lambda m: None)
    return out


def test_the_samples_jaw_from_motion_agrees_with_its_fitted_mandible(sample_prepared):
    """On the sample, the jaw read from the motion of its scans (no jaw mesh: the estimated bones) is jawOpen, a
    turn of 15-25 degrees about the estimated pivot (its lower teeth turn 24; the skin over them less). Read
    the same way on the points constrained to the fitted bones, it takes 60 % or more of those over the
    mandible and at most 1 % of those over the skull (measured: 93 of 140, and 1 of 1,839)."""
    from capture.actor.training import jaw_from_motion

    data, extras = sample_prepared["estimated"]
    src = extras["jaw_source"]
    assert src["from"] == "motion" and src["shape"] == "jawOpen" and 15.0 <= src["angle_deg"] <= 25.0
    assert data.jaw_points.shape[0] == src["points"] > 100

    _, fitted = sample_prepared["fitted"]
    shapes, con = fitted["shapes"], fitted["constraints"]
    at = np.einsum("mk,nmkc->nmc", con.barycentric, shapes.vertices[:, shapes.faces[con.face_index]])
    on_jaw = con.bone_label == 1
    pivot = extras["jaw_pivot"]                           # the estimate, as without a jaw mesh
    follows, src = jaw_from_motion(shapes, at, fitted["frame"], pivot, lambda m: None)
    assert src["shape"] == "jawOpen"
    assert follows[on_jaw].mean() >= 0.6 and follows[~on_jaw].mean() <= 0.01
