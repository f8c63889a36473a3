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
  between them (see :func:`calib.calibrate.choose_model`);
- given the board's corners (``board_points``), the detector found fewer than ``min_detected_fraction``
  (70 %) of the corners that the used views had in view (:func:`missed_corners`): blurred, small or glared
  markers. Then the warning on a bare image corner also says when the board came nearer to it than any used
  corner but was not detected there: recording the board there again helps only if the footage is sharper.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.calibrate import base_model
from calib.uncertainty import (CORNER_NAMES, Coverage, Covariance, coverage, image_corners, intrinsic_covariance,
                               pixel_grid, pixel_uncertainty, projection_difference, term_effects_px)

CORNER_GAP_FRACTION = 0.08
MIN_DETECTED_FRACTION = 0.7


@dataclass(frozen=True)
class MissedCorners:
    """Board corners the used views had in view, and which of them the detector found (:func:`missed_corners`).

    ``in_view`` and ``detected`` are per used view (input order); ``missed_px`` ``(m, 2)`` are the pixels where
    the camera puts the corners in view that were not detected, ``missed_view`` ``(m,)`` their view's index."""

    in_view: np.ndarray
    detected: np.ndarray
    missed_px: np.ndarray
    missed_view: np.ndarray

    @property
    def fraction(self) -> float:
        """Detected corners over corners in view, all views pooled (1 when none was in view)."""
        total = int(self.in_view.sum())
        return float(self.detected.sum()) / total if total else 1.0


def missed_corners(camera, board_points: np.ndarray, object_points: list[np.ndarray], rvecs: list[np.ndarray],
                   tvecs: list[np.ndarray], square_mm: float) -> MissedCorners:
    """Which corners of the board each view had in view, and which of them were detected.

    Args:
        camera: the calibrated :class:`~calib.camera.Camera`.
        board_points: ``(N, 3)`` all the board's corners (mm, z = 0; :meth:`BoardSpec.corner_object_points`).
        object_points: per view, ``(n, 3)`` the detected corners' board points (a subset of ``board_points``).
        rvecs, tvecs: per view, the board's pose from the calibration (OpenCV's ``rvec``, ``tvec``).
        square_mm: the board's square side.

    A corner counts as in view when it and the four points one square away along the board's axes project inside
    the image: a ChArUco corner is found from its neighbouring markers, so one whose neighbourhood is cut by the
    image border cannot be. Points that only a distortion model's fold-over brings into the image (their pinhole
    projection more than half the image outside it) are not in view. Pure geometry, no image.
    """
    import cv2

    w, h = camera.image_size
    board = np.asarray(board_points, np.float64).reshape(-1, 3)
    offsets = np.array([[0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], np.float64) * float(square_mm)
    probe = (board[:, None, :] + offsets[None]).reshape(-1, 3)
    in_view, detected, missed, missed_view = [], [], [], []
    for k, (obj, r, t) in enumerate(zip(object_points, rvecs, tvecs)):
        rvec, tvec = np.asarray(r, np.float64), np.asarray(t, np.float64)
        uv = cv2.projectPoints(probe, rvec, tvec, camera.K, camera.dist)[0].reshape(len(board), len(offsets), 2)
        pin = cv2.projectPoints(probe, rvec, tvec, camera.K, None)[0].reshape(len(board), len(offsets), 2)
        inside = ((uv[..., 0] >= 0) & (uv[..., 0] <= w - 1) & (uv[..., 1] >= 0) & (uv[..., 1] <= h - 1)
                  & (np.abs(pin[..., 0] / w - 0.5) <= 1.0) & (np.abs(pin[..., 1] / h - 0.5) <= 1.0)).all(1)
        found = {tuple(p) for p in np.round(np.asarray(obj, np.float64).reshape(-1, 3), 3)}
        is_found = np.array([tuple(p) in found for p in np.round(board, 3)])
        in_view.append(int(inside.sum()))
        detected.append(int((inside & is_found).sum()))
        miss = inside & ~is_found
        missed.append(uv[miss, 0])
        missed_view.append(np.full(int(miss.sum()), k))
    return MissedCorners(np.array(in_view), np.array(detected),
                         np.concatenate(missed) if missed else np.zeros((0, 2)),
                         np.concatenate(missed_view) if missed_view else np.zeros(0, int))


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
    missed: MissedCorners | None = None  # with the board's corners: what the detector found of what was in view

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
             corner_gap_fraction: float = CORNER_GAP_FRACTION, board_points: np.ndarray | None = None,
             square_mm: float = 0.0, min_detected_fraction: float = MIN_DETECTED_FRACTION) -> Diagnostics:
    """Uncertainty, spread, coverage and warnings of one calibration (module docstring); ``board_points``
    ``(N, 3)`` and ``square_mm`` (the board) add what the detector missed (:func:`missed_corners`)."""
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
    missed = (missed_corners(camera, board_points, result.object_points, result.rvecs, result.tvecs, square_mm)
              if board_points is not None and square_mm > 0 else None)
    poor = missed is not None and missed.fraction < min_detected_fraction
    gap_limit = corner_gap_fraction * float(np.hypot(w, h))
    gaps = {n: g for n, g in cov_map.corner_gaps_px.items() if g > gap_limit}
    if gaps:
        seen = _seen_nearer(missed, gaps, (w, h)) if poor else 0
        warnings.append(
            "image corner" + ("s " if len(gaps) > 1 else " ") + ", ".join(gaps) + " not covered (nearest board "
            "corner " + ", ".join(f"{g:.0f}" for g in gaps.values()) + f" px away, limit {gap_limit:.0f} px): the "
            "lens model is extrapolated there; "
            + (f"the board came nearer to them in {seen} view(s), but its corners there were not detected: record "
               "it there sharper, larger or without glare" if seen else "record the board in the image corners")
        )
    if poor:
        low = int(np.sum(missed.detected < min_detected_fraction * missed.in_view))
        warnings.append(
            f"the detector found only {missed.fraction:.0%} of the board corners in view ({low} of "
            f"{len(missed.in_view)} views under {min_detected_fraction:.0%}): blurred, small or glared markers "
            "leave the views' edges out; sharper footage, a larger board or more light would cover more of the image"
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
    plain = base_model(options.candidates())   # what OpenCV alone would have returned
    if plain.name in result.implausible:
        warnings.append(
            f"lens model {plain.name} fitted to these views is not a real lens ({result.implausible[plain.name]}); "
            f"{result.model.name} is used instead, and it is extrapolated where no board corner was seen: record more "
            "views over the whole image"
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
                       float(sigma_fixed.max()), spread_fixed, missed)


def _seen_nearer(missed: MissedCorners, gaps: dict[str, float], image_size: tuple[int, int]) -> int:
    """Views with an undetected board corner in view nearer to one of the bare image corners in ``gaps``
    (name -> distance to the nearest used corner, px) than every used corner."""
    where = dict(zip(CORNER_NAMES, image_corners(image_size)))
    near = np.zeros(len(missed.missed_px), bool)
    for name, gap in gaps.items():
        near |= np.linalg.norm(missed.missed_px - np.asarray(where[name], np.float64), axis=1) < gap
    return len(set(missed.missed_view[near].tolist()))


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


__all__ = ["CORNER_NAMES", "Diagnostics", "MissedCorners", "diagnose", "missed_corners"]
