"""The fitter's state and the actor at the fit points: what a sequence fit optimises, and how it poses the face.

* :class:`ActorAtPoints`: the frozen actor evaluated once at the fit points;
* :func:`pose_face`: ``s* = T_g(LBS(s0, T_b, k) + sum_i w_i E_i)`` for J frames; :func:`pose_face_shared`, the
  same map for coefficients shared by every point, as one matrix product; :func:`shared_pose_maps` and
  :func:`models.mesh_map.map_vertices`, that product's per-frame matrix and a frame's mesh from it (the meshes a fit
  writes);
* :class:`SequenceFit`: frame codes, ``F_T``, ``F_W`` and the per-frame base (the fitter owns every
  per-frame parameter); :class:`FramePose`, :func:`compose_poses`;
* :class:`Observations`: what a window is fitted to.

Pure data and math: the energy is in :mod:`models.fit_energy`, the solvers in :mod:`models.fit`
(Adam on the networks) and :mod:`models.fit_lm` (Levenberg-Marquardt on the base).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from models.checks import check_shapes
from models.fit_settings import FitSettings
from models.lbs import lbs_jaw
from models.quaternion import rotvec_from_matrix
from models.rotation import IDENTITY_6D, apply_rigid, rot6d_to_matrix, so3_exp


def rbf_basis(points: torch.Tensor, centres: torch.Tensor, sigma_mm: float) -> torch.Tensor:
    """Normalised Gaussians ``phi (P, B)`` (rows sum to 1) of template points ``(P, 3)`` around ``centres (B, 3)``.

    Computed in log space (a point far from every centre still gets weights that sum to 1).
    """
    d2 = torch.cdist(points.double(), centres.double()).square()
    return torch.softmax(-d2 / (2.0 * sigma_mm ** 2), dim=1).to(points.dtype)


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
    jaw_rotvec: torch.Tensor | None = None   # (E, 3) learned jaw rotation (axis-angle, rad) of each expression
    jaw_shift: torch.Tensor | None = None    # (E, 3) mm, its jaw translation (None: unknown, rest)
    _features: torch.Tensor | None = field(default=None, init=False, repr=False, compare=False)  # pose_face_shared's

    @classmethod
    @torch.no_grad()
    def query(cls, model, points: torch.Tensor, jaw_rot6d: torch.Tensor | None = None,
              jaw_t: torch.Tensor | None = None, evaluated=None) -> ActorAtPoints:
        """Evaluate ``model`` (an :class:`~models.aim.AnatomicalFaceModel`) at ``points (P, 3)``; with the
        actor's learned per-expression jaw transforms ``jaw_rot6d (E, 6)``, ``jaw_t (E, 3)`` mm.
        ``evaluated``: ``model(points)`` when the caller already has it (not evaluated again)."""
        a = model(points) if evaluated is None else evaluated
        rotvec = shift = None
        if jaw_rot6d is not None and jaw_t is not None:
            R = rot6d_to_matrix(jaw_rot6d.detach().double()).cpu().numpy()
            rotvec = torch.as_tensor(rotvec_from_matrix(R)).to(points)
            shift = jaw_t.detach().to(points)
        return cls(points=points, neutral=a.neutral, skin_weight=a.skin_weight, expressions=a.expressions,
                   jaw_pivot=model.jaw_pivot, center=model.center, scale=float(model.config.scale),
                   jaw_rotvec=rotvec, jaw_shift=shift)

    def jaw_of(self, coeffs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The jaw the expressions ``coeffs (J, E)`` imply: ``exp(sum_i w_i r_i)``, ``sum_i w_i t_i`` with the
        actor's learned jaw transform ``(r_i, t_i)`` of each expression (its training shapes are
        ``LBS(s0, T_b^i) + E_i``); rest (identity, 0) when they are unknown. Returns ``(J, 3, 3)``, ``(J, 3)``."""
        J = coeffs.shape[0]
        if self.jaw_rotvec is None or self.jaw_shift is None:
            return (torch.eye(3, dtype=coeffs.dtype, device=coeffs.device).expand(J, 3, 3),
                    coeffs.new_zeros(J, 3))
        return so3_exp(coeffs @ self.jaw_rotvec.to(coeffs)), coeffs @ self.jaw_shift.to(coeffs)

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


def pose_features(actor: ActorAtPoints) -> torch.Tensor:
    """``(8 + 3E, P)``: each point's ``[s0 (3), k s0 (3), k, E_1 .. E_E (3 each), 1]``, the inputs that
    :func:`pose_face_shared` maps linearly to the posed point (computed once per actor, kept on it)."""
    if actor._features is None:
        x, k, P, E = actor.neutral, actor.skin_weight, actor.neutral.shape[0], actor.n_expressions
        actor._features = torch.cat([x.T, (k[:, None] * x).T, k[None], actor.expressions.permute(1, 2, 0).reshape(3 * E, P),
                                     x.new_ones(1, P)]).contiguous()
    return actor._features


def shared_pose_maps(actor: ActorAtPoints, head_R: torch.Tensor, head_t: torch.Tensor, jaw_R: torch.Tensor,
                     jaw_t: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """``(J, 3, 8 + 3E)``, in ``head_R``'s dtype: for coefficients ``coeffs (J, E)`` shared by every point, the
    matrix ``M_j`` that maps each point's :func:`pose_features` ``f`` to its posed position, ``M_j f``.

    With the jaw ``T_b(x) = R_b (x - p) + p + t_b``:
    ``s* = R_g x + R_g (R_b - I) k x + k R_g ((I - R_b) p + t_b) + sum_i w_i R_g E_i + t_g``. A frame's whole mesh
    is then ``M_j`` (3 x (8 + 3E) numbers: 240 at E = 24) and the actor's features: :func:`pose_face_shared`, and
    :func:`models.mesh_map.map_vertices` where the features are a numpy array (the run's process, a stored fit).
    """
    J, E = coeffs.shape[0], actor.n_expressions
    check_shapes({"coeffs": (coeffs, "J,E"), "expressions": (actor.expressions, "P,E,3"), "head_R": (head_R, "J,3,3"),
                  "head_t": (head_t, "J,3"), "jaw_R": (jaw_R, "J,3,3"), "jaw_t": (jaw_t, "J,3")})
    eye = torch.eye(3, dtype=head_R.dtype, device=head_R.device)
    jaw_offset = (eye - jaw_R) @ actor.jaw_pivot.to(head_R) + jaw_t                      # (J, 3)
    return torch.cat([head_R, head_R @ (jaw_R - eye), (head_R @ jaw_offset.unsqueeze(-1)),
                      torch.einsum("je,jik->jiek", coeffs.to(head_R), head_R).reshape(J, 3, 3 * E),
                      head_t.unsqueeze(-1)], 2)                                           # (J, 3, 8 + 3E)


def pose_face_shared(actor: ActorAtPoints, head_R: torch.Tensor, head_t: torch.Tensor, jaw_R: torch.Tensor,
                     jaw_t: torch.Tensor, coeffs: torch.Tensor) -> torch.Tensor:
    """:func:`pose_face` for coefficients ``coeffs (J, E)`` shared by every point, as one matrix product
    (:func:`shared_pose_maps` with the features): ~2.5 ms for 30 frames of 9,409 points on one core where
    :func:`pose_face`'s skinning, blend and rigid steps take ~22 ms (the same results to float32 rounding,
    ``tests/test_fit.py``). Returns ``(J, P, 3)`` contiguous, mm.
    """
    J = coeffs.shape[0]
    F = pose_features(actor)
    M = shared_pose_maps(actor, head_R, head_t, jaw_R, jaw_t, coeffs)
    return (M.reshape(3 * J, -1).to(F) @ F).reshape(J, 3, -1).transpose(1, 2).contiguous()


def mesh_basis(actor: ActorAtPoints) -> np.ndarray:
    """``(8 + 3E, P)`` float32 numpy: :func:`pose_features`, the basis that :func:`models.mesh_map.map_vertices` maps."""
    return np.ascontiguousarray(pose_features(actor).detach().cpu().numpy(), np.float32)


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
    (:mod:`models.fit_lm`). With ``settings.field_centres > 0`` the state also holds a per-point
    coefficient field (``field_centres (B, 3)``, ``field (J, B, E)``; :mod:`models.fit_field`), part of
    :meth:`net_coefficients` like F_W's output.
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
        # the per-point coefficient field (models.fit_field): centres (B, 3) mm and coefficients (J, B, E)
        B = settings.field_centres
        self.register_buffer("field_centres", head_t0.new_zeros(B, 3))
        self.register_buffer("field", head_t0.new_zeros(n_frames, B, n_expressions))

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """As :meth:`torch.nn.Module.load_state_dict`; states saved without a coefficient field (older
        runs, or fits without one) load with the field at zero, and a field of another number of
        centres than ``settings.field_centres`` (capped to the fitted points) loads as it is."""
        state = dict(state_dict)
        for k in ("field_centres", "field"):
            if k not in state:
                state[k] = getattr(self, k).clone()
            elif state[k].shape != getattr(self, k).shape:   # a field of another size (centres capped to the points)
                self.register_buffer(k, getattr(self, k).new_zeros(state[k].shape))
        return super().load_state_dict(state, strict=strict, assign=assign)

    def field_basis(self, points: torch.Tensor) -> torch.Tensor:
        """``phi (P, B)``: the field's normalised Gaussians at template points ``(P, 3)`` mm."""
        return rbf_basis(points, self.field_centres, self.settings.field_sigma_mm)

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
        """True while F_W's last layer and the coefficient field are exactly zero (their start):
        ``w_j(c)`` is then ``coeff0`` everywhere."""
        last = self.F_W.net[-1]
        return not (bool(last.weight.any()) or bool(last.bias.any()) or bool(self.field.any()))

    def net_coefficients(self, actor: ActorAtPoints, points: torch.Tensor | None = None,
                         frames: slice | None = None) -> torch.Tensor:
        """F_W's part of ``w_j(c)`` ``(J, P, E)`` plus the coefficient field's (without the base offset ``coeff0``)."""
        c = actor.points if points is None else points
        codes = self.codes if frames is None else self.codes[frames]
        last = self.F_W.net[-1]
        if not torch.is_grad_enabled() and not (bool(last.weight.any()) or bool(last.bias.any())):
            out = c.new_zeros(codes.shape[0], c.shape[0], last.out_features)   # F_W at its zero start
        else:
            x = (c - actor.center) / actor.scale
            # F_W's first layer on [z_j, c] split into a per-frame and a per-point part (the same
            # function as concatenating the inputs, without building the (J, P, f + 3) input).
            first = self.F_W.net[0]
            f = codes.shape[1]
            h = (codes @ first.weight[:, :f].T)[:, None, :] + (x @ first.weight[:, f:].T + first.bias)[None]
            out = self.F_W.net[1:](h)
        if self.field.shape[1] and bool(self.field.any()):
            field = self.field if frames is None else self.field[frames]
            out = out + self.field_basis(c) @ field                                 # (P, B) @ (J, B, E)
        return out


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
