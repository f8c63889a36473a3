"""The sequence fit: float64 gradient check of the fitting energy, and known answers in 3D and 2D."""

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from models.fit import (ActorAtPoints, FitSettings, Observations, SequenceFit, fit_sequence, fitting_losses,
                        pose_face, pose_face_shared)
from models.fit_state import mesh_basis, shared_pose_maps
from models.mesh_map import map_vertices

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


# ---------------------------------------------------------------------------------------------
# Levenberg-Marquardt on the per-frame base (models.fit_lm)

LM_SETTINGS = FitSettings(code_dim=4, hidden=8, coeff_weight=0.05, temporal_weight=0.1, pose_accel_weight=0.5,
                          coeff_temporal_weight=0.3, jaw_prior_weight=0.2, robust_px=2.0)


def _perturbed_fit(settings, J=4, E=4, seed=0):
    """A float64 fit with non-zero network outputs and a base away from rest."""
    torch.manual_seed(seed)
    head_R, head_t, _ = truth(toy_actor(E=4), J=J)
    fit = SequenceFit(J, E, settings, head_R, head_t + torch.tensor([0.0, 0.0, 15.0], dtype=torch.float64)).double()
    with torch.no_grad():
        for p in fit.parameters():
            p.add_(0.05 * torch.randn_like(p))
        fit.jaw_R0.copy_(torch.tensor(Rotation.from_euler("x", 0.1).as_matrix()))
        fit.jaw_t0.add_(0.5)
        fit.coeff0.add_(0.1 * torch.randn_like(fit.coeff0))
    return fit


def _lm_problem(P=150):
    actor = toy_actor(P=P)
    head_R, head_t, face = truth(actor)
    from calib.projection import project_points

    uv = project_points(face, K, DIST) + 0.3 * torch.randn(face.shape[:2] + (2,), dtype=torch.float64,
                                                           generator=torch.Generator().manual_seed(1))
    uv[0, :5] += 40.0  # a few wild landmarks, for the robust loss
    weights = torch.rand(uv.shape[:2], dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    return actor, Observations(points2d=uv, weights=weights, K=K, dist=DIST)


def test_lm_energy_and_gradient_match_the_fitting_energy():
    """The solver's energy equals fitting_losses (less the constant code term); J^T r is half its gradient."""
    from models.fit_lm import _Problem, so3_exp

    actor, obs = _lm_problem()
    fit = _perturbed_fit(LM_SETTINGS)
    prob = _Problem(fit, actor, obs)
    terms = fitting_losses(fit, actor, obs)
    assert {"2d", "coeff", "pose_accel", "coeff_temporal", "jaw", "temporal"} <= set(terms)
    torch.testing.assert_close(torch.tensor(prob.energy(), dtype=torch.float64),
                               (terms["total"] - terms["temporal"]).detach(), rtol=1e-12, atol=0)
    # the gradient wrt the base update, by autograd through fitting_losses
    d = torch.zeros(fit.codes.shape[0], 12 + fit.coeff0.shape[1], dtype=torch.float64, requires_grad=True)
    base = [fit.head_R0.clone(), fit.head_t0.clone(), fit.jaw_R0.clone(), fit.jaw_t0.clone(), fit.coeff0.clone()]
    for name in ("head_R0", "head_t0", "jaw_R0", "jaw_t0", "coeff0"):
        delattr(fit, name)
    u = fit.settings.length_unit_mm
    fit.head_R0, fit.head_t0 = so3_exp(d[:, 0:3]) @ base[0], base[1] + u * d[:, 3:6]
    fit.jaw_R0, fit.jaw_t0, fit.coeff0 = so3_exp(d[:, 6:9]) @ base[2], base[3] + u * d[:, 9:12], base[4] + d[:, 12:]
    grad, = torch.autograd.grad(fitting_losses(fit, actor, obs)["total"], d)
    H, g = prob.normal_equations()
    torch.testing.assert_close(g.reshape(grad.shape), grad / 2, rtol=1e-8, atol=1e-12)
    # the band the solver assumes is the band the terms make (every temporal term is on here)
    from models.banded import block_bandwidth

    assert prob.frame_bandwidth == block_bandwidth(H) == 2


def _lm_residuals(fit, actor, obs, s):
    """The squared-loss fit's residual vector as a function of the base update ``d (J n,)`` (float64 torch),
    built independently of models.fit_lm from pose_face and project_points; and ``model(d)``, the poses and
    coefficients at ``base + d``."""
    from calib.projection import project_points
    from models.fit_lm import so3_exp

    J, E = fit.coeff0.shape
    u = s.length_unit_mm
    with torch.no_grad():
        net = fit.net_poses()
        Fw = fit.net_coefficients(actor)
    base = [fit.head_R0.clone(), fit.head_t0.clone(), fit.jaw_R0.clone(), fit.jaw_t0.clone(), fit.coeff0.clone()]
    W = obs.weights.sum()
    eye = torch.eye(3, dtype=torch.float64)

    def model(x):
        d = torch.as_tensor(x).reshape(J, 12 + E)
        head_R = so3_exp(d[:, 0:3]) @ base[0] @ net.head_R
        head_t = base[1] + u * d[:, 3:6] + net.head_t
        jaw_R = so3_exp(d[:, 6:9]) @ base[2] @ net.jaw_R
        jaw_t = base[3] + u * d[:, 9:12] + net.jaw_t
        w = Fw + (base[4] + d[:, 12:])[:, None]
        return head_R, head_t, jaw_R, jaw_t, w

    def residuals(x):
        head_R, head_t, jaw_R, jaw_t, w = model(x)
        face = pose_face(actor, head_R, head_t, jaw_R, jaw_t, w)
        r = [((obs.weights / W).sqrt()[..., None] * (project_points(face, K, DIST) - obs.points2d)).flatten(),
             (s.coeff_weight / w.numel()) ** 0.5 * w.flatten(),
             (s.jaw_prior_weight / J) ** 0.5 * torch.cat([(jaw_t / u).flatten(), (jaw_R - eye).flatten()]),
             (s.coeff_temporal_weight / ((J - 1) * w.shape[1])) ** 0.5 * (w[1:] - w[:-1]).flatten()]
        acc = lambda q: (q[2:] - 2 * q[1:-1] + q[:-2]).flatten()
        k = (s.pose_accel_weight / (J - 2)) ** 0.5
        r += [k * acc(head_t / u), k * acc(head_R), k * acc(jaw_t / u), k * acc(jaw_R)]
        return torch.cat(r)

    return residuals, model


def test_lm_reaches_the_least_squares_minimum_of_scipy():
    """solve_base and scipy.optimize.least_squares minimise the same energy to the same point.

    scipy sees an independent residual vector (built here from pose_face and project_points, squared
    loss) and differentiates it numerically."""
    import numpy as np
    from scipy.optimize import least_squares

    from models.fit_lm import solve_base

    s = replace(LM_SETTINGS, robust_px=0.0)
    actor, obs = _lm_problem(P=30)
    fit = _perturbed_fit(s)
    J, E = fit.coeff0.shape
    residuals, model = _lm_residuals(fit, actor, obs, s)
    ref = least_squares(lambda x: residuals(x).numpy(), np.zeros(J * (12 + E)), method="trf", xtol=1e-12,
                        ftol=1e-12, gtol=1e-12)
    res = solve_base(fit, actor, obs, iterations=50, tol=1e-14)
    e_ref = float((ref.fun ** 2).sum())
    assert res.energies[-1] == pytest.approx(e_ref, rel=1e-9)
    with torch.no_grad():
        pose = fit.poses()
        ours = pose_face(actor, pose.head_R, pose.head_t, pose.jaw_R, pose.jaw_t, fit.coefficients(actor))
        theirs = pose_face(actor, *model(ref.x))
    # the same minimum: points within a micrometre (the face is ~600 mm from the camera)
    torch.testing.assert_close(ours, theirs, rtol=0, atol=1e-3)


def test_lm_gauss_newton_matrix_is_jt_j_of_the_residuals():
    """The normal equations' matrix (its float32 Jacobian planes, the banded temporal blocks added through
    diagonal views) equals J^T J of the independent residual vector, J by autograd; and g equals J^T r."""
    from models.fit_lm import _Problem

    s = replace(LM_SETTINGS, robust_px=0.0)
    # 7 frames: the pose-acceleration band fills blocks two frames apart; F_W at its zero start: the
    # 2D default's path, without F_W's terms
    for n_frames, zero_fw in ((4, False), (7, False), (7, True)):
        actor, obs = _lm_problem(P=40)
        obs = Observations(points2d=obs.points2d[:1].expand(n_frames, -1, -1).clone(),
                           weights=obs.weights[:1].expand(n_frames, -1).clone(), K=K, dist=DIST)
        fit = _perturbed_fit(s, J=n_frames)
        if zero_fw:
            with torch.no_grad():
                fit.F_W.net[-1].weight.zero_()
                fit.F_W.net[-1].bias.zero_()
            assert fit.net_is_zero()
        residuals, _ = _lm_residuals(fit, actor, obs, s)
        n = 12 + fit.coeff0.shape[1]
        d0 = torch.zeros(n_frames * n, dtype=torch.float64)
        Jm = torch.autograd.functional.jacobian(residuals, d0)
        H, g = _Problem(fit, actor, obs).normal_equations()
        dense = H.permute(0, 2, 1, 3).reshape(n_frames * n, n_frames * n)
        ref = Jm.T @ Jm
        # float32 Jacobian planes: relative rounding ~1e-7 of the largest entries
        torch.testing.assert_close(dense, ref, rtol=0, atol=1e-5 * float(ref.abs().max()))
        torch.testing.assert_close(g, Jm.T @ residuals(d0), rtol=1e-8, atol=1e-12)


def test_lm_ends_where_the_jaw_and_its_target_agree():
    """With the jaw prior pointed at the jaw the coefficients imply, the solve moves that target after
    every step, so it ends at a fixed point: a second solve from its result moves nothing (while the
    target was held for a whole solve, a second solve moved the jaw by the change of its target)."""
    from models.fit_lm import solve_base

    actor, obs = _lm_problem(P=40)
    E = actor.n_expressions
    g = torch.Generator().manual_seed(3)
    actor.jaw_rotvec = 0.2 * torch.randn(E, 3, generator=g, dtype=torch.float64)   # each shape's jaw
    actor.jaw_shift = 2.0 * torch.randn(E, 3, generator=g, dtype=torch.float64)
    s = replace(LM_SETTINGS, jaw_prior_target="expressions", jaw_prior_weight=1.0)
    fit = _perturbed_fit(s)
    first = solve_base(fit, actor, obs, iterations=50, tol=1e-12)
    assert first.energies[-1] < first.energies[0]
    before = [x.clone() for x in (fit.jaw_R0, fit.jaw_t0, fit.coeff0)]
    second = solve_base(fit, actor, obs, iterations=50, tol=1e-12)
    assert second.energies[-1] == pytest.approx(second.energies[0], rel=1e-9)
    for a, b in zip(before, (fit.jaw_R0, fit.jaw_t0, fit.coeff0)):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)


def test_polish_runs_only_after_what_moved_the_base():
    """The second Levenberg-Marquardt solve (``lm_polish_iterations``) follows Adam iterations; right after
    the first solve (2D, no Adam: the default) it is skipped, and the fit is that first solve's."""
    from models.fit import fit_sequence
    from models.fit_lm import solve_base

    actor, obs = _lm_problem(P=40)
    s = replace(LM_SETTINGS, lm_iterations=10, lm_polish_iterations=10, adam_on_landmarks=False, iterations=3)
    R0 = torch.eye(3, dtype=torch.float64).expand(4, 3, 3).clone()
    t0 = torch.tensor([0.0, 0.0, 600.0], dtype=torch.float64).expand(4, 3).clone()
    res = fit_sequence(actor, obs, s, R0, t0)
    fit = SequenceFit(4, actor.n_expressions, s, R0, t0)
    alone = solve_base(fit, actor, obs, 10)
    assert res.lm_iterations == alone.iterations and not res.losses
    torch.testing.assert_close(res.fit.coeff0, fit.coeff0, rtol=0, atol=0)
    torch.testing.assert_close(res.fit.head_t0, fit.head_t0, rtol=0, atol=0)
    adam = fit_sequence(actor, obs, replace(s, adam_on_landmarks=True), R0, t0)
    assert len(adam.losses) == 3 and adam.lm_iterations > alone.iterations


def test_lm_converges_in_a_few_iterations_and_handles_3d():
    from models.fit_lm import solve_base

    actor = toy_actor()
    head_R, head_t, face = truth(actor)
    R0 = head_R @ torch.tensor(Rotation.from_euler("xy", [0.05, -0.05]).as_matrix())
    s = FitSettings(robust_px=0.0, coeff_weight=1e-6)
    fit = SequenceFit(4, 4, s, R0, head_t + 10.0).double()
    res = solve_base(fit, actor, Observations(points3d=face), iterations=20)
    assert res.iterations <= 10
    with torch.no_grad():
        pose = fit.poses()
        pred = pose_face(actor, pose.head_R, pose.head_t, pose.jaw_R, pose.jaw_t, fit.coefficients(actor))
    # the truth is the base model itself (coefficients constant over points): reached to 1e-4 mm
    assert (pred - face).norm(dim=-1).max() < 1e-4


def test_robust_rows_carry_the_pseudo_huber_curvature():
    """robust_2d_linearised against autograd in residual space: D^T D is J^T H J with H half the Hessian
    of the point's loss w rho(|r|^2) / sum w in r, and D^T rs half its gradient; exact=False is IRLS (J^T
    rho' J, the same gradient). Residuals from 0 (no direction) to 20 scales (deep in the linear part)."""
    from models.fit_energy import irls_sqrt_weights, robust_2d, robust_2d_linearised

    g = torch.Generator().manual_seed(3)
    c = 1.5
    r = torch.randn(2, 7, 2, generator=g, dtype=torch.float64) * torch.logspace(-2, 1.5, 7, dtype=torch.float64)[:, None]
    r[0, 0] = 0.0
    w = torch.rand(2, 7, generator=g, dtype=torch.float64)
    Jp = torch.randn(2, 7, 2, 5, generator=g, dtype=torch.float64)
    D, rs = robust_2d_linearised(r, Jp, w, c)
    Di, rsi = robust_2d_linearised(r, Jp, w, c, exact=False)
    for j in range(2):
        for p in range(7):
            loss = lambda x: w[j, p] * robust_2d(x.square().sum(), c) / w.sum()
            H = torch.autograd.functional.hessian(loss, r[j, p]) / 2
            grad = torch.autograd.functional.jacobian(loss, r[j, p]) / 2
            torch.testing.assert_close(D[j, p].T @ D[j, p], Jp[j, p].T @ H @ Jp[j, p], rtol=1e-10, atol=1e-14)
            torch.testing.assert_close(D[j, p].T @ rs[j, p], Jp[j, p].T @ grad, rtol=1e-10, atol=1e-14)
            torch.testing.assert_close(Di[j, p].T @ rsi[j, p], Jp[j, p].T @ grad, rtol=1e-10, atol=1e-14)
    sw = irls_sqrt_weights(r, w, c)[..., None]
    torch.testing.assert_close(Di, sw * Jp, rtol=0, atol=0)
    # squared loss: both are plain weighted least squares
    D0, rs0 = robust_2d_linearised(r, Jp, w, 0.0)
    torch.testing.assert_close(D0, (w / w.sum()).sqrt()[..., None, None] * Jp, rtol=1e-12, atol=0)


def test_lm_with_the_robust_curvature_reaches_the_same_minimum_in_fewer_steps(monkeypatch):
    """With a pseudo-Huber scale below the residuals (a 0.3 px noise, 1.5 px scale against a start ~20 px off
    and 5 wild landmarks), the solve with the exact robust curvature after REWEIGHTED_STEPS steps ends at
    the minimum that reweighting alone reaches, in fewer linearisations."""
    import models.fit_lm as fit_lm

    s = replace(LM_SETTINGS, robust_px=0.3)
    actor, obs = _lm_problem(P=60)
    runs = {}
    for name, steps in (("exact", fit_lm.REWEIGHTED_STEPS), ("reweighted", 10 ** 6)):
        monkeypatch.setattr(fit_lm, "REWEIGHTED_STEPS", steps)
        fit = _perturbed_fit(s)
        runs[name] = fit_lm.solve_base(fit, actor, obs, iterations=200, tol=1e-13)
        runs[name + "_pose"] = fit.poses().head_t.detach()
    e_exact, e_rw = runs["exact"].energies[-1], runs["reweighted"].energies[-1]
    assert e_exact == pytest.approx(e_rw, rel=1e-9)
    torch.testing.assert_close(runs["exact_pose"], runs["reweighted_pose"], rtol=0, atol=1e-3)  # mm
    assert runs["exact"].iterations < 0.6 * runs["reweighted"].iterations, \
        (runs["exact"].iterations, runs["reweighted"].iterations)


@pytest.mark.parametrize("n_dist", [0, 4, 5, 8, 12, 14])
@pytest.mark.parametrize("zero", ["", "tangential", "rational", "prism", "radial"])
def test_projection_jacobian_matches_autograd(n_dist, zero):
    """The analytic projection and its Jacobian equal kornia's projection and autograd through it, with
    every group of distortion terms on or off (the analytic path skips the groups that are zero) and a skew."""
    from calib.projection import project_points
    from models.fit_lm import projection_jacobian

    g = torch.Generator().manual_seed(n_dist)
    x = torch.randn(2, 50, 3, generator=g, dtype=torch.float64) * 80 + torch.tensor([0, 0, 500.0], dtype=torch.float64)
    dist = None if n_dist == 0 else 0.05 * torch.randn(n_dist, generator=g, dtype=torch.float64)
    groups = {"tangential": [2, 3], "rational": [5, 6, 7], "prism": [8, 9, 10, 11], "radial": [0, 1, 4]}
    if dist is not None and zero:
        dist[[i for i in groups[zero] if i < n_dist]] = 0.0
    Kx = K.clone()
    if zero == "radial":
        Kx[0, 1] = 3.0   # a skew, which OpenCV and kornia ignore

    uv, Jp = projection_jacobian(x, Kx, dist)
    torch.testing.assert_close(uv, project_points(x, Kx, dist))
    torch.testing.assert_close(projection_jacobian(x, Kx, dist, jacobian=False), uv, rtol=0, atol=0)
    cols = []
    for k in range(3):
        xg = x.clone().requires_grad_(True)
        cols.append(torch.stack([torch.autograd.grad(project_points(xg, Kx, dist)[..., i].sum(), xg)[0][..., k]
                                 for i in range(2)], -1))
    torch.testing.assert_close(Jp, torch.stack(cols, -1), rtol=1e-9, atol=1e-9)


def test_so3_exp_matches_scipy():
    from models.fit_lm import so3_exp

    v = torch.tensor([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [1e-8, 2e-8, 0.0], [2.0, 0.5, -1.0]], dtype=torch.float64)
    torch.testing.assert_close(so3_exp(v), torch.tensor(Rotation.from_rotvec(v.numpy()).as_matrix()))


def test_pose_face_with_coefficients_constant_over_points():
    actor = toy_actor(P=40, E=4)
    head_R, head_t, _ = truth(actor, J=3)
    w = torch.randn(3, 1, 4, dtype=torch.float64)
    jaw_R, jaw_t = head_R.transpose(1, 2), torch.ones(3, 3, dtype=torch.float64)
    torch.testing.assert_close(pose_face(actor, head_R, head_t, jaw_R, jaw_t, w),
                               pose_face(actor, head_R, head_t, jaw_R, jaw_t, w.expand(3, 40, 4).contiguous()))



@pytest.mark.parametrize("dtype, tol", [(torch.float64, 1e-9), (torch.float32, 2e-4)])
def test_pose_face_shared_is_pose_face(dtype, tol):
    """The meshes' one-product map against pose_face's skinning, blend and rigid steps, with a jaw that turns
    about the actor's pivot and moves; in float32 within 2e-4 mm (head ~600 mm away: a few float32 ulps)."""
    actor = toy_actor(P=60, E=4)
    head_R, head_t, _ = truth(actor, J=5)
    head_R = head_R @ torch.tensor(Rotation.from_rotvec([0.1, 0.2, 0.3]).as_matrix())   # not symmetric
    jaw_R = torch.stack([torch.tensor(Rotation.from_rotvec([0.2 * j, -0.05, 0.03 * j]).as_matrix()) for j in range(5)])
    jaw_t = torch.linspace(-2.0, 3.0, 15, dtype=torch.float64).reshape(5, 3)
    w = torch.randn(5, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    cast = ActorAtPoints(points=actor.points.to(dtype), neutral=actor.neutral.to(dtype),
                         skin_weight=actor.skin_weight.to(dtype), expressions=actor.expressions.to(dtype),
                         jaw_pivot=actor.jaw_pivot.to(dtype), center=actor.center.to(dtype), scale=actor.scale)
    args = [a.to(dtype) for a in (head_R, head_t, jaw_R, jaw_t)]
    ours = pose_face_shared(cast, *args, w.to(dtype))
    assert ours.shape == (5, 60, 3) and ours.is_contiguous() and ours.dtype == dtype
    torch.testing.assert_close(ours, pose_face(cast, *args, w.to(dtype)[:, None, :]), rtol=0, atol=tol)
    # the same meshes from each frame's map of the features, in numpy (what the fit hands over and stores)
    maps = shared_pose_maps(cast, *args, w.to(dtype))
    assert maps.shape == (5, 3, 8 + 3 * 4) and maps.dtype == dtype
    basis = mesh_basis(cast)
    assert basis.dtype == np.float32 and basis.shape == (8 + 3 * 4, 60)
    for j in range(5):
        v = map_vertices(maps[j].numpy().astype(np.float32), basis)
        assert v.dtype == np.float32 and v.shape == (60, 3) and v.flags.c_contiguous
        np.testing.assert_allclose(v, ours[j].double().numpy(), rtol=0, atol=2e-4)
    # a point off the jaw (k = 0) follows the head alone: R_g (x + sum_i w_i E_i) + t_g
    i = int(torch.argmin(actor.skin_weight))
    cast.skin_weight[i] = 0
    cast._features = None
    alone = head_R @ (actor.neutral[i] + torch.einsum("je,ec->jc", w, actor.expressions[i])).unsqueeze(-1)
    torch.testing.assert_close(pose_face_shared(cast, *args, w.to(dtype))[:, i].double(),
                               alone.squeeze(-1) + head_t, rtol=0, atol=tol)

def test_paper_preset_stays_the_papers():
    """The paper preset (the reference) has none of the default's additions: no LM base, no extra priors."""
    from models.fit import FIT_PRESETS

    p = FIT_PRESETS["paper"]
    assert (p.iterations, p.lr, p.lr_final_fraction, p.coeff_weight, p.temporal_weight, p.robust_px) == \
        (10_000, 1e-3, 1.0, 0.75, 0.05, 0.0)
    assert (p.lm_iterations, p.lm_polish_iterations, p.pose_accel_weight, p.coeff_temporal_weight,
            p.jaw_prior_weight, p.early_stop_tol) == (0, 0, 0.0, 0.0, 0.0, 0.0)
    assert p.adam_on_landmarks and p.warm_iterations is None
