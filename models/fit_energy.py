"""The fitting energy of a sequence fit: data terms (2D landmarks, 3D points) and priors.

:func:`energy_terms` is the energy as a function of poses and coefficients (used by Adam through
:func:`fitting_losses`, and mirrored term by term by the Levenberg-Marquardt solver of
:mod:`models.fit_lm`).
"""

from __future__ import annotations

from dataclasses import replace

import torch

from calib.projection import project_points
from models.fit_settings import FitSettings
from models.fit_state import (
    ActorAtPoints,
    FramePose,
    Observations,
    SequenceFit,
    pose_face,
)


def fitting_losses(fit: SequenceFit, actor: ActorAtPoints, obs: Observations) -> dict[str, torch.Tensor]:
    """The weighted loss terms of the fitting energy; key ``total`` sums them."""
    s = fit.settings
    terms = energy_terms(actor, obs, s, fit.poses(), fit.coefficients(actor))
    if fit.codes.shape[0] > 1:
        terms["temporal"] = s.temporal_weight * (fit.codes[1:] - fit.codes[:-1]).square().sum(-1).mean()
    terms["total"] = sum(terms.values())
    return terms


def squared_norm(x: torch.Tensor) -> torch.Tensor:
    """``|x|^2`` over a short last axis (2D or 3D residuals): ``(*, k) -> (*)``. The same as
    ``x.square().sum(-1)``, which torch's CPU reduction over an axis of 2 or 3 makes about 10x slower
    (250 us against 20 us for 30 x 468 pixel residuals in float64)."""
    parts = x.unbind(-1)
    out = parts[0] * parts[0]
    for p in parts[1:]:
        out = out.addcmul(p, p)
    return out


def robust_2d(r2: torch.Tensor, robust_px: float) -> torch.Tensor:
    """The 2D loss of squared pixel distances ``r2``: pseudo-Huber with scale ``robust_px`` (0: ``r2``)."""
    if robust_px <= 0:
        return r2
    c2 = robust_px ** 2
    return 2 * c2 * (torch.sqrt(1 + r2 / c2) - 1)  # pseudo-Huber: r^2 near 0, 2c|r| far


def irls_sqrt_weights(r: torch.Tensor, w2d: torch.Tensor, robust_px: float) -> torch.Tensor:
    """``(J, P, 1)`` square roots of the Gauss-Newton weights of 2D residuals ``r (J, P, 2)`` px with
    confidences ``w2d (J, P)``: the pseudo-Huber loss of :func:`robust_2d` as iteratively reweighted
    least squares (weight ``1 / sqrt(1 + |r|^2 / c^2)``), normalised like the 2D term's weighted mean."""
    drho = torch.ones_like(r[..., 0]) if robust_px <= 0 else torch.rsqrt(1 + squared_norm(r) / robust_px ** 2)
    return torch.sqrt(w2d * drho / w2d.sum().clamp_min(1e-12))[..., None]


def robust_2d_linearised(r: torch.Tensor, Jp: torch.Tensor, w2d: torch.Tensor, robust_px: float,
                         exact: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """The 2D term's Gauss-Newton rows with the robust loss's own curvature (Triggs et al., "Bundle
    adjustment - a modern synthesis", 2000, sec. 4.3; Ceres' ``Corrector``): ``(D, rs)`` with
    ``D (J, P, 2, m)`` and ``rs (J, P, 2)`` such that per point

    * ``D^T D = Jp^T H Jp`` where ``H = w / sum(w) (rho' I + 2 rho'' r r^T)`` is half the Hessian of the
      point's loss ``w rho(|r|^2) / sum(w)`` in ``r`` (:func:`robust_2d`), and
    * ``D^T rs = Jp^T w rho' r / sum(w)``, half its gradient,

    for residuals ``r (J, P, 2)`` px, their Jacobian ``Jp (J, P, 2, m)`` and confidences ``w2d (J, P)``.
    Plain IRLS (:func:`irls_sqrt_weights`) drops the ``rho''`` part: it takes the loss as twice as curved
    as it is along ``r`` at 1 px for the 1 px pseudo-Huber, so its steps fall short and it converges
    linearly (each step removed ~57 % of the remaining energy gap on a take). For the pseudo-Huber loss
    ``rho' + 2 |r|^2 rho'' = rho' / (1 + |r|^2 / c^2) > 0``: ``H`` is positive definite and
    ``D = sqrt(w rho' / sum w) (I - alpha r^ r^T) Jp`` with ``1 - alpha = (1 + |r|^2 / c^2)^(-1/2)``.

    Far from the minimum, where many residuals lie in the loss's linear part, that curvature is small
    and a step by it overshoots; plain IRLS majorises the loss there and is the safe step. With
    ``exact=False`` the rows are IRLS's: ``D = sqrt(w rho' / sum w) Jp``, ``rs = sqrt(w rho' / sum w) r``."""
    sw = irls_sqrt_weights(r, w2d, robust_px)                                         # (J, P, 1)
    if robust_px <= 0 or not exact:
        return sw[..., None] * Jp, sw * r
    r2 = squared_norm(r)[..., None]                                                    # (J, P, 1)
    keep = torch.rsqrt(1 + r2 / robust_px ** 2)                                       # 1 - alpha
    # (I - alpha r^ r^T) Jp = Jp - r (alpha / |r|^2) (r^T Jp), row by row (no (J, P, 2, m) outer product)
    J0, J1 = Jp.unbind(-2)                                                            # (J, P, m)
    rJ = r[..., 0:1] * J0 + r[..., 1:2] * J1                                          # r^T Jp
    ar = (sw * (1 - keep) / r2.clamp_min(1e-300)) * r                                # 0 where r = 0
    D = torch.stack([sw * J0 - ar[..., 0:1] * rJ, sw * J1 - ar[..., 1:2] * rJ], -2)
    return D, sw * r / keep


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


def jaw_prior_target(actor: ActorAtPoints, s: FitSettings, coeffs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the jaw prior pulls the jaw of J frames with mean coefficients ``coeffs (J, E)``:
    ``(R (J, 3, 3), t (J, 3) mm)`` (see :attr:`FitSettings.jaw_prior_target`)."""
    if s.jaw_prior_target == "expressions":
        return actor.jaw_of(coeffs)
    if s.jaw_prior_target != "rest":
        raise ValueError(f"jaw_prior_target must be 'rest' or 'expressions', got {s.jaw_prior_target!r}")
    J = coeffs.shape[0]
    return torch.eye(3, dtype=coeffs.dtype, device=coeffs.device).expand(J, 3, 3), coeffs.new_zeros(J, 3)


def energy_terms(actor: ActorAtPoints, obs: Observations, s: FitSettings, pose: FramePose,
                 w: torch.Tensor) -> dict[str, torch.Tensor]:
    """The terms of the fitting energy that depend on the poses and coefficients ``w (J, P, E)``."""
    s = monocular_priors(s, obs)
    face = pose_face(actor, pose.head_R, pose.head_t, pose.jaw_R, pose.jaw_t, w)
    terms: dict[str, torch.Tensor] = {}
    if obs.points2d is not None:
        uv = project_points(face, obs.K, obs.dist)
        weight = observation_weights(obs, face.dtype)
        r2 = squared_norm(uv - torch.nan_to_num(obs.points2d))
        terms["2d"] = (weight * robust_2d(r2, s.robust_px)).sum() / weight.sum().clamp_min(1e-12)
    if obs.points3d is not None:
        terms["3d"] = squared_norm((face - obs.points3d) / s.length_unit_mm).mean()
    terms["coeff"] = s.coeff_weight * w.square().mean()
    J = w.shape[0]
    if s.pose_accel_weight > 0 and J > 2:
        acc = lambda x: (x[2:] - 2 * x[1:-1] + x[:-2]).flatten(1).square().sum(-1).mean()
        unit = s.length_unit_mm
        terms["pose_accel"] = s.pose_accel_weight * (acc(pose.head_t / unit) + acc(pose.head_R) +
                                                     acc(pose.jaw_t / unit) + acc(pose.jaw_R))
    if s.jaw_prior_weight > 0:
        tR, tt = jaw_prior_target(actor, s, w.mean(1))
        terms["jaw"] = s.jaw_prior_weight * (((pose.jaw_t - tt) / s.length_unit_mm).square().sum(-1).mean() +
                                             (pose.jaw_R - tR).square().sum((-1, -2)).mean())
    if s.coeff_temporal_weight > 0 and J > 1:
        terms["coeff_temporal"] = s.coeff_temporal_weight * (w[1:] - w[:-1]).square().sum(-1).mean()
    return terms
