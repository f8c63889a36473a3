"""Levenberg-Marquardt on the per-frame base of a sequence fit (the default preset's fast solver).

A :class:`~models.fit.SequenceFit` poses frame j as the base ``(head_R0, head_t0, jaw_R0, jaw_t0,
coeff0)`` composed with its networks' corrections. With the networks held fixed, the fitting energy
(:func:`models.fit.energy_terms`) is a small nonlinear least-squares problem in the base: per frame
a head rotation and translation, a jaw rotation and translation and one offset per expression
(``n = 12 + E`` unknowns), coupled between frames only by the temporal terms. The actor is frozen
and already evaluated at the fit points, so a Gauss-Newton step costs a few ``pose_face`` calls.

Each iteration linearises at the current base: the update ``delta (J, n)`` is ``[head rotation
vector (rad), head translation (length_unit_mm), jaw rotation vector, jaw translation, coefficient
offsets]``; rotations are updated on the left (``R0 <- exp([a]x) R0``). The Jacobians are analytic:
``d x / d delta`` per point (:meth:`_Problem._jacobian`) chained with the projection's ``d uv / d x``
(:func:`projection_jacobian`, OpenCV's distortion model); the temporal terms add banded blocks
(:func:`_add_stencil`). The Gauss-Newton matrix comes from that Jacobian in float32, laid out as planes
over the points so that every product runs along contiguous rows; the gradient is contracted in float64
from the residuals' derivative wrt the points, without the Jacobian (:meth:`_Problem._gradient`). The
normal equations (``J n`` unknowns) are solved in float64 by Cholesky with Marquardt's scaled damping;
a step is kept only if the exact energy (robust 2D loss included) goes down. The pseudo-Huber 2D loss
enters the linearisation with its own curvature (Triggs' correction,
:func:`models.fit_energy.robust_2d_linearised`): ``J^T r`` is the exact gradient and ``J^T J`` the exact
Gauss-Newton matrix of the robust loss, so the solve converges in a few steps, as with the squared
loss (plain reweighting converged linearly and spent the whole iteration budget of every window).

The jaw prior's target (the jaw the coefficients imply, ``jaw_prior_target="expressions"``) is held
fixed within a linearisation and moved to the coefficients after every accepted step
(:meth:`_Problem.retarget`), a fixed-point iteration: the solve ends where the jaw and the coefficients
agree. Held for a whole solve, frames without landmarks (bridged by the priors) kept the jaw of their
warm start: 2.0 - 2.2 mm on the test take of ``tests/test_fit_take.py`` against 0.7 - 0.9 mm now.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from calib.projection import project_points
from models.banded import solve_banded_blocks
from models.fit_energy import (
    jaw_prior_target,
    monocular_priors,
    observation_weights,
    robust_2d,
    robust_2d_linearised,
    squared_norm,
)
from models.fit_state import (
    ActorAtPoints,
    FramePose,
    Observations,
    SequenceFit,
    compose_poses,
)
from models.rotation import skew, so3_exp

__all__ = ["LMResult", "projection_jacobian", "so3_exp", "solve_base"]


#: Accepted steps taken with the reweighted (IRLS) curvature of the robust 2D loss before the solve
#: switches to its exact Gauss-Newton curvature (:func:`models.fit_energy.robust_2d_linearised`). IRLS
#: is safe far from the minimum, where a window's new frames start from the previous frame's pose; the
#: exact curvature converges in a few steps near it. On a 300-frame 1280x720 take (468 landmarks, 13
#: windows) the first solve of each warm window took 6 steps instead of the 10 of its budget, with a
#: lower final energy; switching after 1 step was slower (overshoots, rejected steps), after 3 the same.
REWEIGHTED_STEPS = 2


@dataclass
class LMResult:
    energies: list[float]   # energy at the start and after every accepted step
    iterations: int         # linearisations (accepted or not)


class _Problem:
    """The base problem of one window, in float64, linearised at the current base."""

    def __init__(self, fit: SequenceFit, actor: ActorAtPoints, obs: Observations):
        f64 = torch.float64
        cast = lambda x: None if x is None else x.detach().to(f64)
        self.s = monocular_priors(fit.settings, obs)
        self.unit = self.s.length_unit_mm
        self.s0, self.k = cast(actor.neutral), cast(actor.skin_weight)[:, None]           # (P, 3), (P, 1)
        self.pivot, self.E_basis = cast(actor.jaw_pivot), cast(actor.expressions)         # (3,), (P, E, 3)
        self.k32 = self.k.float().reshape(-1)                                              # the Jacobian's copies:
        self.E32c = self.E_basis.float().permute(2, 1, 0)[:, :, None, :].contiguous()     # (3, E, 1, P) planes
        self.p2d = None if obs.points2d is None else torch.nan_to_num(cast(obs.points2d))
        self.w2d = None if obs.points2d is None else observation_weights(obs, f64).to(f64)
        self.K, self.dist, self.p3d = cast(obs.K), cast(obs.dist), cast(obs.points3d)
        with torch.no_grad():
            net = fit.net_poses()
            self.net = FramePose(*(cast(x) for x in (net.head_R, net.head_t, net.jaw_R, net.jaw_t)))
            zero = fit.net_is_zero()                 # F_W at its zero start (the 2D default): no F_W terms
            Fw = None if zero else fit.net_coefficients(actor).to(f64)                # (J, P, E) fixed
        J, P, E = fit.coeff0.shape[0], self.E_basis.shape[0], self.E_basis.shape[1]
        self.Fw_mean = self.E_basis.new_zeros(J, E) if zero else Fw.mean(1)           # (J, E)
        self.Fw_sq = 0.0 if zero else float(Fw.square().sum())
        self.Fw_sq_diff = 0.0 if zero else float((Fw[1:] - Fw[:-1]).square().sum())
        self.Fw_diff_mean = self.Fw_mean[1:] if zero else (Fw[1:] - Fw[:-1]).mean(1)   # (J-1, E)
        self.A = None if zero else torch.einsum("jpe,pec->jpc", Fw, self.E_basis)     # F_W's displacement
        self.P = P
        self.base = [cast(fit.head_R0), cast(fit.head_t0), cast(fit.jaw_R0), cast(fit.jaw_t0), cast(fit.coeff0)]
        self.J, self.E = self.base[4].shape
        self.E_flat = self.E_basis.permute(1, 0, 2).reshape(self.E, -1)                  # (E, P 3)
        self.n = 12 + self.E
        self._H = None
        self.actor = actor
        self._point_jaw_prior()

    def _point_jaw_prior(self) -> None:
        self.jaw_tR, self.jaw_tt = (x.to(torch.float64) for x in
                                    jaw_prior_target(self.actor, self.s, self.Fw_mean + self.base[4]))

    def _jaw_energy(self, pose: FramePose) -> float:
        """The jaw prior's term of :meth:`energy`."""
        s, u = self.s, self.unit
        if s.jaw_prior_weight <= 0:
            return 0.0
        return s.jaw_prior_weight * (float(squared_norm((pose.jaw_t - self.jaw_tt) / u).mean()) +
                                     float((pose.jaw_R - self.jaw_tR).square().sum((-1, -2)).mean()))

    def retarget(self) -> float:
        """Point the jaw prior at the jaw that the current coefficients imply (``jaw_prior_target``): held
        fixed within a linearisation, moved after every accepted step. Returns the change of the energy
        at the current base."""
        if self.s.jaw_prior_weight <= 0 or self.s.jaw_prior_target == "rest":
            return 0.0
        pose, _ = self.totals()
        before = self._jaw_energy(pose)
        self._point_jaw_prior()
        return self._jaw_energy(pose) - before

    def totals(self, d: torch.Tensor | None = None) -> tuple[FramePose, torch.Tensor]:
        """Poses and coefficient offsets ``(J, E)`` at base + ``d`` (``d (J, n)``; None: the base)."""
        R0, t0, jR0, jt0, c0 = self.base
        if d is not None:
            u = self.unit
            R0, t0, jR0, jt0, c0 = (so3_exp(d[:, 0:3]) @ R0, t0 + u * d[:, 3:6], so3_exp(d[:, 6:9]) @ jR0,
                                    jt0 + u * d[:, 9:12], c0 + d[:, 12:])
        return compose_poses(R0, t0, jR0, jt0, self.net), c0

    def model(self, pose: FramePose, c: torch.Tensor):
        """Camera-frame points ``x (J, P, 3)``, their rotated local part ``y = R_g L`` and ``R_b (s0 - pivot)``."""
        q = self.s0 - self.pivot
        # products over the points' long axis (R @ q^T), as models.rotation.apply_rigid
        jaw_q = torch.matmul(pose.jaw_R, q.transpose(-1, -2)).transpose(1, 2)             # R_b q (J, P, 3)
        skinned = self.s0 + self.k * (jaw_q + self.pivot + pose.jaw_t[:, None] - self.s0)
        local = skinned + (c @ self.E_flat).reshape(self.J, self.P, 3)
        if self.A is not None:
            local = local + self.A
        y = torch.bmm(pose.head_R, local.transpose(1, 2)).transpose(1, 2)                 # R_g L
        return y + pose.head_t[:, None], y, jaw_q

    def energy(self, d: torch.Tensor | None = None) -> float:
        """The fitting energy (:func:`models.fit.energy_terms`, all terms) at base + ``d``."""
        pose, c = self.totals(d)
        x, _, _ = self.model(pose, c)
        s, J, P, E, u = self.s, self.J, self.P, self.E, self.unit
        e = 0.0
        if self.p2d is not None:
            r2 = squared_norm(projection_jacobian(x, self.K, self.dist, jacobian=False) - self.p2d)
            e += float((self.w2d * robust_2d(r2, s.robust_px)).sum() / self.w2d.sum().clamp_min(1e-12))
        if self.p3d is not None:
            e += float(squared_norm((x - self.p3d) / u).mean())
        # sum over (j, p, e) of (F_W + c)^2 = sum F_W^2 + 2 P sum(m c) + P sum(c^2)
        e += s.coeff_weight * (self.Fw_sq + P * float((2 * self.Fw_mean * c + c.square()).sum())) / (J * P * E)
        if s.pose_accel_weight > 0 and J > 2:
            acc = lambda x: float((x[2:] - 2 * x[1:-1] + x[:-2]).flatten(1).square().sum(-1).mean())
            e += s.pose_accel_weight * (acc(pose.head_t / u) + acc(pose.head_R) + acc(pose.jaw_t / u) +
                                        acc(pose.jaw_R))
        e += self._jaw_energy(pose)
        if s.coeff_temporal_weight > 0 and J > 1:
            dc = c[1:] - c[:-1]
            e += s.coeff_temporal_weight * (self.Fw_sq_diff + P * float((2 * self.Fw_diff_mean * dc +
                                                                         dc.square()).sum())) / ((J - 1) * P)
        return e

    @property
    def frame_bandwidth(self) -> int:
        """How many frames apart the normal equations couple frames: 2 with the pose-acceleration term
        (second differences), 1 with the coefficient smoothness (first differences), else 0."""
        s, J = self.s, self.J
        if s.pose_accel_weight > 0 and J > 2:
            return 2
        return 1 if s.coeff_temporal_weight > 0 and J > 1 else 0

    def normal_equations(self, exact_robust: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """``H = J^T J`` as its frame blocks ``(J, J, n, n)`` (``H[j, k]`` couples frames ``j`` and ``k``; zero
        beyond :attr:`frame_bandwidth`) and ``g = J^T r`` ``(J n,)`` of the residuals at the base.

        The residuals are those whose squares sum to the energy up to a constant: per landmark
        ``uv - p`` as :func:`~models.fit_energy.robust_2d_linearised` weighs it (with the robust loss's
        curvature if ``exact_robust``, else reweighted), per 3D point ``(x - p) / (unit sqrt(J P))``, per
        frame and expression ``sqrt(lambda_w / (J E)) (mean_p F_W + c)``, and the temporal differences.
        """
        s, J, P, E, n, u = self.s, self.J, self.P, self.E, self.n, self.unit
        pose, c = self.totals()
        x, y, jaw_q = self.model(pose, c)
        Hb = x.new_zeros(J, n, n)
        gb = x.new_zeros(J, n)
        if self.p2d is not None:
            uv, Jp = projection_jacobian(x, self.K, self.dist)                        # (J, P, 2), (J, P, 2, 3)
            r = uv - self.p2d
            D, rs = robust_2d_linearised(r, Jp, self.w2d, s.robust_px, exact_robust)    # (J, P, 2, 3), (J, P, 2)
            Hb += _gram(self._jacobian(D, y, jaw_q, pose.head_R))
            gb += self._gradient(D, rs, y, jaw_q, pose.head_R)
        if self.p3d is not None:
            k3 = 1 / (u * math.sqrt(J * P))
            D = k3 * torch.eye(3, dtype=x.dtype).expand(J, P, 3, 3)
            Hb += _gram(self._jacobian(D, y, jaw_q, pose.head_R))
            gb += self._gradient(D, k3 * (x - self.p3d), y, jaw_q, pose.head_R)
        kw = s.coeff_weight / (J * E)
        Hb[:, 12:, 12:] += kw * torch.eye(E, dtype=x.dtype)
        gb[:, 12:] += kw * (self.Fw_mean + c)
        if self._H is None:     # H[j, k] is the (n, n) block of frames j, k; reused: no fresh pages per step
            self._H = x.new_zeros(J, J, n, n)
        H = self._H
        for d in range(-self.frame_bandwidth, self.frame_bandwidth + 1):   # only the band is ever written
            torch.diagonal(H, offset=d, dim1=0, dim2=1).zero_()
        j = torch.arange(J)
        H[j, j] = Hb
        self._add_temporal(H, gb, pose, c)
        return H, gb.reshape(-1)

    def _jacobian(self, D: torch.Tensor, y: torch.Tensor, jaw_q: torch.Tensor, head_R: torch.Tensor) -> torch.Tensor:
        """The residuals' Jacobian ``D @ d x / d delta``, transposed: ``(J, n, m P)`` float32, for ``D (J, P, m, 3)``
        (the residuals' derivative wrt ``x``); column ``i P + p`` is residual ``i`` of point ``p``.

        ``d x / d delta`` is ``[-[y]x, unit I, -k R_g [R_b q]x, unit k R_g, R_g E_p^T]`` per point; a row
        ``d`` of ``D`` times ``-[v]x`` is ``v x d``. Laid out as planes over the points (every product runs
        along contiguous rows of P) and in float32, like the Gauss-Newton matrix it is only used for
        (:func:`_gram`); the gradient is :meth:`_gradient`'s, in float64.
        """
        f32 = torch.float32
        J, P, m, _ = D.shape
        Dt = D.to(f32).permute(0, 3, 2, 1).contiguous()                              # (J, 3, m, P)
        yt = y.to(f32).permute(0, 2, 1)[:, :, None, :]                                # (J, 3, 1, P)
        qt = jaw_q.to(f32).permute(0, 2, 1)[:, :, None, :]
        DRt = (head_R.to(f32).transpose(1, 2) @ Dt.reshape(J, 3, m * P)).reshape(J, 3, m, P)   # rows of D R_g
        X = Dt.new_empty(J, self.n, m, P)
        _cross_planes(X[:, 0:3], yt, Dt)
        torch.mul(Dt, self.unit, out=X[:, 3:6])
        _cross_planes(X[:, 6:9], qt, DRt)
        X[:, 6:9].mul_(self.k32)
        torch.mul(DRt, self.unit * self.k32, out=X[:, 9:12])
        C, Ec = X[:, 12:], self.E32c                                                  # R_g E_p^T
        C.zero_()
        C.addcmul_(DRt[:, 0:1], Ec[0])
        C.addcmul_(DRt[:, 1:2], Ec[1])
        C.addcmul_(DRt[:, 2:3], Ec[2])
        return X.reshape(J, self.n, m * P)

    def _gradient(self, D: torch.Tensor, rs: torch.Tensor, y: torch.Tensor, jaw_q: torch.Tensor,
                  head_R: torch.Tensor) -> torch.Tensor:
        """``(D @ d x / d delta)^T rs`` summed over points ``(J, n)``, float64, for residuals ``rs (J, P, m)``.

        With ``v = D^T rs`` per point (the gradient wrt ``x``) this is, per frame, ``[sum y x v, unit sum v,
        sum k R_b q x v R_g, unit sum k v R_g, sum E_p R_g^T v]`` (see :meth:`_jacobian`)."""
        v = sum(D[:, :, i] * rs[:, :, i, None] for i in range(D.shape[2]))          # (J, P, 3)
        vR = torch.bmm(v, head_R)
        return torch.cat([_cross(y, v).sum(1), self.unit * v.sum(1),
                          (self.k * _cross(jaw_q, vR)).sum(1), self.unit * (self.k * vR).sum(1),
                          torch.einsum("jpc,pec->je", vR, self.E_basis)], -1)

    def _add_temporal(self, H: torch.Tensor, g: torch.Tensor, pose: FramePose, c: torch.Tensor) -> None:
        """Add the temporal terms' ``J^T J`` to ``H (J, J, n, n)`` and ``J^T r`` to ``g (J, n)``, at the base."""
        s, J, u, n = self.s, self.J, self.unit, self.n
        eye3 = torch.eye(3, dtype=c.dtype).expand(J, 3, 3)
        gens = skew(torch.eye(3, dtype=c.dtype))                                    # (3, 3, 3): [e_a]x
        # per frame, each quantity's derivative wrt its own update: vec(R) wrt R's rotation vector
        dR = lambda R: torch.einsum("aik,jkl->jila", gens, R).reshape(J, 9, 3)
        if s.pose_accel_weight > 0 and J > 2:
            # head R, head t, jaw R, jaw t stacked (J, 24); their updates are delta[:, 0:12] in that order
            k = math.sqrt(s.pose_accel_weight / (J - 2))
            val = torch.cat([pose.head_R.reshape(J, 9), pose.head_t / u, pose.jaw_R.reshape(J, 9), pose.jaw_t / u], 1)
            G = _blocks([dR(pose.head_R), eye3, dR(pose.jaw_R), eye3])                 # (J, 24, 12)
            _add_stencil(H, g, val, G, slice(0, 12), (1.0, -2.0, 1.0), k)
        if s.jaw_prior_weight > 0:
            # jaw R and jaw t against their targets (J, 12); updates delta[:, 6:12]
            k = math.sqrt(s.jaw_prior_weight / J)
            val = torch.cat([(pose.jaw_R - self.jaw_tR).reshape(J, 9), (pose.jaw_t - self.jaw_tt) / u], 1)
            _add_stencil(H, g, val, _blocks([dR(pose.jaw_R), eye3]), slice(6, 12), (1.0,), k)
        if s.coeff_temporal_weight > 0 and J > 1:
            k = math.sqrt(s.coeff_temporal_weight / (J - 1))
            _add_stencil(H, g, self.Fw_mean + c, None, slice(12, n), (-1.0, 1.0), k)

    def accept(self, d: torch.Tensor) -> None:
        R0, t0, jR0, jt0, c0 = self.base
        u = self.unit
        self.base = [so3_exp(d[:, 0:3]) @ R0, t0 + u * d[:, 3:6], so3_exp(d[:, 6:9]) @ jR0, jt0 + u * d[:, 9:12],
                     c0 + d[:, 12:]]


def _gram(Xt: torch.Tensor) -> torch.Tensor:
    """``Xt Xt^T`` ``(J, n, n)`` float64 for a transposed Jacobian ``Xt (J, n, rows)`` (:meth:`_Problem._jacobian`), in float32.

    Only the Gauss-Newton matrix is rounded (it shapes the step, not the fixed point: the gradient and
    the energy that accepts a step stay in float64)."""
    return (Xt @ Xt.transpose(1, 2)).to(torch.float64)


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a x b`` over the last axis (``torch.linalg.cross`` is several times slower on CPU for small vectors)."""
    a0, a1, a2 = a.unbind(-1)
    b0, b1, b2 = b.unbind(-1)
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


def _cross_planes(out: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> None:
    """``out = a x b`` over axis 1 (``(J, 3, ...)`` planes, broadcast), written in place."""
    for i, (j, k) in enumerate(((1, 2), (2, 0), (0, 1))):
        torch.mul(a[:, j], b[:, k], out=out[:, i])
        out[:, i].addcmul_(a[:, k], b[:, j], value=-1)


def _blocks(G: list[torch.Tensor]) -> torch.Tensor:
    """Per-frame block diagonal ``(J, sum q_i, sum c_i)`` of ``G_i (J, q_i, c_i)``."""
    J = G[0].shape[0]
    out = G[0].new_zeros(J, sum(x.shape[1] for x in G), sum(x.shape[2] for x in G))
    r = c = 0
    for x in G:
        out[:, r:r + x.shape[1], c:c + x.shape[2]] = x
        r, c = r + x.shape[1], c + x.shape[2]
    return out


def _add_stencil(H: torch.Tensor, g: torch.Tensor, v: torch.Tensor, G: torch.Tensor | None, cols: slice,
                 stencil: tuple[float, ...], k: float) -> None:
    """Add the Gauss-Newton terms of residuals ``r_j = k sum_i stencil[i] v_{j+i}`` (``v (J, q)``) whose
    Jacobian wrt ``delta_{j+i}[cols]`` is ``k stencil[i] G_{j+i}`` (``G (J, q, c)``; None: the identity),
    to ``H (J, J, n, n)`` and ``g (J, n)``."""
    S = len(stencil)
    M = v.shape[0] - S + 1
    r = k * sum(a * v[i:i + M] for i, a in enumerate(stencil))                         # (M, q)
    if G is None:       # the identity: blocks k^2 a_i a_i2 I, gradients k a_i r
        eye = torch.eye(v.shape[1], dtype=v.dtype, device=v.device)[..., None]           # (c, c, 1)
        gs = [(k * a) * r for a in stencil]
        blk = [[(k * k * a * a2) * eye for a2 in stencil] for a in stencil]
    else:               # all products in one call: (S, M, c) and (S, S, c, c, M)
        w = k * torch.tensor(stencil, dtype=v.dtype, device=v.device)
        Gs = torch.stack([G[i:i + M] for i in range(S)]) * w[:, None, None, None]
        gs = torch.einsum("smqa,mq->sma", Gs, r)
        blk = torch.einsum("smqa,tmqb->stabm", Gs, Gs)
    for i in range(S):
        g[i:i + M, cols] += gs[i]
        for i2 in range(S):
            # H[m + i, m + i2] for m < M: entries min(i, i2) + m of the block diagonal at offset i2 - i
            t = min(i, i2)
            torch.diagonal(H, offset=i2 - i, dim1=0, dim2=1)[cols, cols, t:t + M] += blk[i][i2]


def projection_jacobian(x: torch.Tensor, K: torch.Tensor, dist: torch.Tensor | None, jacobian: bool = True):
    """Pixels ``(*, N, 2)`` of camera points ``x (*, N, 3)`` and their Jacobian ``d uv / d x (*, N, 2, 3)``
    (``jacobian=False``: the pixels alone).

    Analytic for OpenCV's pinhole model with 0, 4, 5, 8 or 12 distortion coefficients (k1 k2 p1 p2
    [k3 [k4 k5 k6 [s1 s2 s3 s4]]]), skipping the terms whose coefficients are all zero; by reverse-mode
    autograd through :func:`project_points` otherwise. Like ``cv2.projectPoints`` and kornia it reads
    ``fx fy cx cy`` from ``K`` and ignores a skew ``K[0, 1]``.
    """
    D = 0 if dist is None else dist.shape[-1]
    if D not in (0, 4, 5, 8, 12) or K.dim() != 2:
        xg = x.detach().requires_grad_(True)
        with torch.enable_grad():
            uv = project_points(xg, K, dist)
            gu, = torch.autograd.grad(uv[..., 0].sum(), xg, retain_graph=True)
            gv, = torch.autograd.grad(uv[..., 1].sum(), xg)
        return (uv.detach(), torch.stack([gu, gv], -2)) if jacobian else uv.detach()
    c = [0.0] * 12
    if D:
        c[:D] = [float(v) for v in dist]
    k1, k2, p1, p2, k3, k4, k5, k6, s1, s2, s3, s4 = c
    rational, tangential, prism = any(c[5:8]), bool(p1 or p2), any(c[8:])     # terms that are there at all
    iz = 1 / x[..., 2]
    a, b = x[..., 0] * iz, x[..., 1] * iz
    r2 = a * a + b * b
    num = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    den = 1 + r2 * (k4 + r2 * (k5 + r2 * k6)) if rational else 1.0
    rad = num / den if rational else num
    xd, yd = a * rad, b * rad
    if tangential:
        ab2 = 2 * a * b
        xd = xd + p1 * ab2 + p2 * (r2 + 2 * a * a)
        yd = yd + p1 * (r2 + 2 * b * b) + p2 * ab2
    if prism:
        xd = xd + r2 * (s1 + s2 * r2)
        yd = yd + r2 * (s3 + s4 * r2)
    fx, cx, fy, cy = (float(v) for v in (K[0, 0], K[0, 2], K[1, 1], K[1, 2]))   # no skew: as OpenCV and kornia
    uv = torch.stack([fx * xd + cx, fy * yd + cy], -1)
    if not jacobian:
        return uv
    drad = k1 + r2 * (2 * k2 + 3 * k3 * r2)
    if rational:
        drad = (drad * den - num * (k4 + r2 * (2 * k5 + 3 * k6 * r2))) / den ** 2
    # d(xd, yd)/d(a, b) = [[xa, xb], [ya, yb]]
    xa, yb, xb = rad + 2 * a * a * drad, rad + 2 * b * b * drad, 2 * a * b * drad
    ya = xb
    if tangential:
        xa = xa + 2 * p1 * b + 6 * p2 * a
        yb = yb + 6 * p1 * b + 2 * p2 * a
        xb = xb + 2 * p1 * a + 2 * p2 * b
        ya = xb
    if prism:
        tx, ty = s1 + 2 * s2 * r2, s3 + 2 * s4 * r2
        xa, xb = xa + 2 * a * tx, xb + 2 * b * tx
        ya, yb = ya + 2 * a * ty, yb + 2 * b * ty
    # @ d(a, b)/d(x, y, z); d a/dx = 1/z, d a/dz = -a/z
    dxd = torch.stack([xa * iz, xb * iz, -(xa * a + xb * b) * iz], -1)
    dyd = torch.stack([ya * iz, yb * iz, -(ya * a + yb * b) * iz], -1)
    return uv, torch.stack([fx * dxd, fy * dyd], -2)


@torch.no_grad()
def _write_back(fit: SequenceFit, base: list[torch.Tensor]) -> None:
    for name, x in zip(("head_R0", "head_t0", "jaw_R0", "jaw_t0", "coeff0"), base):
        getattr(fit, name).copy_(x.to(getattr(fit, name).dtype))


def solve_base(fit: SequenceFit, actor: ActorAtPoints, obs: Observations, iterations: int,
               tol: float | None = None) -> LMResult:
    """Minimise the fitting energy over ``fit``'s base buffers (networks fixed); updates ``fit`` in place.

    Args:
        fit: the window's state; its base buffers are overwritten with the solution.
        actor: the frozen actor at the fit points; obs: the window's observations.
        iterations: at most this many linearisations.
        tol: stop when an accepted step lowers the energy by less than this fraction
            (default ``fit.settings.lm_tol``).
    """
    tol = fit.settings.lm_tol if tol is None else tol
    prob = _Problem(fit, actor, obs)
    J, n = prob.J, prob.n
    energy = prob.energy()
    energies = [energy]
    mu = 1e-3
    it = accepted = 0
    frames = torch.arange(J)
    while it < iterations:
        H, g = prob.normal_equations(exact_robust=accepted >= REWEIGHTED_STEPS)
        diag = torch.diagonal(H[frames, frames], dim1=-2, dim2=-1).reshape(-1)       # of the (J n, J n) matrix
        diag = diag.clamp_min(1e-12 * float(diag.max()) + 1e-30)
        improved = False
        while it < iterations:
            it += 1
            step = solve_banded_blocks(H, g, prob.frame_bandwidth, mu * diag)
            if step is None:  # not positive definite: damp more
                mu *= 4
                continue
            step = -step.reshape(J, n)
            trial = prob.energy(step)
            if math.isfinite(trial) and trial < energy:
                prob.accept(step)
                accepted += 1
                mu = max(mu / 3, 1e-9)
                improved = energy - trial >= tol * abs(energy)
                energy = trial + prob.retarget()       # the jaw prior's target moves with the step
                energies.append(energy)
                break
            mu *= 4
            if mu > 1e8:
                break
        if not improved:
            break
    _write_back(fit, prob.base)
    return LMResult(energies=energies, iterations=it)
