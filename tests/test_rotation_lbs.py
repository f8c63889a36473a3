"""6D rotations and jaw LBS against hand-computed cases and scipy."""


import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from models.lbs import lbs_jaw
from models.rotation import apply_rigid, identity_6d, matrix_to_rot6d, rot6d_to_matrix


def test_rot6d_round_trip_on_random_rotations():
    R = torch.tensor(Rotation.random(200, random_state=0).as_matrix())
    back = rot6d_to_matrix(matrix_to_rot6d(R))
    torch.testing.assert_close(back, R, atol=1e-12, rtol=0)


def test_rot6d_of_arbitrary_vectors_is_a_proper_rotation():
    x = torch.randn(500, 6, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    R = rot6d_to_matrix(x)
    eye = torch.eye(3, dtype=torch.float64).expand(500, 3, 3)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(500, dtype=torch.float64), atol=1e-12, rtol=0)
    # Gram-Schmidt keeps the direction of the first column.
    torch.testing.assert_close(R[:, :, 0], torch.nn.functional.normalize(x[:, :3], dim=-1))


def test_identity_6d_maps_to_identity_and_gradcheck():
    torch.testing.assert_close(rot6d_to_matrix(identity_6d(4)), torch.eye(3).expand(4, 3, 3))
    x = torch.randn(3, 6, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(rot6d_to_matrix, (x,))


def test_shape_errors_name_the_argument():
    with pytest.raises(ValueError, match=r"x: expected shape \(\*,6\), got \(4, 5\)"):
        rot6d_to_matrix(torch.zeros(4, 5))


def test_lbs_hand_computed_case():
    # Jaw rotates 90 degrees about z around pivot (1, 0, 0) and moves by t = (0, 0, 2).
    # Point (2, 0, 0): about the pivot it is (1, 0, 0) -> (0, 1, 0) -> world (1, 1, 0) + t = (1, 1, 2).
    R = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    t = torch.tensor([0.0, 0.0, 2.0])
    pivot = torch.tensor([1.0, 0.0, 0.0])
    pts = torch.tensor([[2.0, 0.0, 0.0], [2.0, 0.0, 0.0], [2.0, 0.0, 0.0]])
    k = torch.tensor([0.0, 1.0, 0.25])
    out = lbs_jaw(pts, k, R, t, pivot)
    expected = torch.tensor([[2.0, 0.0, 0.0], [1.0, 1.0, 2.0], [0.75 * 2 + 0.25 * 1, 0.25, 0.5]])
    torch.testing.assert_close(out, expected)


def test_apply_rigid_matches_scipy_with_batches():
    rots = Rotation.random(5, random_state=3)
    R = torch.tensor(rots.as_matrix())
    t = torch.randn(5, 3, dtype=torch.float64)
    pts = torch.randn(5, 7, 3, dtype=torch.float64)
    out = apply_rigid(pts, R, t)
    ref = np.stack([rots[i].apply(pts[i].numpy()) + t[i].numpy() for i in range(5)])
    np.testing.assert_allclose(out.numpy(), ref, atol=1e-12)


def test_apply_rigid_broadcasts_points_and_pivot_like_scipy():
    """One point set under a batch of rotations, and a batch of batches with a pivot: every item as scipy
    moves it (the product runs over the points' axis, ``R @ points^T``, so its broadcasting is checked here)."""
    rots = Rotation.random(6, random_state=4)
    R = torch.tensor(rots.as_matrix())
    t = torch.randn(6, 3, dtype=torch.float64)
    pivot = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    shared = torch.randn(9, 3, dtype=torch.float64)
    out = apply_rigid(shared, R, t, pivot)
    assert out.shape == (6, 9, 3)
    for i in range(6):
        ref = rots[i].apply(shared.numpy() - pivot.numpy()) + pivot.numpy() + t[i].numpy()
        np.testing.assert_allclose(out[i].numpy(), ref, atol=1e-12)
    pts = torch.randn(2, 3, 9, 3, dtype=torch.float64)
    out = apply_rigid(pts, R.reshape(2, 3, 3, 3), t.reshape(2, 3, 3), pivot)
    for a in range(2):
        for b in range(3):
            ref = rots[3 * a + b].apply(pts[a, b].numpy() - pivot.numpy()) + pivot.numpy() + t[3 * a + b].numpy()
            np.testing.assert_allclose(out[a, b].numpy(), ref, atol=1e-12)
