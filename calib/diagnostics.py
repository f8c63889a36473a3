"""How far a calibration can be trusted, and where: the numbers and warnings ``capture calibrate`` reports.

:func:`diagnose` takes a :class:`~calib.calibrate.CalibrationResult` and measures, over a grid of
pixels covering the whole image (:mod:`calib.uncertainty`):

- the **predicted uncertainty** (1 sigma, px) from the intrinsic covariance,
- the **hold-out spread**: how far each hold-out fold's camera (calibrated without some views)
  projects from the full camera, the largest over folds,
- the **coverage**: used corners per cell and the distance from each image corner to the data.

The uncertainty and the spread are measured up to the camera's rotation (:mod:`calib.uncertainty`: the
rotation of the camera frame that the views cannot pin, and that a take's solved head poses absorb, is
not counted as error); the report also gives their largest values without it (``..._fixed_frame``).

It warns (and ``--strict`` fails) when the model extrapolates or is not determined:

- fewer than 6 views were used;

- an image corner is farther than ``corner_gap_fraction`` (8 %) of the image diagonal from every
  used board corner: the lens model there is extrapolated, not measured;
- the predicted uncertainty exceeds ``tolerance_px / 2`` somewhere (so 2 sigma exceeds the
  tolerance); the distortion terms whose 1 sigma alone moves the farthest image corner by more than
  ``tolerance_px / 2`` are named as not determined;
- the hold-out spread exceeds ``tolerance_px`` somewhere: leaving some views out changes the model
  there by more than the tolerance (or the check could not be run at all);
- another lens model (not the rational one) predicts the left-out views within 5 % as well but
  differs from the chosen one by more than ``tolerance_px`` somewhere: the views cannot decide
  between them (see :func:`calib.calibrate.choose_model`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.uncertainty import (CORNER_NAMES, Coverage, Covariance, coverage, intrinsic_covariance, pixel_grid,
                               pixel_uncertainty, projection_difference, term_effects_px)

CORNER_GAP_FRACTION = 0.08


@dataclass(frozen=True)
class Diagnostics:
    grid: np.ndarray  # (m, 2) pixels
    grid_shape: tuple[int, int]  # (nx, ny)
    uncertainty_px: np.ndarray  # (m,) predicted 1-sigma, up to the camera's rotation
    spread_px: np.ndarray  # (m,) hold-out spread up to the camera's rotation (0 when there were no fold cameras)
    covariance: Covariance
    coverage: Coverage
    term_effects_px: dict[str, float]
    tolerance_px: float
    warnings: list[str] = field(default_factory=list)
    image_size: tuple[int, int] = (0, 0)
    uncertainty_fixed_frame_max_px: float = 0.0  # the same two without the implied rotation, for reference
    spread_fixed_frame_max_px: float = 0.0

    def _at(self, values: np.ndarray) -> list[float]:
        return [float(v) for v in self.grid[int(np.argmax(values))]]

    @property
    def uncertainty_max_px(self) -> float:
        return float(self.uncertainty_px.max())

    @property
    def uncertainty_median_px(self) -> float:
        return float(np.median(self.uncertainty_px))

    @property
    def uncertainty_at(self) -> list[float]:
        return self._at(self.uncertainty_px)

    @property
    def spread_max_px(self) -> float:
        return float(self.spread_px.max())

    @property
    def spread_at(self) -> list[float]:
        return self._at(self.spread_px)


def diagnose(result, options, tolerance_px: float = 1.0, grid_step_px: float | None = None,
             corner_gap_fraction: float = CORNER_GAP_FRACTION) -> Diagnostics:
    """Uncertainty, spread, coverage and warnings of one calibration (module docstring)."""
    camera = result.camera
    w, h = camera.image_size
    step = grid_step_px or max(4.0, float(np.hypot(w, h)) / 100.0)
    grid, shape = pixel_grid((w, h), step)
    fpp, far = options.fix_principal_point, options.fix_aspect_ratio
    cov = intrinsic_covariance(camera, result.model, result.object_points, result.image_points,
                               result.rvecs, result.tvecs, fpp, far)
    sigma = pixel_uncertainty(camera, result.model, cov, grid, fpp, far, modulo_rotation=True)
    sigma_fixed = pixel_uncertainty(camera, result.model, cov, grid, fpp, far)
    folds = result.holdout.fold_cameras if result.holdout else []
    spread = (np.max([projection_difference(camera, c, grid, align=True) for c in folds], axis=0)
              if folds else np.zeros(len(grid)))
    spread_fixed = max((float(projection_difference(camera, c, grid).max()) for c in folds), default=0.0)
    cov_map = coverage(result.image_points, (w, h))
    effects = term_effects_px(camera, result.model, cov, fpp, far)

    warnings = []
    gap_limit = corner_gap_fraction * float(np.hypot(w, h))
    gaps = {n: g for n, g in cov_map.corner_gaps_px.items() if g > gap_limit}
    if gaps:
        warnings.append(
            "image corner" + ("s " if len(gaps) > 1 else " ") + ", ".join(gaps) + " not covered (nearest board "
            "corner " + ", ".join(f"{g:.0f}" for g in gaps.values()) + f" px away, limit {gap_limit:.0f} px): the "
            "lens model is extrapolated there; record the board in the image corners"
        )
    if sigma.max() > tolerance_px / 2:
        at = grid[int(np.argmax(sigma))]
        loose = [n for n, e in effects.items() if e > tolerance_px / 2]
        warnings.append(
            f"predicted uncertainty reaches {sigma.max():.2f} px (1 sigma) at ({at[0]:.0f}, {at[1]:.0f}), above "
            f"half the {tolerance_px:g} px tolerance"
            + (f"; distortion term(s) {', '.join(loose)} not determined" if loose else "")
            + "; record more views there, or fix terms (--model)"
        )
    rival = _rival_model(result, tolerance_px)
    if rival:
        name, diff = rival
        warnings.append(
            f"lens model undecided: {name} predicts the left-out views about as well as the chosen "
            f"{result.model.name} but differs from it by up to {diff:.2f} px over the image: these views cannot "
            "tell which is right; record the board in the image corners, or choose with --model"
        )
    if len(result.views) < 6:
        warnings.append(f"only {len(result.views)} views: too few to pin the lens model and to check it by "
                        "leaving views out; record at least 6, better 15-40, over the whole image")
    if result.holdout is None or not np.isfinite(result.holdout.rms_px):
        warnings.append("hold-out check failed: OpenCV could not calibrate with views left out, so the model "
                        "is not checked; record more views")
    if spread.max() > tolerance_px:
        at = grid[int(np.argmax(spread))]
        warnings.append(
            f"hold-out check: leaving views out moves the model by up to {spread.max():.2f} px at "
            f"({at[0]:.0f}, {at[1]:.0f}), above the {tolerance_px:g} px tolerance; record more views"
        )
    return Diagnostics(grid, shape, sigma, spread, cov, cov_map, effects, tolerance_px, warnings, (w, h),
                       float(sigma_fixed.max()), spread_fixed)


def _rival_model(result, tolerance_px: float, holdout_tolerance: float = 0.05) -> tuple[str, float] | None:
    """The non-rational candidate that predicts the left-out views within 5 % as well as the chosen model
    and differs most from it over the image, if by more than ``tolerance_px`` (differences are measured
    against OpenCV's default model up to the camera's rotation, :class:`calib.calibrate.ModelEvidence`)."""
    from calib.models import OPENCV_DEFAULT

    evidence, scores, chosen = result.model_evidence, result.model_scores, result.model.name
    if chosen not in evidence or OPENCV_DEFAULT.name not in evidence or not np.isfinite(scores.get(chosen, np.inf)):
        return None
    limit = scores[chosen] * (1.0 + holdout_tolerance)
    if chosen != OPENCV_DEFAULT.name:
        rivals = {OPENCV_DEFAULT.name: evidence[chosen].difference_aligned_max_px}
    else:
        rivals = {n: e.difference_aligned_max_px for n, e in evidence.items() if n != chosen and "k6" not in n}
    rivals = {n: d for n, d in rivals.items() if scores.get(n, np.inf) <= limit and d > tolerance_px}
    if not rivals:
        return None
    name = max(rivals, key=rivals.get)
    return name, rivals[name]


__all__ = ["CORNER_NAMES", "Diagnostics", "diagnose"]
