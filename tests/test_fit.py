"""The sequence fit: float64 gradient check of the fitting energy, and known answers in 3D and 2D."""

from dataclasses import replace

import pytest
import torch
from scipy.spatial.transform import Rotation

from models.fit import (ActorAtPoints, FitSettings, Observations, SequenceFit, fit_sequence, fitting_losses,
                        pose_face)

K = torch.tensor([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]], dtype=torch.float64)
DIST = torch.tensor([-0.1, 0.02, 0.001, -0.001, 0.0], dtype=torch.float64)


def toy_actor(P=150, E=4, seed=0) -> ActorAtPoints:
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(P, 3, generator=g, dtype=torch.float64) * torch.tensor([60.0, 80.0, 40.0], dtype=torch.float64)
    k = torch.sigmoid(-(pts[:, 1] + 30) / 10)  # the lower face follows the jaw
    expr = torch.randn(P, E, 3, generator=g, dtype=torch.float64) * 3.0
    return ActorAtPoints(points=pts, neutral=pts.clone(), skin_weight=k, expressions=expr,
                         jaw_pivot=torch.tensor([0.0, 10.0, -60.0], dtype=torch.float64),
                         center=torch.zeros(3, dtype=torch.float64), scale=100.0)


def truth(actor, J=4):
    yaw = torch.linspace(-0.3, 0.3, J, dtype=torch.float64)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # face the camera
    head_R = torch.stack([flip @ torch.tensor(Rotation.from_euler("y", float(a)).as_matrix()) for a in yaw])
    head_t = torch.tensor([[5.0, -3.0, 600.0]], dtype=torch.float64).expand(J, 3) + torch.arange(J)[:, None] * 2.0
    jaw_R = torch.stack([torch.tensor(Rotation.from_euler("x", 0.05 * j).as_matrix()) for j in range(J)])
    jaw_t = torch.zeros(J, 3, dtype=torch.float64)
    w = torch.linspace(0, 0.6, J, dtype=torch.float64)[:, None, None] * torch.tensor([1.0, -0.5, 0.3, 0.0], dtype=torch.float64)
    w = w.expand(J, actor.points.shape[0], 4)
    return head_R, head_t, pose_face(actor, head_R, head_t, jaw_R, jaw_t, w)


def test_fitting_energy_gradcheck_float64():
    torch.manual_seed(0)
    actor = toy_actor(P=12, E=2)
    head_R, head_t, face = truth(toy_actor(P=12, E=4), J=3)
    s = FitSettings(code_dim=4, hidden=8)
    fit = SequenceFit(3, 2, s, head_R, head_t).double()
    obs = Observations(points2d=face.new_zeros(3, 12, 2) + 300.0, weights=torch.rand(3, 12, dtype=torch.float64),
                       K=K, dist=DIST, points3d=face + 1.0)
    with torch.no_grad():  # a non-degenerate point: non-zero outputs of both MLPs
        for p in fit.parameters():
            p.add_(0.05 * torch.randn_like(p))

    codes = fit.codes.detach().clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda c: _energy_with(fit, actor, obs, c), (codes,), eps=1e-6, atol=1e-5)


def _energy_with(fit, actor, obs, codes):
    """The fitting energy as a function of the frame codes (swapped in for the parameter)."""
    saved = fit.codes
    del fit.codes
    fit.codes = codes
    try:
        return fitting_losses(fit, actor, obs)["total"]
    finally:
        del fit.codes
        fit.codes = saved


def test_3d_fit_reaches_the_truth():
    torch.manual_seed(0)
    actor = toy_actor()
    head_R, head_t, face = truth(actor)
    # start 5 degrees and 10 mm away from the true head pose
    R0 = head_R @ torch.tensor(Rotation.from_euler("xy", [0.05, -0.05]).as_matrix())
    s = FitSettings(iterations=600, lr=1e-2, robust_px=0.0, coeff_weight=1e-6)
    res = fit_sequence(actor, Observations(points3d=face), s, R0, head_t + 10.0)
    with torch.no_grad():
        pose = res.fit.poses()
        pred = pose_face(actor, pose.head_R, pose.head_t, pose.jaw_R, pose.jaw_t, res.fit.coefficients(actor))
    err = (pred - face).norm(dim=-1)
    # Expression offsets reach 5 mm and the head starts 10 mm off; 0.1 mm is 1 % of that.
    assert err.mean() < 0.1, err.mean()


def test_2d_fit_reprojects_the_truth():
    torch.manual_seed(0)
    actor = toy_actor()
    head_R, head_t, face = truth(actor)
    from calib.projection import project_points

    uv = project_points(face, K, DIST)
    s = FitSettings(iterations=600, lr=1e-2, coeff_weight=1e-6)
    res = fit_sequence(actor, Observations(points2d=uv, K=K, dist=DIST), s, head_R, head_t + torch.tensor([0, 0, 20.0], dtype=torch.float64))
    with torch.no_grad():
        pose = res.fit.poses()
        pred = pose_face(actor, pose.head_R, pose.head_t, pose.jaw_R, pose.jaw_t, res.fit.coefficients(actor))
        rms = (project_points(pred, K, DIST) - uv).square().sum(-1).mean().sqrt()
    assert rms < 0.1, rms  # pixels: noise-free landmarks are matched to a tenth of a pixel


def test_split_first_layer_equals_concatenated_input():
    """F_W's first layer is evaluated per frame and per point separately: same as on [z_j, c]."""
    actor = toy_actor(P=20, E=3)
    head_R, head_t, _ = truth(toy_actor(P=20, E=4), J=3)
    fit = SequenceFit(3, 3, FitSettings(code_dim=5, hidden=16), head_R, head_t).double()
    with torch.no_grad():
        for p in fit.parameters():
            p.add_(0.1 * torch.randn_like(p))
        x = (actor.points - actor.center) / actor.scale
        inp = torch.cat([fit.codes[:, None].expand(3, 20, -1), x[None].expand(3, 20, 3)], -1)
        torch.testing.assert_close(fit.coefficients(actor), fit.F_W(inp))
        torch.testing.assert_close(fit.coefficients(actor, frames=slice(1, 2)), fit.F_W(inp[1:2]))


def test_early_stop_and_iteration_override():
    actor = toy_actor(P=30, E=2)
    head_R, head_t, face = truth(toy_actor(P=30, E=4), J=2)
    s = FitSettings(code_dim=4, hidden=8, iterations=1000, early_stop_tol=0.5, early_stop_every=10)
    res = fit_sequence(actor, Observations(points3d=face), s, head_R, head_t)
    assert 20 <= len(res.losses) < 1000  # stopped once the loss stopped halving per 10 iterations
    res = fit_sequence(actor, Observations(points3d=face), replace(s, early_stop_tol=0.0), head_R, head_t,
                       iterations=7)
    assert len(res.losses) == 7
