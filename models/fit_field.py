"""Per-point expression coefficients: a smooth coefficient field solved by Gauss-Newton (2D and 3D fits).

The paper's ``F_W(z_j, c)`` lets the expression coefficients vary over the face, which is what takes
a fit beyond the span of the training shapes (an actor learned from 19 shapes fitting expressions it
never saw). Fitted by Adam from 2D landmarks it needs hundreds of iterations and overfits the
landmarks' noise in depth. This module gives the same freedom a form that a few Gauss-Newton steps
solve exactly: per frame j

    w_j(c) = m_j(c) + sum_b phi_b(c) a_jb,        phi_b(c) = g_b(c) / sum_b' g_b'(c),
    g_b(c) = exp(-|c - c_b|^2 / (2 sigma^2))

with ``m_j(c)`` everything else (``F_W`` and the base offsets ``coeff0``), ``B`` centres ``c_b``
(farthest-point samples of the fit points on the template) and per-frame coefficients ``a_jb (E,)``.
The displacement a frame gets is ``sum_e w_je(c) E_e(c)``: points move only where and how the
actor's expressions move them (the anatomical constraint), smoothly over the face (sigma), and the
field is linear in ``a``: with the poses fixed, the 2D energy is a least-squares problem in ``a``
that is nonlinear only through the projection.

Energy in ``a`` (the poses, ``F_W`` and ``coeff0`` fixed; all terms of
:func:`models.fit_energy.energy_terms` that depend on ``w``, plus two priors of the field):

* the 2D landmark term (confidence-weighted pseudo-Huber, as in the base solve),
* ``coeff_weight * mean_{j,p,e} w^2`` and ``coeff_temporal_weight * mean_{j,p} |w_j - w_{j-1}|^2``,
* ``field_weight * mean_{j,b,e} a^2``: the field stays at 0 where the landmarks say nothing,
* ``field_temporal_weight * mean_j sum_{b,e} (a_j - a_{j-1})^2``: no flicker,
* ``field_motion_weight * mean_{j,p} |d_jp / unit|^2`` with ``d`` the displacement the field adds: of the
  fields that explain the landmarks the one that moves the face least, so that motion along the
  camera axis (which the landmarks do not see) is not invented.

The normal equations are block tridiagonal over frames (blocks of ``B E`` unknowns, coupled only by
the temporal terms) and are solved by block Cholesky (:func:`solve_block_tridiagonal`), with
Marquardt's damping and a step kept only when the exact energy goes down.

With 3D points (``capture fit3d``) the landmark term is replaced by the 3D position term
``mean_{j,p} |(x_jp - y_jp) / unit|^2`` of :func:`models.fit_energy.energy_terms`. It is quadratic in
``a`` and its Gauss-Newton matrix ``E_p E_p^T / unit^2`` per point does not depend on the head
rotation, so without temporal terms every frame has the same matrix: it is built and factored once
per solve and each step is a gradient and two triangular solves (:func:`_solve_constant`). There, with
nothing ambiguous in depth, the field is dense (``FIT3D_PRESETS``: 256 centres, every vertex).
"""

from __future__ import annotations

import math

import torch

from calib.projection import project_points
from models.banded import solve_block_tridiagonal
from models.fit_energy import irls_sqrt_weights, monocular_priors, observation_weights, robust_2d
from models.fit_lm import projection_jacobian
from models.fit_state import ActorAtPoints, Observations, SequenceFit, rbf_basis
from models.lbs import lbs_jaw

#: Centres per point in the Gauss-Newton matrix of the field (see _FieldProblem.normal_equations), when
#: the matrix is rebuilt at every step (2D data) and when it is built once per solve (3D data).
NEAREST_CENTRES = 4
NEAREST_CENTRES_CONSTANT = 12

__all__ = ["farthest_points", "field_centres", "field_energy", "rbf_basis", "solve_field"]


def farthest_points(points: torch.Tensor, n: int) -> torch.Tensor:
    """``n`` farthest-point samples ``(n, 3)`` of ``points (P, 3)``, starting from the one nearest their mean."""
    P = points.shape[0]
    if n >= P:
        return points.clone()
    x = points.double()
    idx = [int(torch.argmin((x - x.mean(0)).square().sum(1)))]
    d = (x - x[idx[0]]).square().sum(1)
    for _ in range(1, n):
        idx.append(int(torch.argmax(d)))
        d = torch.minimum(d, (x - x[idx[-1]]).square().sum(1))
    return points[torch.tensor(idx)]


def field_centres(actor: ActorAtPoints, n: int, min_motion_mm: float = 1.0) -> torch.Tensor:
    """``n`` centres ``(n, 3)``: farthest points among the fit points that the actor's expressions move
    (``sqrt(sum_e |E_e(c)|^2) >= min_motion_mm``; all points when fewer than ``n`` do): a field
    where nothing moves could only move nothing, so its centres go where the expressions act."""
    motion = actor.expressions.detach().square().sum((-1, -2)).sqrt()
    moving = actor.points.detach()[motion >= min_motion_mm]
    return farthest_points(moving if moving.shape[0] >= n else actor.points.detach(), n)


class _FieldProblem:
    """The field energy of one window (poses and everything but the field fixed), in float64."""

    def __init__(self, fit: SequenceFit, actor: ActorAtPoints, obs: Observations):
        f64 = torch.float64
        s = monocular_priors(fit.settings, obs)
        self.s = s
        with torch.no_grad():
            pose = fit.poses()
            self.phi = fit.field_basis(actor.points).to(f64)                                   # (P, B)
            saved = fit.field.clone()
            fit.field.zero_()
            self.m = fit.coefficients(actor).to(f64)                                            # (J, P, E)
            fit.field.copy_(saved)
            self.a0 = saved.to(f64)                                                            # (J, B, E)
        self.E_basis = actor.expressions.detach().to(f64)                                      # (P, E, 3)
        self.R = pose.head_R.detach().to(f64)
        skinned = lbs_jaw(actor.neutral.detach().to(f64).expand(self.R.shape[0], -1, -1),
                          actor.skin_weight.detach().to(f64).expand(self.R.shape[0], -1), pose.jaw_R.detach().to(f64),
                          pose.jaw_t.detach().to(f64), actor.jaw_pivot.detach().to(f64))
        local = skinned + torch.einsum("jpe,pec->jpc", self.m, self.E_basis)
        self.x0 = torch.einsum("jab,jpb->jpa", self.R, local) + pose.head_t.detach().to(f64)[:, None]
        self.p2d = self.p3d = None
        if obs.points2d is not None:
            self.p2d = torch.nan_to_num(obs.points2d.detach().to(f64))
            self.w2d = observation_weights(obs, f64).detach().to(f64)
            self.K = obs.K.detach().to(f64)
            self.dist = None if obs.dist is None else obs.dist.detach().to(f64)
        if obs.points3d is not None:
            self.p3d = obs.points3d.detach().to(f64)
        self.J, self.P, self.E = self.m.shape
        self.B = self.phi.shape[1]

    def displacement(self, a: torch.Tensor) -> torch.Tensor:
        """The field's displacement ``(J, P, 3)`` mm (head frame) for coefficients ``a (J, B, E)``."""
        return torch.einsum("jpe,pec->jpc", torch.einsum("pb,jbe->jpe", self.phi, a), self.E_basis)

    def points(self, a: torch.Tensor) -> torch.Tensor:
        """Camera-frame fit points ``(J, P, 3)`` for field coefficients ``a (J, B, E)``."""
        return self.x0 + torch.einsum("jab,jpb->jpa", self.R, self.displacement(a))

    def energy(self, a: torch.Tensor) -> float:
        return float(field_energy(self, a))

    @property
    def constant_hessian(self) -> bool:
        """True when the Gauss-Newton matrix depends neither on ``a`` nor on the frame: 3D data only
        (its Jacobian ``R_g E_p^T`` has ``J^T J = E_p E_p^T`` whatever the head rotation) and no
        temporal terms; it is then built and factored once per solve."""
        s = self.s
        return self.p2d is None and (self.J == 1 or (s.coeff_temporal_weight <= 0 and s.field_temporal_weight <= 0))

    def normal_equations(self, a: torch.Tensor, hessian: bool = True
                         ) -> tuple[torch.Tensor | None, torch.Tensor | None, torch.Tensor]:
        """Gauss-Newton blocks at ``a``: diagonal ``(J, m, m)`` (``(1, m, m)`` when every frame has the
        same), upper ``(J-1, m, m)`` (None when the frames are independent) and ``g (J, m)``, ``m = B E``.
        With ``hessian=False`` only ``g`` is computed (the blocks are None)."""
        s, J, P, E, B = self.s, self.J, self.P, self.E, self.B
        m = B * E
        x = self.points(a)
        Q = x.new_zeros(J if self.p2d is not None else 1, P, E, E)
        gp = x.new_zeros(J, P, E)
        if self.p2d is not None:
            uv, Jp = projection_jacobian(x, self.K, self.dist)                            # (J, P, 2), (J, P, 2, 3)
            r = uv - self.p2d
            sw = irls_sqrt_weights(r, self.w2d, s.robust_px)                             # (J, P, 1)
            # G_p = sw Jp R_g E_p^T (2, E): the landmark residual's derivative wrt w_j(c_p)
            JR = torch.einsum("jpia,jab->jpib", sw[..., None] * Jp, self.R)
            G = torch.einsum("jpib,peb->jpie", JR, self.E_basis)                         # (J, P, 2, E)
            Q = Q + torch.einsum("jpie,jpif->jpef", G, G)                                 # (J, P, E, E)
            gp = gp + torch.einsum("jpie,jpi->jpe", G, sw * r)                           # (J, P, E)
        EE = torch.einsum("pec,pfc->pef", self.E_basis, self.E_basis)[None] if hessian else 0   # (1, P, E, E)
        if self.p3d is not None:  # residual (x - p3d) / unit / sqrt(J P); its derivative R_g E_p^T / unit / sqrt(J P)
            k = 1.0 / (J * P * s.length_unit_mm ** 2)
            Q = Q + k * EE
            gp = gp + k * torch.einsum("pec,jpc->jpe", self.E_basis,
                                       torch.einsum("jba,jpb->jpa", self.R, x - self.p3d))
        if s.field_motion_weight > 0:  # residual sqrt(k) E_p^T phi_p a_j / unit per point
            k = s.field_motion_weight / (J * P * s.length_unit_mm ** 2)
            Q = Q + k * EE
            gp = gp + k * torch.einsum("pec,jpc->jpe", self.E_basis, self.displacement(a))
        g = torch.einsum("pb,jpe->jbe", self.phi, gp).reshape(J, m)
        w = self.m + torch.einsum("pb,jbe->jpe", self.phi, a)                             # (J, P, E)
        if s.coeff_weight > 0:
            g += s.coeff_weight / (J * P * E) * torch.einsum("pb,jpe->jbe", self.phi, w).reshape(J, m)
        if s.field_weight > 0:
            g += s.field_weight / (J * B * E) * a.reshape(J, m)
        dg = torch.zeros(max(J - 1, 0), m, dtype=torch.float64)
        if J > 1 and s.coeff_temporal_weight > 0:
            k = s.coeff_temporal_weight / ((J - 1) * P)
            dg += k * torch.einsum("pb,jpe->jbe", self.phi, w[1:] - w[:-1]).reshape(J - 1, m)
        if J > 1 and s.field_temporal_weight > 0:
            dg += s.field_temporal_weight / (J - 1) * (a[1:] - a[:-1]).reshape(J - 1, m)
        if J > 1:
            g[:-1] -= dg
            g[1:] += dg
        if not hessian:
            return None, None, g
        Jq = Q.shape[0]   # 1 when Q is the same for every frame (3D data only): one block for all frames
        Q = Q.reshape(Jq, P, E * E).float()
        # H_j[b, e, c, f] = sum_p phi_pb phi_pc Q_p[e, f], accumulated in float32 over each point's
        # NEAREST_CENTRES largest weights (the rest are < 1e-3 for the default spacing): the Gauss-Newton
        # matrix shapes the step only; the gradient and the energy that accepts a step are exact.
        k = min(NEAREST_CENTRES_CONSTANT if self.constant_hessian else NEAREST_CENTRES, B)
        val, idx = torch.topk(self.phi, k, dim=1)                                         # (P, k)
        pair = (idx[:, :, None] * B + idx[:, None, :]).reshape(P, k * k)                  # (P, k k)
        pw = (val[:, :, None] * val[:, None, :]).reshape(P, k * k, 1).float()
        D = torch.empty(Jq, m, m, dtype=torch.float64)
        chunk = max(1, (1 << 24) // (k * k * E * E))   # points per chunk: <= 64 MB of float32 terms
        for j in range(Jq):
            Hb = torch.zeros(B * B, E * E, dtype=torch.float32)
            for p0 in range(0, P, chunk):
                sl = slice(p0, p0 + chunk)
                Hb.index_add_(0, pair[sl].reshape(-1), (pw[sl] * Q[j, sl, None, :]).reshape(-1, E * E))
            D[j].view(B, E, B, E).copy_(Hb.view(B, B, E, E).permute(0, 2, 1, 3))
            del Hb
        eyeE = torch.eye(E, dtype=torch.float64)
        PhiTPhi = self.phi.T @ self.phi                                                   # (B, B)
        Dd = D.diagonal(dim1=1, dim2=2)
        if s.coeff_weight > 0:   # + k kron(Phi^T Phi, I_E), added in place
            k = s.coeff_weight / (J * P * E)
            for e in range(E):
                D.view(Jq, B, E, B, E)[:, :, e, :, e] += k * PhiTPhi
        if s.field_weight > 0:
            Dd += s.field_weight / (J * B * E)
        if J == 1 or (s.coeff_temporal_weight <= 0 and s.field_temporal_weight <= 0):
            return D, None, g
        D = D.expand(J, m, m).clone()
        Gt = torch.zeros(m, m, dtype=torch.float64)
        if s.coeff_temporal_weight > 0:
            Gt += s.coeff_temporal_weight / ((J - 1) * P) * torch.kron(PhiTPhi, eyeE)
        if s.field_temporal_weight > 0:
            Gt.diagonal().add_(s.field_temporal_weight / (J - 1))
        D[:-1] += Gt
        D[1:] += Gt
        U = -Gt.expand(J - 1, m, m)
        return D, U, g


def field_energy(prob: _FieldProblem, a: torch.Tensor) -> torch.Tensor:
    """The terms of the fitting energy that depend on the field coefficients ``a (J, B, E)`` (module docstring)."""
    s, J = prob.s, prob.J
    x = prob.points(a)
    e = x.new_zeros(())
    if prob.p2d is not None:
        r2 = (project_points(x, prob.K, prob.dist) - prob.p2d).square().sum(-1)
        e = e + (prob.w2d * robust_2d(r2, s.robust_px)).sum() / prob.w2d.sum().clamp_min(1e-12)
    if prob.p3d is not None:
        e = e + ((x - prob.p3d) / s.length_unit_mm).square().sum(-1).mean()
    w = prob.m + torch.einsum("pb,jbe->jpe", prob.phi, a)
    e = e + s.coeff_weight * w.square().mean()
    e = e + s.field_weight * a.square().mean()
    if s.field_motion_weight > 0:
        e = e + s.field_motion_weight * (prob.displacement(a) / s.length_unit_mm).square().sum(-1).mean()
    if J > 1:
        e = e + s.coeff_temporal_weight * (w[1:] - w[:-1]).square().sum(-1).mean()
        e = e + s.field_temporal_weight * (a[1:] - a[:-1]).square().sum((-1, -2)).mean()
    return e


def solve_field(fit: SequenceFit, actor: ActorAtPoints, obs: Observations, iterations: int) -> int:
    """Minimise the field energy over ``fit.field`` (Gauss-Newton with Marquardt damping); in place.

    Sets ``fit.field_centres`` (farthest points of ``actor.points``) when they are still all zero; with
    fewer points than centres, every point is a centre and the field's buffers shrink to match.
    Returns the number of linearisations.
    """
    if fit.field.shape[1] == 0 or iterations <= 0 or (obs.points2d is None and obs.points3d is None):
        return 0
    with torch.no_grad():
        if not bool(fit.field_centres.any()):
            centres = field_centres(actor, fit.field.shape[1])
            if centres.shape[0] != fit.field.shape[1]:   # fewer fitted points than centres: one per point
                fit.register_buffer("field", fit.field.new_zeros(fit.field.shape[0], centres.shape[0],
                                                                 fit.field.shape[2]))
                fit.register_buffer("field_centres", fit.field_centres.new_zeros(centres.shape))
            fit.field_centres.copy_(centres)
    prob = _FieldProblem(fit, actor, obs)
    a, it = (_solve_constant if prob.constant_hessian else _solve_damped)(prob, iterations, fit.settings.lm_tol)
    with torch.no_grad():
        fit.field.copy_(a.to(fit.field.dtype))
    return it


def _damped(D: torch.Tensor, mu: float) -> torch.Tensor:
    """``D + mu diag(D)`` (Marquardt's damping of each diagonal block), a new tensor."""
    diag = D.diagonal(dim1=1, dim2=2).clamp_min(1e-12 * float(D.diagonal(dim1=1, dim2=2).max()) + 1e-30)
    out = D.clone()
    out.diagonal(dim1=1, dim2=2).add_(mu * diag)
    return out


def _solve_damped(prob: _FieldProblem, iterations: int, tol: float) -> tuple[torch.Tensor, int]:
    """Levenberg-Marquardt on the field: the Gauss-Newton matrix rebuilt at every accepted step."""
    J = prob.J
    a = prob.a0.clone()
    energy = prob.energy(a)
    mu, it = 1e-4, 0
    while it < iterations:
        D, U, g = prob.normal_equations(a)
        improved = False
        while it < iterations:
            it += 1
            step = solve_block_tridiagonal(_damped(D, mu), U, g)
            if step is None:
                mu *= 4
                continue
            trial_a = a - step.reshape(J, prob.B, prob.E)
            trial = prob.energy(trial_a)
            if math.isfinite(trial) and trial < energy:
                improved = energy - trial >= tol * abs(energy)
                a, energy = trial_a, trial
                mu = max(mu / 3, 1e-9)
                break
            mu *= 4
            if mu > 1e8:
                break
        if not improved:
            break
    return a, it


def _solve_constant(prob: _FieldProblem, iterations: int, tol: float) -> tuple[torch.Tensor, int]:
    """Gauss-Newton with a Gauss-Newton matrix that does not change (:attr:`_FieldProblem.constant_hessian`):
    built and factored once (refactored only when a step fails and the damping grows); each iteration
    is a gradient and two triangular solves. The matrix is the exact one up to the nearest-centres
    truncation, so a few steps converge."""
    J = prob.J
    a = prob.a0.clone()
    energy = prob.energy(a)
    D, _, g = prob.normal_equations(a)
    mu, it, L = 1e-6, 0, None
    while it < iterations:
        if L is None:
            L, info = torch.linalg.cholesky_ex(_damped(D, mu)[0])
            if int(info) != 0:
                L, mu = None, mu * 10
                if mu > 1e8:
                    break
                continue
        it += 1
        trial_a = a - torch.cholesky_solve(g.T, L).T.reshape(J, prob.B, prob.E)
        trial = prob.energy(trial_a)
        if math.isfinite(trial) and trial < energy:
            improved = energy - trial >= tol * abs(energy)
            a, energy = trial_a, trial
            if not improved:
                break
            g = prob.normal_equations(a, hessian=False)[2]
        else:
            L, mu = None, mu * 10
            if mu > 1e8:
                break
    return a, it
