"""The per-point coefficient field of 2D fits (models/fit_field.py) against references."""

from dataclasses import replace

import numpy as np
import torch

from calib.projection import project_points
from models.banded import solve_block_tridiagonal
from models.fit import FitSettings, Observations, SequenceFit, fitting_losses
from models.fit_field import (
    _FieldProblem,
    farthest_points,
    field_energy,
    rbf_basis,
    solve_field,
)
from tests.test_fit import DIST, K, toy_actor, truth


def test_block_tridiagonal_matches_a_dense_solve():
    g = torch.Generator().manual_seed(0)
    J, m = 5, 7
    A = torch.zeros(J * m, J * m, dtype=torch.float64)
    D = torch.empty(J, m, m, dtype=torch.float64)
    U = torch.randn(J - 1, m, m, generator=g, dtype=torch.float64)
    for j in range(J):
        X = torch.randn(m, m, generator=g, dtype=torch.float64)
        D[j] = X @ X.T + 3 * m * torch.eye(m, dtype=torch.float64)   # diagonally dominant: SPD
        A[j * m:(j + 1) * m, j * m:(j + 1) * m] = D[j]
    for j in range(J - 1):
        A[j * m:(j + 1) * m, (j + 1) * m:(j + 2) * m] = U[j]
        A[(j + 1) * m:(j + 2) * m, j * m:(j + 1) * m] = U[j].T
    b = torch.randn(J, m, generator=g, dtype=torch.float64)
    x = solve_block_tridiagonal(D, U, b)
    torch.testing.assert_close(x.reshape(-1), torch.linalg.solve(A, b.reshape(-1)), rtol=1e-9, atol=1e-10)
    D[2] = -D[2]
    assert solve_block_tridiagonal(D, U, b) is None      # not positive definite: reported, not garbage


def test_rbf_basis_is_normalised_gaussians():
    pts = torch.randn(50, 3, dtype=torch.float64) * 30
    c = farthest_points(pts, 6)
    phi = rbf_basis(pts, c, 12.0)
    d2 = ((pts[:, None] - c[None]) ** 2).sum(-1).numpy()
    ref = np.exp(-d2 / (2 * 12.0 ** 2))
    np.testing.assert_allclose(phi.numpy(), ref / ref.sum(1, keepdims=True), rtol=1e-9)
    # farthest points: every centre is a point, the second is the farthest from the first
    assert all(bool((pts == ci).all(1).any()) for ci in c)
    assert int(torch.argmax(((pts - c[0]) ** 2).sum(1))) == int(torch.nonzero((pts == c[1]).all(1))[0])


def _problem(field_weight=0.3, temporal=0.7):
    actor = toy_actor(P=40, E=3, seed=1)
    head_R, head_t, face = truth(toy_actor(P=40, E=4, seed=1), J=4)
    s = FitSettings(code_dim=4, hidden=8, field_centres=5, field_sigma_mm=40.0, field_weight=field_weight,
                    field_temporal_weight=temporal, field_motion_weight=0.4 * temporal, coeff_weight=0.2,
                    coeff_temporal_weight=0.5, robust_px=2.0)
    fit = SequenceFit(4, 3, s, head_R, head_t).double()
    obs = Observations(points2d=project_points(face, K, DIST), weights=torch.rand(4, 40, dtype=torch.float64),
                       K=K, dist=DIST)
    with torch.no_grad():
        fit.field_centres.copy_(farthest_points(actor.points, 5))
        fit.field.copy_(0.1 * torch.randn(4, 5, 3, dtype=torch.float64))
        fit.coeff0.copy_(0.2 * torch.randn(4, 3, dtype=torch.float64))
    return fit, actor, obs


def test_field_energy_and_gradient_match_the_fitting_energy():
    fit, actor, obs = _problem()
    prob = _FieldProblem(fit, actor, obs)
    a = fit.field.detach().clone().requires_grad_(True)
    e = field_energy(prob, a)
    # the same energy through the fitter's own terms (fitting_losses) plus the field's own priors
    s = fit.settings
    with torch.no_grad():
        terms = fitting_losses(fit, actor, obs)
    d = torch.einsum("pb,jbe,pec->jpc", fit.field_basis(actor.points), fit.field, actor.expressions)  # field's motion
    ref = (terms["2d"] + terms["coeff"] + terms["coeff_temporal"] + s.field_weight * fit.field.square().mean()
           + s.field_temporal_weight * (fit.field[1:] - fit.field[:-1]).square().sum((-1, -2)).mean()
           + s.field_motion_weight * (d / s.length_unit_mm).square().sum(-1).mean())
    torch.testing.assert_close(e.detach(), ref, rtol=1e-9, atol=1e-12)
    grad, = torch.autograd.grad(e, a)
    _, _, g = prob.normal_equations(a.detach())
    # J^T r is half the exact gradient (IRLS weights included)
    torch.testing.assert_close(2 * g.reshape(grad.shape), grad, rtol=1e-6, atol=1e-9)


def test_field_solve_recovers_a_field_it_can_represent():
    fit, actor, obs = _problem(field_weight=0.0, temporal=0.0)
    s = replace(fit.settings, coeff_weight=0.0, coeff_temporal_weight=0.0, robust_px=0.0, lm_tol=1e-12)
    truth_fit = SequenceFit(4, 3, s, fit.head_R0, fit.head_t0).double()
    truth_fit.load_state_dict(fit.state_dict())
    with torch.no_grad():
        truth_fit.field.copy_(0.3 * torch.randn(4, 5, 3, dtype=torch.float64))
        face = truth_fit.coefficients(actor)
        pose = truth_fit.poses()
        from models.fit import pose_face
        uv = project_points(pose_face(actor, pose.head_R, pose.head_t, pose.jaw_R, pose.jaw_t, face), K, DIST)
    start = SequenceFit(4, 3, s, fit.head_R0, fit.head_t0).double()
    start.load_state_dict(fit.state_dict())
    with torch.no_grad():
        start.field.zero_()
    obs = Observations(points2d=uv, weights=torch.ones(4, 40, dtype=torch.float64), K=K, dist=DIST)
    solve_field(start, actor, obs, 20)
    torch.testing.assert_close(start.field, truth_fit.field, rtol=0, atol=1e-6)


def test_jaw_prior_towards_the_expressions_jaw():
    """``jaw_of``: the learned jaw transforms blended by the coefficients (scipy's rotation vectors); the
    Levenberg-Marquardt energy with that target equals the fitter's energy at the base."""
    from scipy.spatial.transform import Rotation

    from models.fit_lm import _Problem

    actor = toy_actor(P=30, E=3, seed=2)
    rv = np.array([[0.2, 0.0, 0.01], [0.0, 0.05, -0.1], [0.03, 0.02, 0.0]])
    tt = torch.tensor([[0.0, -2.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.5, 0.5]], dtype=torch.float64)
    from models.fit import ActorAtPoints
    jaw_actor = ActorAtPoints(**{**actor.__dict__, "jaw_rotvec": torch.as_tensor(rv), "jaw_shift": tt})
    w = torch.tensor([[0.5, 0.2, 0.0], [1.0, -0.3, 0.4]], dtype=torch.float64)
    R, t = jaw_actor.jaw_of(w)
    np.testing.assert_allclose(R.numpy(), Rotation.from_rotvec(w.numpy() @ rv).as_matrix(), atol=1e-12)
    torch.testing.assert_close(t, w @ tt)
    head_R, head_t, face = truth(toy_actor(P=30, E=4, seed=2), J=3)
    s = FitSettings(code_dim=4, hidden=8, jaw_prior_weight=0.7, jaw_prior_target="expressions")
    fit = SequenceFit(3, 3, s, head_R, head_t).double()
    with torch.no_grad():
        fit.coeff0.copy_(0.3 * torch.randn(3, 3, dtype=torch.float64))
        fit.jaw_R0.copy_(torch.as_tensor(Rotation.from_rotvec([[0.1, 0, 0]] * 3).as_matrix()))
    obs = Observations(points2d=project_points(face, K, DIST), weights=torch.ones(3, 30, dtype=torch.float64), K=K,
                       dist=DIST)
    with torch.no_grad():
        terms = fitting_losses(fit, jaw_actor, obs)
    ref = float(terms["total"] - terms["temporal"])
    assert abs(_Problem(fit, jaw_actor, obs).energy() - ref) < 1e-9 * abs(ref)
    assert float(terms["jaw"]) > 0


def test_independent_and_shared_blocks_match_a_dense_solve():
    """U None: frames independent; D (1, m, m): one matrix for every frame (the 3D fits' case)."""
    g = torch.Generator().manual_seed(3)
    J, m = 4, 6
    X = torch.randn(m, m, generator=g, dtype=torch.float64)
    D1 = X @ X.T + m * torch.eye(m, dtype=torch.float64)
    b = torch.randn(J, m, generator=g, dtype=torch.float64)
    ref = torch.linalg.solve(D1, b.T).T
    torch.testing.assert_close(solve_block_tridiagonal(D1[None], None, b), ref, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(solve_block_tridiagonal(D1.expand(J, m, m).clone(), None, b), ref, rtol=1e-10,
                               atol=1e-12)


def _problem_3d(field_weight=0.3):
    actor = toy_actor(P=40, E=3, seed=4)
    head_R, head_t, face = truth(toy_actor(P=40, E=4, seed=4), J=4)
    s = FitSettings(code_dim=4, hidden=8, field_centres=5, field_sigma_mm=40.0, field_weight=field_weight,
                    coeff_weight=0.2, field_iterations=3)
    fit = SequenceFit(4, 3, s, head_R, head_t).double()
    with torch.no_grad():
        fit.field_centres.copy_(farthest_points(actor.points, 5))
        fit.field.copy_(0.1 * torch.randn(4, 5, 3, dtype=torch.float64))
        fit.coeff0.copy_(0.2 * torch.randn(4, 3, dtype=torch.float64))
    return fit, actor, Observations(points3d=face)


def test_field_energy_and_gradient_with_3d_points():
    """The field's energy on 3D points equals the fitter's (3D position + coefficient terms + the field's
    prior), and its Gauss-Newton gradient is half autograd's; the matrix is one for all frames."""
    fit, actor, obs = _problem_3d()
    prob = _FieldProblem(fit, actor, obs)
    assert prob.constant_hessian
    a = fit.field.detach().clone().requires_grad_(True)
    e = field_energy(prob, a)
    with torch.no_grad():
        terms = fitting_losses(fit, actor, obs)
    ref = terms["3d"] + terms["coeff"] + fit.settings.field_weight * fit.field.square().mean()
    torch.testing.assert_close(e.detach(), ref, rtol=1e-9, atol=1e-12)
    grad, = torch.autograd.grad(e, a)
    D, U, g = prob.normal_equations(a.detach())
    assert D.shape[0] == 1 and U is None
    torch.testing.assert_close(2 * g.reshape(grad.shape), grad, rtol=1e-6, atol=1e-9)
    torch.testing.assert_close(prob.normal_equations(a.detach(), hessian=False)[2], g)


def test_field_solve_recovers_a_field_from_3d_points():
    fit, actor, _ = _problem_3d(field_weight=0.0)
    s = replace(fit.settings, coeff_weight=0.0, lm_tol=1e-14, field_iterations=30)
    truth_fit = SequenceFit(4, 3, s, fit.head_R0, fit.head_t0).double()
    truth_fit.load_state_dict(fit.state_dict())
    with torch.no_grad():
        truth_fit.field.copy_(0.3 * torch.randn(4, 5, 3, dtype=torch.float64))
        pose = truth_fit.poses()
        from models.fit import pose_face
        face = pose_face(actor, pose.head_R, pose.head_t, pose.jaw_R, pose.jaw_t, truth_fit.coefficients(actor))
    start = SequenceFit(4, 3, s, fit.head_R0, fit.head_t0).double()
    start.load_state_dict(fit.state_dict())
    with torch.no_grad():
        start.field.zero_()
    solve_field(start, actor, Observations(points3d=face), 30)
    torch.testing.assert_close(start.field, truth_fit.field, rtol=0, atol=1e-6)
