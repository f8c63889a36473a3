"""The anatomical implicit face model (AIM): five SIREN networks over template points.

For a template point c (mm, on the template mesh C) the model predicts

* the bone (anatomy) point   ``b = B(c)``        (mm)
* the soft-tissue thickness  ``d = D(c)``        (mm)
* the bone normal            ``n = N(c)``        (unit vector)
* the jaw skinning weight    ``k = K(c)``
* the expression basis       ``E(c)``            ((N-1) x 3, mm)

and builds the neutral skin ``s0 = b + d n`` and training shape i as
``s_i = LBS(s0, T_b^i, k) + E(c)[i]`` (paper, eqs. 1-9).

Scaling (an implementation detail that keeps every network's output near unit size; it changes
no function the model can represent): inputs are normalised to ``(c - center) / scale`` with the
template's bounding box, so they lie in [-1, 1]; B predicts the bone point as an offset from c,
``b = c + bone_offset_mm * B(.)``; D and E are scaled by ``thickness_mm`` and ``expression_mm``;
N is normalised to unit length. At initialisation b is close to c, d and E close to zero, so the
model starts near the template. The networks read a point through the actor's input chart when it has
one (:mod:`models.input_chart`: the template with the mouth a little open, so that the touching lips
are apart); their outputs stay attached to ``c``. An edited actor (``capture actor edit``) multiplies d by the
factors of its ``thickness_edits`` (:mod:`models.anatomy_edit`), functions of c like the networks.

The model is stateless with respect to shapes and frames: per-shape jaw transforms are owned by
the trainer, per-frame parameters by the fitter.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from models.aim_config import AIMConfig  # noqa: F401  (its home before)
from models.checks import check_shape
from models.input_chart import InputChart
from models.lbs import lbs_jaw
from models.rotation import rot6d_to_matrix
from models.siren import Siren


@dataclass
class Anatomy:
    """Model outputs at P template points (all tensors share the batch shape ``*``).

    From :meth:`AnatomicalFaceModel.assemble` with only some networks, the other fields are None.
    """

    bone: torch.Tensor          # (*, P, 3) mm
    thickness: torch.Tensor     # (*, P) mm
    normal: torch.Tensor        # (*, P, 3) unit
    neutral: torch.Tensor       # (*, P, 3) mm, s0 = b + d n
    skin_weight: torch.Tensor   # (*, P) jaw skinning weight k
    expressions: torch.Tensor   # (*, P, N-1, 3) mm, the expression basis E(c)

    def slice(self, start: int, stop: int) -> "Anatomy":
        """The outputs of points ``start:stop`` (flat evaluation, batch shape ``()``)."""
        return Anatomy(*(None if getattr(self, f) is None else getattr(self, f)[start:stop]
                         for f in self.__dataclass_fields__))


class AnatomicalFaceModel(nn.Module):
    """The ensemble of SIRENs B, D, N, K, E (see the module docstring)."""

    def __init__(self, config: AIMConfig):
        super().__init__()
        self.config = config
        siren = dict(width=config.width, depth=config.depth, first_omega_0=config.first_omega_0,
                     hidden_omega_0=config.hidden_omega_0)
        self.B = Siren(3, 3, output_scale=0.1, **siren)
        self.D = Siren(3, 1, output_scale=0.1, **siren)
        self.N = Siren(3, 3, **siren)
        self.K = Siren(3, 1, output_scale=0.1, **siren)
        self.E = Siren(3, 3 * config.n_expressions, output_scale=0.1, **siren)
        self.thickness_edits = nn.ModuleList()  # anatomy edits (models/anatomy_edit.py); empty when learned
        self.chart: InputChart | None = None     # where the networks read c (models/input_chart.py); None: at c
        self.register_buffer("center", torch.tensor(config.center, dtype=torch.float32))
        self.register_buffer("jaw_pivot", torch.tensor(config.jaw_pivot, dtype=torch.float32))

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        """Chart points (mm; :meth:`chart_points`) to network inputs in about [-1, 1]."""
        return (x - self.center) / self.config.scale

    def chart_points(self, c: torch.Tensor, chart_triangles=None) -> torch.Tensor:
        """Where the networks read template points ``c`` ``(*, P, 3)`` mm: ``c`` itself without a chart.
        ``chart_triangles``: the points' triangles (:meth:`models.input_chart.InputChart.locate`), found when None."""
        return c if self.chart is None else self.chart(c, chart_triangles)

    def inputs(self, c: torch.Tensor, chart_triangles=None) -> torch.Tensor:
        """The network inputs of template points ``c`` ``(*, P, 3)`` mm."""
        return self.normalize(self.chart_points(c, chart_triangles))

    def bone(self, c: torch.Tensor) -> torch.Tensor:
        """Bone points ``(*, P, 3)`` mm at template points ``(*, P, 3)``."""
        return c + self.config.bone_offset_mm * self.B(self.inputs(c))

    NETWORKS = ("B", "D", "N", "K", "E")

    def forward(self, c: torch.Tensor, chart_triangles=None) -> Anatomy:
        """Evaluate all five networks at template points ``c`` ``(*, P, 3)`` mm (``chart_triangles``: see
        :meth:`chart_points`; callers under ``torch.func`` transforms locate the points first)."""
        check_shape(c, "*,P,3", "template points")
        x = self.inputs(c, chart_triangles)
        return self.assemble(c, {name: getattr(self, name)(x) for name in self.NETWORKS})

    def assemble(self, c: torch.Tensor, raw: dict[str, torch.Tensor]) -> Anatomy:
        """The model outputs at points ``c`` from the networks' raw outputs ``raw[name]`` ``(*, P, out)``.

        ``forward`` is ``assemble(c, {n: net_n(inputs(c))})``; a trainer that evaluates only some
        networks at some points (or reuses their sine features) passes those, and the outputs of
        the missing networks are None (the neutral needs B, D and N).
        """
        bone = thickness = normal = neutral = k = e = None
        if "B" in raw:
            bone = c + self.config.bone_offset_mm * raw["B"]
        if "D" in raw:
            thickness = self.config.thickness_mm * raw["D"].squeeze(-1)
            for edit in self.thickness_edits:  # d' = d * (1 + (S - 1) w(c)), composed
                thickness = thickness * edit(c)
        if "N" in raw:
            normal = torch.nn.functional.normalize(raw["N"], dim=-1, eps=1e-8)
        if bone is not None and thickness is not None and normal is not None:
            neutral = bone + thickness.unsqueeze(-1) * normal
        if "K" in raw:
            k = raw["K"].squeeze(-1)
        if "E" in raw:
            e = self.config.expression_mm * raw["E"]
            e = e.reshape(*e.shape[:-1], self.config.n_expressions, 3)
        return Anatomy(bone, thickness, normal, neutral, k, e)

    def shape(self, anatomy: Anatomy, jaw_rot6d: torch.Tensor, jaw_t: torch.Tensor,
              coefficients: torch.Tensor) -> torch.Tensor:
        """Skin of an expression: ``LBS(s0, T_b, k) + sum_i w_i E_i``.

        Args:
            anatomy: outputs at P points (batch shape ``()``).
            jaw_rot6d: ``(S, 6)`` jaw rotations; jaw_t: ``(S, 3)`` translations (mm).
            coefficients: ``(S, N-1)`` global or ``(S, P, N-1)`` per-point blend weights w.

        Returns:
            ``(S, P, 3)`` skin points in the head (skull) frame, mm.
        """
        R = rot6d_to_matrix(jaw_rot6d)
        skinned = lbs_jaw(anatomy.neutral.expand(R.shape[0], -1, -1),
                          anatomy.skin_weight.expand(R.shape[0], -1), R, jaw_t, self.jaw_pivot)
        if coefficients.dim() == 2:
            offsets = torch.einsum("se,pec->spc", coefficients, anatomy.expressions)
        else:
            offsets = torch.einsum("spe,pec->spc", coefficients, anatomy.expressions)
        return skinned + offsets

    def training_shapes(self, anatomy: Anatomy, jaw_rot6d: torch.Tensor, jaw_t: torch.Tensor) -> torch.Tensor:
        """All N training shapes ``(N, P, 3)``: the neutral, then shape i = LBS(s0, T_b^i, k) + E_i.

        ``jaw_rot6d (N-1, 6)`` and ``jaw_t (N-1, 3)`` are the learned jaw transforms of the
        non-neutral shapes; the neutral's jaw is at rest by definition.
        """
        R = rot6d_to_matrix(jaw_rot6d)
        n = R.shape[0]
        skinned = lbs_jaw(anatomy.neutral.expand(n, -1, -1), anatomy.skin_weight.expand(n, -1),
                          R, jaw_t, self.jaw_pivot)
        expr = anatomy.expressions.permute(1, 0, 2)  # (N-1, P, 3)
        return torch.cat([anatomy.neutral.unsqueeze(0), skinned + expr], dim=0)
