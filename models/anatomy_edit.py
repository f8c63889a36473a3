"""Anatomy editing: scale the learned soft-tissue thickness in a painted region (paper, Sec. 5.2).

The networks of an actor are implicit functions of the template point c, and the product evaluates
them wherever it needs (vertices, landmarks at barycentric points, samples), so an edit must be a
function of c too. A :class:`ThicknessEdit` is

    d'(c) = d(c) * (1 + (S - 1) w(c))

with the scale S and a region weight w(c) in [0, 1] built from the painted template vertices v_i
(mm, on the template C) with mask values m_i in (0, 1]:

    w(c) = max_i  m_i * phi((|c - v_i| - h) / r),    phi(t) = 1 - smoothstep(clamp(t, 0, 1))

* ``h`` (core, mm): points within h of a painted vertex get the vertex's full mask value, so points
  inside painted triangles (landmarks at barycentric points) are scaled (nearly) like the vertices
  around them; ``capture actor edit`` uses half the template's mean edge length by default.
* ``r`` (falloff, mm): beyond the core the weight falls smoothly (C1) to zero over r mm; at
  ``|c - v_i| >= h + r`` from every painted vertex the thickness, and so the skin, is unchanged
  exactly (r = 0: a hard edge at h).

Through the anatomical formulation (``s0 = b + d n``) the neutral moves along the bone normal by
``(d' - d) n``; every expression ``LBS(s0, T_b, k) + E`` follows (the LBS is affine in s0).
Edits compose: the factors of several edits multiply. Everything is a buffer of the module, so the
edit travels inside ``weights.safetensors`` and the weights' hash covers it.
"""

from __future__ import annotations

import torch
from torch import nn

from models.checks import check_shape, check_shapes


def region_weight(c: torch.Tensor, points: torch.Tensor, mask: torch.Tensor, core_mm: float,
                  falloff_mm: float, chunk: int = 4096) -> torch.Tensor:
    """The region weight ``w(c)`` ``(*, P)`` in [0, 1] (see the module docstring).

    Args:
        c: ``(*, P, 3)`` template points, mm.
        points: ``(M, 3)`` painted template vertices, mm.
        mask: ``(M,)`` their mask values in (0, 1].
        core_mm, falloff_mm: h and r, mm (>= 0).
        chunk: points per distance block (memory: chunk x M floats).
    """
    check_shape(c, "*,P,3", "template points")
    check_shapes({"points": (points, "M,3"), "mask": (mask, "M")})
    if core_mm < 0 or falloff_mm < 0:
        raise ValueError(f"core and falloff must be >= 0 mm, got {core_mm}, {falloff_mm}")
    flat = c.reshape(-1, 3)
    pts, m = points.to(flat), mask.to(flat)
    out = torch.empty(flat.shape[0], dtype=flat.dtype, device=flat.device)
    for s in range(0, flat.shape[0], chunk):
        d = torch.cdist(flat[s:s + chunk], pts)                              # (chunk, M) mm
        if falloff_mm > 0:
            t = ((d - core_mm) / falloff_mm).clamp(0.0, 1.0)
            phi = 1.0 - t * t * (3.0 - 2.0 * t)
        else:
            phi = (d <= core_mm).to(d.dtype)
        out[s:s + chunk] = (m * phi).amax(dim=1)
    return out.reshape(c.shape[:-1])


class ThicknessEdit(nn.Module):
    """A thickness scale S over a painted region: ``forward(c)`` is the factor ``1 + (S - 1) w(c)``."""

    def __init__(self, points: torch.Tensor, mask: torch.Tensor, scale: float, falloff_mm: float, core_mm: float):
        super().__init__()
        check_shapes({"points": (points, "M,3"), "mask": (mask, "M")})
        if not (scale > 0 and torch.isfinite(torch.as_tensor(scale))):
            raise ValueError(f"thickness scale must be positive, got {scale}")
        if not bool(((mask > 0) & (mask <= 1)).all()):
            raise ValueError("mask values must lie in (0, 1]")
        self.register_buffer("points", points.detach().to(torch.float32).clone())
        self.register_buffer("mask", mask.detach().to(torch.float32).clone())
        # scale, falloff_mm, core_mm: a buffer, so the settings live in the weights file with the region
        self.register_buffer("settings", torch.tensor([scale, falloff_mm, core_mm], dtype=torch.float32))

    @classmethod
    def empty(cls, n_points: int) -> "ThicknessEdit":
        """A placeholder of the right buffer sizes, to load a saved state dict into."""
        return cls(torch.zeros(n_points, 3), torch.ones(n_points), 1.0, 0.0, 0.0)

    @property
    def scale(self) -> float:
        return float(self.settings[0])

    @property
    def falloff_mm(self) -> float:
        return float(self.settings[1])

    @property
    def core_mm(self) -> float:
        return float(self.settings[2])

    def weight(self, c: torch.Tensor) -> torch.Tensor:
        """``w(c)`` ``(*, P)`` at template points ``(*, P, 3)`` mm."""
        return region_weight(c, self.points, self.mask, self.core_mm, self.falloff_mm)

    def forward(self, c: torch.Tensor) -> torch.Tensor:
        """The thickness factor ``1 + (S - 1) w(c)`` ``(*, P)``; exactly 1 outside region and falloff."""
        return 1.0 + (self.settings[0].to(c) - 1.0) * self.weight(c)


def edits_from_state(state: dict[str, torch.Tensor], prefix: str = "thickness_edits.") -> list[ThicknessEdit]:
    """Empty :class:`ThicknessEdit` modules matching the edits saved in a model state dict (in order)."""
    edits = []
    while f"{prefix}{len(edits)}.points" in state:
        edits.append(ThicknessEdit.empty(state[f"{prefix}{len(edits)}.points"].shape[0]))
    return edits
