"""Fitting a frozen actor to a sequence of frames: the paper's neurally reparameterised solve (Sec. 4.2).

Unknowns per frame j: head transform T_g, jaw transform T_b and spatially varying expression
coefficients w(c). They are not optimised directly: frame codes ``z_j`` are, together with two
small GELU MLPs, ``F_T(z_j) -> [T_g, T_b]`` (6D rotation + translation each) and
``F_W(z_j, c) -> w_j(c)``. The face is

    s*(c) = T_g( LBS(s0(c), T_b, k(c)) + sum_i w_i(c) E_i(c) )

with ``s0, k, E`` queried from the frozen actor once at the points being fitted
(:class:`ActorAtPoints`), never per iteration. Losses: 2D position through the calibrated camera
(confidence-weighted, optionally robust), or 3D position; coefficient L2; temporal
``||z_j - z_{j-1}||^2``.

Units: lengths in the losses are divided by ``length_unit_mm`` (10 mm), as in actor learning;
2D residuals are in pixels. The paper's coefficient weight 0.75 over-regularises with faces in
these units (a perfect model plateaus near 0.09 mm in 3D, DESIGN.md measured notes), so the
default preset uses 0.0075; the ``paper`` preset keeps 0.75.

The networks correct a per-frame *base* (head and jaw pose, one offset per expression coefficient;
:class:`SequenceFit`). The paper's fit keeps the base at the initial head pose with the jaw at rest;
the default preset solves it by Levenberg-Marquardt (:mod:`models.fit_lm`) with the networks held
fixed, which converges in a few steps where Adam needs hundreds, and on 2D landmark fits that solve
is the whole fit (``adam_on_landmarks``); 3D fits then run Adam on the networks for the spatially
varying detail and polish the base again.

The fitter owns every per-frame parameter (:class:`SequenceFit`); the actor model stays frozen.
"""

from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, replace

import torch
from torch import nn

from calib.projection import project_points
from models.checks import check_shapes
from models.lbs import lbs_jaw
from models.rotation import IDENTITY_6D, apply_rigid, rot6d_to_matrix


@dataclass(frozen=True)
class FitSettings:
    """Settings of one sequence fit (saved with every run)."""

    iterations: int = 500
    lr: float = 5e-3
    lr_final_fraction: float = 0.1
    """Cosine decay to this fraction of ``lr``; 1.0 keeps it constant (the paper)."""
    code_dim: int = 32
    hidden: int = 128
    coeff_weight: float = 0.0075
    temporal_weight: float = 0.05
    length_unit_mm: float = 10.0
    robust_px: float = 3.0
    """Scale of the pseudo-Huber 2D loss in pixels (quadratic below, linear above); 0 = squared."""
    seed: int = 0
    warm_iterations: int | None = 150
    """Iterations of a window warm-started from the previous one (None: ``iterations``)."""
    early_stop_tol: float = 0.0
    """Stop when the mean loss of the last ``early_stop_every`` iterations improved on the block
    before by less than this fraction (0 = run all iterations, the paper)."""
    early_stop_every: int = 25
    pose_accel_weight: float = 0.0
    """Weight of the squared second differences over frames of the head and jaw transforms
    (translations in ``length_unit_mm``, rotation matrices unit-free): a smooth-motion prior that
    removes per-frame depth jitter of monocular fits. Not in the paper (0 there). This and the next
    two priors apply to 2D fits only (:func:`monocular_priors`)."""
    coeff_temporal_weight: float = 0.0
    """Weight of the squared first differences over frames of the coefficients ``w_j(c)`` (mean over
    points): keeps expressions from flickering. Not in the paper (0 there)."""
    jaw_prior_weight: float = 0.0
    """Weight of the squared distance of the jaw transform from rest (translation in
    ``length_unit_mm``, rotation matrix minus identity): the jaw's translation along the view and an
    opening expression explain landmarks almost alike, and this keeps the jaw where nothing moves it.
    Not in the paper (0 there)."""
    lm_iterations: int = 0
    """Levenberg-Marquardt iterations on each frame's *base* (head and jaw pose, one coefficient
    offset per expression; :mod:`models.fit_lm`) before the Adam iterations, with the networks'
    outputs held fixed. 0 = none (the paper)."""
    lm_polish_iterations: int = 0
    """The same after the Adam iterations (0 = none)."""
    lm_tol: float = 1e-6
    """Levenberg-Marquardt stops when an accepted step lowers the energy by less than this fraction."""
    adam_on_landmarks: bool = True
    """Run the Adam iterations on 2D landmark fits (3D fits always run them). False: a 2D fit is the
    Levenberg-Marquardt solve of the base alone and the networks keep their zero start (on synthetic
    takes with 1,000 landmarks the Adam phase changed the error by < 0.001 mm at 10x the time)."""

    def to_dict(self) -> dict:
        return asdict(self)


FIT_PRESETS: dict[str, FitSettings] = {
    # hidden 64: 3x cheaper than 128 per iteration at the same accuracy on synthetic takes;
    # temporal 0.5: codes of neighbouring frames held closer than the paper's 0.05, which halves the
    # per-frame depth jitter of monocular fits (benchmarks/bench_fit.py).
    # The base (head and jaw pose, per-frame coefficient offsets) by Levenberg-Marquardt before and
    # after Adam, with smooth-motion, jaw-at-rest and coefficient-smoothness priors; on 2D takes the
    # solve is the base alone (adam_on_landmarks). Weights chosen on a synthetic 1280x720 take of the
    # demo actor with 1,000 landmarks (benchmarks/bench_fit.py, BENCHMARKS.md "Take fitting").
    "default": FitSettings(hidden=64, lr=1e-2, temporal_weight=0.5, early_stop_tol=2e-3, lm_iterations=10,
                           lm_polish_iterations=10, pose_accel_weight=10.0, coeff_temporal_weight=1.0,
                           jaw_prior_weight=0.01, adam_on_landmarks=False),
    "paper": FitSettings(iterations=10_000, lr=1e-3, lr_final_fraction=1.0, coeff_weight=0.75, robust_px=0.0,
                         warm_iterations=None),
}


@dataclass
class ActorAtPoints:
    """The frozen actor evaluated once at P template points (mm)."""

    points: torch.Tensor        # (P, 3) template points c
    neutral: torch.Tensor       # (P, 3) s0
    skin_weight: torch.Tensor   # (P,) k
    expressions: torch.Tensor   # (P, E, 3) expression basis
    jaw_pivot: torch.Tensor     # (3,)
    center: torch.Tensor        # (3,) template normalisation, for F_W's input
    scale: float

    @classmethod
    @torch.no_grad()
    def query(cls, model, points: torch.Tensor) -> "ActorAtPoints":
        """Evaluate ``model`` (an :class:`~models.aim.AnatomicalFaceModel`) at ``points (P, 3)``."""
        a = model(points)
        return cls(points=points, neutral=a.neutral, skin_weight=a.skin_weight, expressions=a.expressions,
                   jaw_pivot=model.jaw_pivot, center=model.center, scale=float(model.config.scale))

    @property
    def n_expressions(self) -> int:
        return self.expressions.shape[1]


def pose_face(actor: ActorAtPoints, head_R: torch.Tensor, head_t: torch.Tensor, jaw_R: torch.Tensor,
              jaw_t: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """``s* = T_g(LBS(s0, T_b, k) + sum_i w_i E_i)`` for J frames.

    Args: head_R, jaw_R ``(J, 3, 3)``; head_t, jaw_t ``(J, 3)`` mm; coeffs ``(J, P, E)``, or
        ``(J, 1, E)`` for coefficients that are the same at every point (one matrix product).
    Returns: ``(J, P, 3)`` points in the camera frame (mm) when T_g maps head to camera.
    """
    J, P, E = coeffs.shape[0], actor.expressions.shape[0], actor.expressions.shape[1]
    if coeffs.shape[1] == 1 and P != 1:
        check_shapes({"coeffs": (coeffs, "J,1,E"), "expressions": (actor.expressions, "P,E,3")})
        disp = (coeffs[:, 0] @ actor.expressions.permute(1, 0, 2).reshape(E, P * 3)).reshape(J, P, 3)
    else:
        check_shapes({"coeffs": (coeffs, "J,P,E"), "expressions": (actor.expressions, "P,E,3")})
        disp = torch.einsum("jpe,pec->jpc", coeffs, actor.expressions)
    skinned = lbs_jaw(actor.neutral.expand(J, -1, -1), actor.skin_weight.expand(J, -1), jaw_R, jaw_t,
                      actor.jaw_pivot)
    return apply_rigid(skinned + disp, head_R, head_t)


class GeluMLP(nn.Module):
    """Four linear layers with GELU between them; the last layer starts at zero output."""

    def __init__(self, n_in: int, n_out: int, hidden: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(n_in, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(),
                                 nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, n_out))
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


@dataclass
class FramePose:
    """Per-frame parameters (J frames)."""

    head_R: torch.Tensor   # (J, 3, 3) head (template frame) -> camera
    head_t: torch.Tensor   # (J, 3) mm
    jaw_R: torch.Tensor    # (J, 3, 3) jaw about the actor's jaw pivot
    jaw_t: torch.Tensor    # (J, 3) mm


class SequenceFit(nn.Module):
    """Frame codes, F_T and F_W for J frames: the fitter's state.

    The networks predict corrections on top of a per-frame *base* (buffers, not optimised by Adam):
    the head pose ``head_R0, head_t0`` (for example a PnP estimate), the jaw pose ``jaw_R0, jaw_t0``
    (rest: identity, 0) and an offset ``coeff0 (J, E)`` added to ``w_j(c)`` at every point (0).
    A zero network output - the state at initialisation - is the base itself. The paper's fit keeps
    the jaw and coefficient base at rest; the default preset solves the base by Levenberg-Marquardt
    (:mod:`models.fit_lm`).
    """

    def __init__(self, n_frames: int, n_expressions: int, settings: FitSettings,
                 head_R0: torch.Tensor, head_t0: torch.Tensor):
        super().__init__()
        check_shapes({"head_R0": (head_R0, "J,3,3"), "head_t0": (head_t0, "J,3")})
        g = torch.Generator().manual_seed(settings.seed)
        self.settings = settings
        self.codes = nn.Parameter(0.01 * torch.randn(n_frames, settings.code_dim, generator=g).to(head_t0))
        self.F_T = GeluMLP(settings.code_dim, 18, settings.hidden).to(head_t0)
        self.F_W = GeluMLP(settings.code_dim + 3, n_expressions, settings.hidden).to(head_t0)
        self.register_buffer("head_R0", head_R0.clone())
        self.register_buffer("head_t0", head_t0.clone())
        self.register_buffer("jaw_R0", torch.eye(3).to(head_t0).expand(n_frames, 3, 3).clone())
        self.register_buffer("jaw_t0", head_t0.new_zeros(n_frames, 3))
        self.register_buffer("coeff0", head_t0.new_zeros(n_frames, n_expressions))
        self.register_buffer("eye6", torch.tensor(IDENTITY_6D).to(head_t0))

    def net_poses(self) -> FramePose:
        """F_T's corrections: rotations ``(J, 3, 3)`` (right-multiplied) and translations ``(J, 3)`` mm (added)."""
        out = self.F_T(self.codes)
        unit = self.settings.length_unit_mm
        return FramePose(rot6d_to_matrix(self.eye6 + out[:, 0:6]), unit * out[:, 6:9],
                         rot6d_to_matrix(self.eye6 + out[:, 9:15]), unit * out[:, 15:18])

    def poses(self) -> FramePose:
        return compose_poses(self.head_R0, self.head_t0, self.jaw_R0, self.jaw_t0, self.net_poses())

    def coefficients(self, actor: ActorAtPoints, points: torch.Tensor | None = None,
                     frames: slice | None = None) -> torch.Tensor:
        """``w_j(c)`` ``(J, P, E)`` at ``points`` (default: the actor's points), for ``frames`` (default all)."""
        sl = slice(None) if frames is None else frames
        return self.net_coefficients(actor, points, frames) + self.coeff0[sl, None, :]

    def net_is_zero(self) -> bool:
        """True while F_W's last layer is exactly zero (its start): ``w_j(c)`` is then ``coeff0`` everywhere."""
        last = self.F_W.net[-1]
        return not (bool(last.weight.any()) or bool(last.bias.any()))

    def net_coefficients(self, actor: ActorAtPoints, points: torch.Tensor | None = None,
                         frames: slice | None = None) -> torch.Tensor:
        """F_W's part of ``w_j(c)`` ``(J, P, E)`` (without the base offset ``coeff0``)."""
        c = actor.points if points is None else points
        codes = self.codes if frames is None else self.codes[frames]
        if not torch.is_grad_enabled() and self.net_is_zero():
            return c.new_zeros(codes.shape[0], c.shape[0], self.F_W.net[-1].out_features)
        x = (c - actor.center) / actor.scale
        # F_W's first layer on [z_j, c] split into a per-frame and a per-point part (the same
        # function as concatenating the inputs, without building the (J, P, f + 3) input).
        first = self.F_W.net[0]
        f = codes.shape[1]
        h = (codes @ first.weight[:, :f].T)[:, None, :] + (x @ first.weight[:, f:].T + first.bias)[None]
        return self.F_W.net[1:](h)


def compose_poses(head_R0: torch.Tensor, head_t0: torch.Tensor, jaw_R0: torch.Tensor, jaw_t0: torch.Tensor,
                  net: FramePose) -> FramePose:
    """Base pose then the network's correction: ``R = R0 @ dR``, ``t = t0 + dt`` for head and jaw."""
    return FramePose(head_R0 @ net.head_R, head_t0 + net.head_t, jaw_R0 @ net.jaw_R, jaw_t0 + net.jaw_t)


@dataclass
class Observations:
    """What a sequence is fitted to: 2D landmarks (with a camera) or 3D points."""

    points2d: torch.Tensor | None = None   # (J, P, 2) pixels; NaN where missing
    weights: torch.Tensor | None = None    # (J, P) confidence in [0, 1]; 0 where missing
    K: torch.Tensor | None = None          # (3, 3)
    dist: torch.Tensor | None = None       # (D,)
    points3d: torch.Tensor | None = None   # (J, P, 3) mm, camera frame


def fitting_losses(fit: SequenceFit, actor: ActorAtPoints, obs: Observations) -> dict[str, torch.Tensor]:
    """The weighted loss terms of the fitting energy; key ``total`` sums them."""
    s = fit.settings
    terms = energy_terms(actor, obs, s, fit.poses(), fit.coefficients(actor))
    if fit.codes.shape[0] > 1:
        terms["temporal"] = s.temporal_weight * (fit.codes[1:] - fit.codes[:-1]).square().sum(-1).mean()
    terms["total"] = sum(terms.values())
    return terms


def robust_2d(r2: torch.Tensor, robust_px: float) -> torch.Tensor:
    """The 2D loss of squared pixel distances ``r2``: pseudo-Huber with scale ``robust_px`` (0: ``r2``)."""
    if robust_px <= 0:
        return r2
    c2 = robust_px ** 2
    return 2 * c2 * (torch.sqrt(1 + r2 / c2) - 1)  # pseudo-Huber: r^2 near 0, 2c|r| far


def observation_weights(obs: Observations, dtype: torch.dtype) -> torch.Tensor:
    """``(J, P)`` weights of the 2D landmarks: confidence where finite, 0 where missing."""
    valid = torch.isfinite(obs.points2d).all(-1)
    return (obs.weights if obs.weights is not None else valid.to(dtype)) * valid


def monocular_priors(s: FitSettings, obs: Observations) -> FitSettings:
    """``s`` as it applies to ``obs``: the smooth-motion, coefficient-smoothness and jaw priors steady
    monocular (2D-only) fits; with 3D observations there is no depth ambiguity and they are off."""
    if obs.points3d is None:
        return s
    return replace(s, pose_accel_weight=0.0, coeff_temporal_weight=0.0, jaw_prior_weight=0.0)


def energy_terms(actor: ActorAtPoints, obs: Observations, s: FitSettings, pose: FramePose,
                 w: torch.Tensor) -> dict[str, torch.Tensor]:
    """The terms of the fitting energy that depend on the poses and coefficients ``w (J, P, E)``."""
    s = monocular_priors(s, obs)
    face = pose_face(actor, pose.head_R, pose.head_t, pose.jaw_R, pose.jaw_t, w)
    terms: dict[str, torch.Tensor] = {}
    if obs.points2d is not None:
        uv = project_points(face, obs.K, obs.dist)
        weight = observation_weights(obs, face.dtype)
        r2 = (uv - torch.nan_to_num(obs.points2d)).square().sum(-1)
        terms["2d"] = (weight * robust_2d(r2, s.robust_px)).sum() / weight.sum().clamp_min(1e-12)
    if obs.points3d is not None:
        terms["3d"] = ((face - obs.points3d) / s.length_unit_mm).square().sum(-1).mean()
    terms["coeff"] = s.coeff_weight * w.square().mean()
    J = w.shape[0]
    if s.pose_accel_weight > 0 and J > 2:
        acc = lambda x: (x[2:] - 2 * x[1:-1] + x[:-2]).flatten(1).square().sum(-1).mean()
        unit = s.length_unit_mm
        terms["pose_accel"] = s.pose_accel_weight * (acc(pose.head_t / unit) + acc(pose.head_R) +
                                                     acc(pose.jaw_t / unit) + acc(pose.jaw_R))
    if s.jaw_prior_weight > 0:
        eye = torch.eye(3, dtype=w.dtype, device=w.device)
        terms["jaw"] = s.jaw_prior_weight * ((pose.jaw_t / s.length_unit_mm).square().sum(-1).mean() +
                                             (pose.jaw_R - eye).square().sum((-1, -2)).mean())
    if s.coeff_temporal_weight > 0 and J > 1:
        terms["coeff_temporal"] = s.coeff_temporal_weight * (w[1:] - w[:-1]).square().sum(-1).mean()
    return terms


@dataclass
class FitResult:
    fit: SequenceFit
    losses: list[float]          # Adam iterations' energies
    seconds: float
    lm_iterations: int = 0       # Levenberg-Marquardt linearisations (before and after Adam)


def fit_sequence(actor: ActorAtPoints, obs: Observations, settings: FitSettings, head_R0: torch.Tensor,
                 head_t0: torch.Tensor, warm_start: dict | None = None, callback=None,
                 iterations: int | None = None) -> FitResult:
    """Fit J frames; ``warm_start`` is a :class:`SequenceFit` state dict of the same size to start from.

    ``iterations`` overrides ``settings.iterations`` (the cosine schedule spans it); with
    ``settings.early_stop_tol > 0`` the loop may stop earlier (see :class:`FitSettings`). With
    ``settings.lm_iterations`` / ``lm_polish_iterations`` the base is solved by Levenberg-Marquardt
    before / after the Adam iterations (:func:`models.fit_lm.solve_base`).
    """
    from models.fit_lm import solve_base

    n_it = settings.iterations if iterations is None else int(iterations)
    if obs.points3d is None and not settings.adam_on_landmarks:
        n_it = 0
    torch.manual_seed(settings.seed)
    fit = SequenceFit(head_R0.shape[0], actor.n_expressions, settings, head_R0, head_t0)
    if warm_start is not None:
        fit.load_state_dict(warm_start)
    t0 = time.perf_counter()
    n_lm = 0
    if settings.lm_iterations > 0:
        n_lm += solve_base(fit, actor, obs, settings.lm_iterations).iterations
    opt = torch.optim.Adam(fit.parameters(), lr=settings.lr)
    f = settings.lr_final_fraction
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda it: 1.0 if f >= 1 else f + (1 - f) * 0.5 * (1 + math.cos(math.pi * min(it / max(n_it, 1), 1))))
    history = []
    every = max(1, settings.early_stop_every)
    for it in range(n_it):
        terms = fitting_losses(fit, actor, obs)
        opt.zero_grad(set_to_none=True)
        terms["total"].backward()
        opt.step()
        sched.step()
        history.append(float(terms["total"].detach()))
        if callback is not None:
            callback(it, terms)
        if settings.early_stop_tol > 0 and (it + 1) % every == 0 and it + 1 >= 2 * every:
            last = sum(history[-every:]) / every
            before = sum(history[-2 * every:-every]) / every
            if before - last < settings.early_stop_tol * abs(before):
                break
    if settings.lm_polish_iterations > 0:
        n_lm += solve_base(fit, actor, obs, settings.lm_polish_iterations).iterations
    return FitResult(fit=fit, losses=history, seconds=time.perf_counter() - t0, lm_iterations=n_lm)
