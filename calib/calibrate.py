"""Intrinsics from board views: OpenCV's calibration, outlier views out, the lens model picked by hold-out.

Pure computation on corner lists (no files, no video). :func:`calibrate_views`:

1. **First solve** with OpenCV's default model (k1, k2, p1, p2, k3; or the richest one the flags
   allow, :func:`base_model`). Views whose RMS reprojection error is above ``outlier_factor`` times the median view RMS
   *and* above ``outlier_floor_px`` (1 px: a clean view is far below, a mis-detected one far above)
   are rejected and the solve repeated, up to ``max_rounds`` times, never below ``min_views``.
2. **Model choice** (``model="auto"``): every candidate model (:mod:`calib.models`) is scored by the
   hold-out check (:mod:`calib.holdout`: views left out, their error predicted by the model fitted to
   the others, and the spread over the image of the models fitted without them). OpenCV's default
   model is kept unless the check clearly supports another (:func:`choose_model`): a richer model
   must predict the left-out views better, a simpler one is taken when the default is unstable
   over the image (undetermined terms) and the simpler one predicts at least as well.
3. **Final solve** with the chosen model on all kept views, with the full intrinsic covariance
   (:mod:`calib.uncertainty`) and the hold-out cameras of that model for the report.

``cv2.calibrateCameraExtended`` does every solve; nothing here re-implements its optimiser.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.camera import Camera
from calib.holdout import HoldoutResult, holdout_check
from calib.solve import Solve, solve  # noqa: F401  (Solve: part of this module's API)
from calib.models import OPENCV_DEFAULT, DistortionModel, candidate_models
from capture.io.errors import CaptureError

STD_NAMES = ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")


@dataclass(frozen=True)
class CalibrationOptions:
    """What OpenCV estimates, how outlier views are rejected and how the lens model is chosen."""

    fix_principal_point: bool = False  # keep (cx, cy) at the exact image centre ((w-1)/2, (h-1)/2)
    fix_aspect_ratio: bool = False  # fx = fy (square pixels)
    model: str = "auto"  # a name from calib.models.MODEL_NAMES, or "auto" (hold-out choice)
    fix_k3: bool = False  # restrict the candidates to k1, k2 (+p)
    zero_tangent: bool = False  # restrict the candidates to no p1, p2
    rational: bool = False  # restrict the candidates to the rational model (k1..k6)
    min_views: int = 4
    outlier_factor: float = 3.0  # 0 disables rejection
    outlier_floor_px: float = 1.0  # views below this RMS are never outliers
    max_rounds: int = 3
    folds: int = 5  # hold-out folds (leave-one-out when there are fewer views)
    model_tolerance: float = 0.0  # a simpler model may be this much worse on hold-out (see choose_model)
    tolerance_px: float = 1.0  # hold-out spread over the image that makes a model unstable
    rational_min_views: int = 10  # fewer views cannot pin 8 distortion terms: not a candidate

    def candidates(self) -> list[DistortionModel]:
        return candidate_models(self.model, self.fix_k3, self.zero_tangent, self.rational)

    def flags(self, model: DistortionModel) -> int:
        import cv2

        flags = model.flags()
        if self.fix_principal_point:
            flags |= cv2.CALIB_FIX_PRINCIPAL_POINT
        if self.fix_aspect_ratio:
            flags |= cv2.CALIB_FIX_ASPECT_RATIO
        return flags


@dataclass(frozen=True)
class ViewError:
    label: str
    rms_px: float
    corners: int


@dataclass(frozen=True)
class CalibrationResult:
    camera: Camera
    rms_px: float
    views: list[ViewError]  # views used in the final calibration, in input order
    rejected: list[ViewError]  # outlier views, with the error they had when rejected
    std_dev: dict[str, float]  # 1-sigma of the estimated intrinsics (pixels / unitless); fixed terms absent
    model: DistortionModel = OPENCV_DEFAULT
    model_scores: dict[str, float] = field(default_factory=dict)  # hold-out RMS (px) per candidate model
    holdout: HoldoutResult | None = None  # the chosen model's hold-out check
    rvecs: list[np.ndarray] = field(repr=False, default_factory=list)
    tvecs: list[np.ndarray] = field(repr=False, default_factory=list)
    rounds: int = 1
    object_points: list[np.ndarray] = field(repr=False, default_factory=list)  # of the used views
    image_points: list[np.ndarray] = field(repr=False, default_factory=list)


def calibrate_views(
    object_points: list[np.ndarray],
    image_points: list[np.ndarray],
    labels: list[str],
    image_size: tuple[int, int],
    options: CalibrationOptions = CalibrationOptions(),
    provenance: str = "",
) -> CalibrationResult:
    """Calibrate from per-view corners (object (n, 3) mm, image (n, 2) px); steps in the module docstring."""
    if not (len(object_points) == len(image_points) == len(labels)):
        raise ValueError("object_points, image_points and labels must have one entry per view")
    if len(labels) < options.min_views:
        raise CaptureError(
            f"too few usable views: found {len(labels)}, need at least {options.min_views}; "
            "record the board at more positions and tilts (or lower --min-views)"
        )
    candidates = options.candidates()
    obj = [np.ascontiguousarray(o, np.float32).reshape(-1, 3) for o in object_points]
    img = [np.ascontiguousarray(p, np.float32).reshape(-1, 2) for p in image_points]

    # 1. first solve and outlier views
    first = base_model(candidates)
    active = list(range(len(labels)))
    rejected: list[ViewError] = []
    rounds = 0
    while True:
        rounds += 1
        s = solve([obj[i] for i in active], [img[i] for i in active], image_size, first, options)
        if options.outlier_factor <= 0 or rounds > options.max_rounds:
            break
        limit = max(options.outlier_factor * float(np.median(s.per_view)), options.outlier_floor_px)
        bad = [k for k, e in enumerate(s.per_view) if e > limit]
        if not bad or len(active) - len(bad) < options.min_views:
            break
        rejected += [ViewError(labels[active[k]], float(s.per_view[k]), len(img[active[k]])) for k in bad]
        bad_set = set(bad)
        active = [i for k, i in enumerate(active) if k not in bad_set]
    obj_a, img_a = [obj[i] for i in active], [img[i] for i in active]

    # 2. model choice by hold-out
    if len(candidates) > 1:
        candidates = [m for m in candidates if m.radial != 6 or len(active) >= options.rational_min_views] \
            or candidates
    solves = {first.name: s}
    checks = {}
    for m in candidates:
        if m.name not in solves:
            try:
                solves[m.name] = solve(obj_a, img_a, image_size, m, options)
            except CaptureError:
                continue
        full = Camera(solves[m.name].K, solves[m.name].dist, image_size)
        checks[m.name] = holdout_check(obj_a, img_a, image_size, m, options, full)
    candidates = [m for m in candidates if m.name in checks]
    model = choose_model(candidates, checks, first, options.tolerance_px, options.model_tolerance)
    scores = {name: c.rms_px for name, c in checks.items()}

    # 3. the chosen model's solve on all kept views
    s = solves[model.name]
    std = {name: float(s.std_int[k]) for k, name in enumerate(STD_NAMES[: 4 + model.n_dist]) if k < len(s.std_int)}
    fixed = {"cx", "cy"} if options.fix_principal_point else set()
    fixed |= {STD_NAMES[4 + k] for k in range(model.n_dist) if k not in model.free_terms}
    std = {k: v for k, v in std.items() if k not in fixed}
    camera = Camera(s.K, s.dist, image_size, s.rms, provenance, False,
                    {k: std[k] for k in ("fx", "fy", "cx", "cy") if k in std})
    views = [ViewError(labels[i], float(s.per_view[k]), len(img[i])) for k, i in enumerate(active)]
    return CalibrationResult(camera, s.rms, views, rejected, std, model, scores, checks[model.name],
                             s.rvecs, s.tvecs, rounds, obj_a, img_a)


def base_model(candidates: list[DistortionModel]) -> DistortionModel:
    """OpenCV's default model, or the richest non-rational candidate the flags allow (the rational one
    only when nothing else is allowed): what plain OpenCV would fit with the same flags."""
    if OPENCV_DEFAULT in candidates:
        return OPENCV_DEFAULT
    plain = [m for m in candidates if m.radial != 6] or candidates
    return max(plain, key=lambda m: m.num_params)


def choose_model(models: list[DistortionModel], checks: dict[str, HoldoutResult], base: DistortionModel,
                 tolerance_px: float = 1.0, model_tolerance: float = 0.0, gain: float = 0.03) -> DistortionModel:
    """The lens model the hold-out check supports, starting from ``base`` (OpenCV's default model).

    ``models`` must all have a full solve and an entry in ``checks``.

    - A model with more terms replaces it only when it predicts the left-out views clearly better
      (hold-out RMS lower by ``gain``, 3 %) without being less stable over the image (spread).
    - When the chosen model is unstable over the image (hold-out spread above ``tolerance_px``), the
      most stable of the simpler models that predict the left-out views at least as well (hold-out
      RMS not above the chosen one's, ``model_tolerance`` = 0) replaces it, if it is a third more
      stable. (A 2 % allowance lost up to 2.6 px against OpenCV's default on strong lenses.)
      A term the data cannot determine does not improve the hold-out error but makes the spread large.
    """
    ok = [m for m in models if np.isfinite(checks[m.name].rms_px)]
    if not ok:  # no model could be checked (the diagnostics warn): keep OpenCV's default
        return base if base in models else models[0]
    chosen = base if base in ok else min(ok, key=lambda m: checks[m.name].rms_px)
    c = checks[chosen.name]
    richer = [m for m in ok if m.num_params > chosen.num_params
              and checks[m.name].rms_px < c.rms_px * (1.0 - gain)
              and checks[m.name].spread_px <= max(c.spread_px, tolerance_px)]
    if richer:
        chosen = min(richer, key=lambda m: checks[m.name].rms_px)
        c = checks[chosen.name]
    if c.spread_px > tolerance_px:
        simpler = [m for m in ok if m.num_params < chosen.num_params
                   and checks[m.name].rms_px <= c.rms_px * (1.0 + model_tolerance)
                   and checks[m.name].spread_px < c.spread_px / 1.5]
        if simpler:
            chosen = min(simpler, key=lambda m: checks[m.name].spread_px)
    return chosen
