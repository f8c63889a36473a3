"""The architecture and normalisation of an actor model (:class:`AIMConfig`, saved in the actor package).

Plain data, no torch: an actor's package is checked without importing torch. :mod:`models.aim`
re-exports it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class AIMConfig:
    """Architecture and normalisation of an actor model (saved in the actor package)."""

    n_expressions: int
    """N - 1: number of non-neutral training shapes (columns of the expression basis)."""
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Centre of the template's bounding box (mm)."""
    scale: float = 100.0
    """Half the largest side of the template's bounding box (mm)."""
    jaw_pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Centre of jaw rotation (mm), near the temporomandibular joint."""
    width: int = 256
    depth: int = 3
    first_omega_0: float = 30.0
    hidden_omega_0: float = 1.0
    bone_offset_mm: float = 10.0
    thickness_mm: float = 10.0
    expression_mm: float = 10.0

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "AIMConfig":
        unknown = set(d) - set(cls.__dataclass_fields__)
        if unknown:
            raise ValueError(f"unknown AIMConfig fields: {sorted(unknown)}")
        d = dict(d)
        for key in ("center", "jaw_pivot"):
            if key in d:
                d[key] = tuple(float(v) for v in d[key])
        return cls(**d)
