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
is the whole fit (``adam_on_landmarks``). The spatially varying detail of 3D fits comes, by default
(:data:`FIT3D_PRESETS`), from a dense per-point coefficient field solved in closed form
(:mod:`models.fit_field`); with Adam iterations (the ``networks`` and ``paper`` presets) F_T/F_W are
trained for it and the base is polished again.

The fitter owns every per-frame parameter (:class:`SequenceFit`); the actor model stays frozen.

Modules: settings and presets in :mod:`models.fit_settings`, the state (:class:`SequenceFit`,
:class:`ActorAtPoints`, :class:`Observations`) in :mod:`models.fit_state`, the energy in
:mod:`models.fit_energy`, the Levenberg-Marquardt base solve in :mod:`models.fit_lm` and the
per-point coefficient field (``--preset field`` of 2D fits, the 3D default) in :mod:`models.fit_field`; this module
runs them (:func:`fit_sequence`) and re-exports their public names. None imports this one.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import torch

from models.fit_energy import (  # noqa: F401
    energy_terms,
    fitting_losses,
    monocular_priors,
    observation_weights,
    robust_2d,
)
from models.fit_field import solve_field
from models.fit_lm import solve_base
from models.fit_settings import FIT3D_PRESETS, FIT_PRESETS, FitSettings  # noqa: F401
from models.fit_state import (  # noqa: F401
    ActorAtPoints,
    FramePose,
    GeluMLP,
    Observations,
    SequenceFit,
    compose_poses,
    pose_face,
    pose_face_shared,
)


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
    history = []
    if n_it > 0:   # torch.optim imports torch._dynamo on first use (~1-3 s): only when Adam runs
        opt = torch.optim.Adam(fit.parameters(), lr=settings.lr)
        f = settings.lr_final_fraction
        sched = torch.optim.lr_scheduler.LambdaLR(
            opt, lambda it: 1.0 if f >= 1 else f + (1 - f) * 0.5 * (1 + math.cos(math.pi * min(it / max(n_it, 1), 1))))
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
    field = settings.field_centres > 0 and settings.field_iterations > 0
    if field:
        n_lm += solve_field(fit, actor, obs, settings.field_iterations)
    # the polish solves the base again after what moved it: with no Adam iteration and no field it would
    # start at the first solve's own minimum
    if settings.lm_polish_iterations > 0 and (len(history) > 0 or field or settings.lm_iterations == 0):
        n_lm += solve_base(fit, actor, obs, settings.lm_polish_iterations).iterations
        if field:
            n_lm += solve_field(fit, actor, obs, settings.field_iterations)
    return FitResult(fit=fit, losses=history, seconds=time.perf_counter() - t0, lm_iterations=n_lm)
