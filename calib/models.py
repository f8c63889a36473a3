"""Lens distortion models a calibration can fit, as OpenCV flag sets.

Each model is a set of free OpenCV distortion terms; the others are held at zero. Models are named
by their terms:

========== ===================================== ============ ======
name       free terms                            OpenCV flags  dist
========== ===================================== ============ ======
k1-k2      k1 k2                                 FIX_K3, ZERO_TANGENT_DIST  5
k1-k2+p    k1 k2 p1 p2                           FIX_K3       5
k1-k3      k1 k2 k3                              ZERO_TANGENT_DIST  5
k1-k3+p    k1 k2 p1 p2 k3 (OpenCV's default)     (none)       5
k1-k6      k1..k6 (rational)                     RATIONAL_MODEL, ZERO_TANGENT_DIST  8
k1-k6+p    k1..k6 p1 p2 (rational)               RATIONAL_MODEL  8
========== ===================================== ============ ======

``dist`` is always written in OpenCV order ``(k1, k2, p1, p2, k3[, k4, k5, k6])`` with fixed terms 0.
Which model fits a lens best is decided by the hold-out check (:mod:`calib.holdout`).
"""

from __future__ import annotations

from dataclasses import dataclass

from capture.io.errors import CaptureError

DIST_NAMES = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


@dataclass(frozen=True)
class DistortionModel:
    """``radial`` is 2, 3 or 6 radial terms (6 = OpenCV's rational model); ``tangential`` adds p1, p2."""

    radial: int
    tangential: bool

    @property
    def name(self) -> str:
        return f"k1-k{self.radial}" + ("+p" if self.tangential else "")

    @property
    def n_dist(self) -> int:
        """Length of the distortion vector OpenCV returns for this model (5 or 8)."""
        return 8 if self.radial == 6 else 5

    @property
    def free_terms(self) -> tuple[int, ...]:
        """Indices into ``DIST_NAMES`` of the estimated terms."""
        idx = [0, 1] + ([2, 3] if self.tangential else [])
        if self.radial >= 3:
            idx.append(4)
        if self.radial == 6:
            idx += [5, 6, 7]
        return tuple(sorted(idx))

    @property
    def num_params(self) -> int:
        return len(self.free_terms)

    def flags(self) -> int:
        import cv2

        flags = 0
        if self.radial == 2:
            flags |= cv2.CALIB_FIX_K3
        if self.radial == 6:
            flags |= cv2.CALIB_RATIONAL_MODEL
        if not self.tangential:
            flags |= cv2.CALIB_ZERO_TANGENT_DIST
        return flags


MODELS = tuple(DistortionModel(r, t) for r in (2, 3, 6) for t in (False, True))
MODEL_NAMES = tuple(m.name for m in MODELS)
OPENCV_DEFAULT = DistortionModel(3, True)


def model_by_name(name: str) -> DistortionModel:
    for m in MODELS:
        if m.name == name:
            return m
    raise CaptureError(f"distortion model {name!r} is unknown; use auto or one of {', '.join(MODEL_NAMES)}")


def candidate_models(model: str = "auto", fix_k3: bool = False, zero_tangent: bool = False,
                     rational: bool = False) -> list[DistortionModel]:
    """The models to choose among: one if ``model`` names it, else those allowed by the constraint flags.

    Without ``zero_tangent`` the models without p1, p2 other than the simplest (k1-k2) are not
    candidates: small tangential terms trade off with the principal point, and leaving them out
    moves it even when the hold-out error cannot tell the difference.
    """
    if model != "auto":
        chosen = model_by_name(model)
        if (fix_k3 and chosen.radial != 2) or (rational and chosen.radial != 6) or (zero_tangent and chosen.tangential):
            raise CaptureError(f"--model {model} contradicts --fix-k3/--rational/--zero-tangent; give one or the other")
        return [chosen]
    if fix_k3 and rational:
        raise CaptureError("--fix-k3 and --rational contradict each other (the rational model has k3); give one")
    out = [m for m in MODELS
           if not (fix_k3 and m.radial != 2) and not (rational and m.radial != 6)
           and not (zero_tangent and m.tangential)]
    if not zero_tangent:  # keep p1, p2 (they trade off with the principal point) unless told
        out = [m for m in out if m.tangential or m == DistortionModel(2, False)]
    return out
