"""Each learning loss on a case whose value is known by hand."""


import pytest
import torch

from models.losses import (anatomy_losses, skin_position_loss, skinning_weight_loss, symmetry_loss,
                           thickness_regularizer)


def test_skin_position_loss_known_value():
    target = torch.zeros(2, 4, 3)
    pred = target.clone()
    pred[0, 0] = torch.tensor([3.0, 4.0, 0.0])  # one point 5 mm off: 25 mm^2 over 8 points
    assert skin_position_loss(pred, target, unit=1.0).item() == pytest.approx(25 / 8)
    # In centimetre units the same residual is 0.5 cm: 0.25 cm^2 / 8.
    assert skin_position_loss(pred, target, unit=10.0).item() == pytest.approx(0.25 / 8)


def test_anatomy_losses_known_values_and_empty_set():
    bone = torch.tensor([[1.0, 0, 0], [0, 0, 0]])
    bone_t = torch.zeros(2, 3)
    d, d_t = torch.tensor([5.0, 7.0]), torch.tensor([5.0, 5.0])
    n = torch.tensor([[0.0, 0, 1], [0, 1.0, 0]])
    n_t = torch.tensor([[0.0, 0, 1], [0, 0, 1.0]])  # second normal 90 degrees off: |a-b|^2 = 2
    lb, ld, ln = anatomy_losses(bone, d, n, bone_t, d_t, n_t, unit=1.0)
    assert (lb.item(), ld.item(), ln.item()) == pytest.approx((0.5, 2.0, 1.0))
    empty = torch.zeros(0, 3)
    zeros = anatomy_losses(empty, torch.zeros(0), empty, empty, torch.zeros(0), empty, unit=1.0)
    assert all(z.item() == 0.0 for z in zeros)


def test_anatomy_losses_reject_mismatched_counts():
    with pytest.raises(ValueError, match="M=2"):
        anatomy_losses(torch.zeros(2, 3), torch.zeros(3), torch.zeros(2, 3), torch.zeros(2, 3),
                       torch.zeros(2), torch.zeros(2, 3), unit=1.0)


def test_thickness_symmetry_and_skinning_losses():
    assert thickness_regularizer(torch.tensor([10.0, 0.0]), unit=10.0).item() == pytest.approx(0.5)
    a = torch.tensor([[1.0, 2.0, 2.0]])
    assert symmetry_loss(a, torch.zeros(1, 3), unit=1.0).item() == pytest.approx(9.0)
    assert skinning_weight_loss(torch.tensor([0.5, -0.5, 0.0, 0.0])).item() == pytest.approx(0.125)
    assert skinning_weight_loss(torch.zeros(0)).item() == 0.0


def test_symmetry_loss_is_zero_for_a_mirror_symmetric_bone_map():
    # B(c) = c + (0, 0, |x|) is symmetric about x = 0: B(R c) = R B(c).
    def B(c):
        return c + torch.stack([torch.zeros_like(c[:, 0]), torch.zeros_like(c[:, 0]), c[:, 0].abs()], -1)

    def R(c):
        return c * torch.tensor([-1.0, 1.0, 1.0])

    c = torch.randn(100, 3)
    assert symmetry_loss(B(R(c)), R(B(c)), unit=1.0).item() == pytest.approx(0.0, abs=1e-12)
    # An asymmetric map B(c) = c + (0, 0, x) gives ||(0,0,-x) - (0,0,x)||^2 = 4 x^2.
    def B2(c):
        return c + torch.stack([torch.zeros_like(c[:, 0]), torch.zeros_like(c[:, 0]), c[:, 0]], -1)

    expected = (4 * c[:, 0] ** 2).mean().item()
    assert symmetry_loss(B2(R(c)), R(B2(c)), unit=1.0).item() == pytest.approx(expected, rel=1e-5)
