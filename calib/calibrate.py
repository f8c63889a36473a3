"""Intrinsics from board views: OpenCV's calibration, outlier views out, the lens model picked by hold-out.

Pure computation on corner lists (no files, no video). :func:`calibrate_views`:

1. **First solve** with OpenCV's default model (k1, k2, p1, p2, k3; or the richest one the flags
   allow, :func:`base_model`). Views whose RMS reprojection error is above ``outlier_factor`` times the median view RMS
   *and* above ``outlier_floor_px`` (1 px: a clean view is far below, a mis-detected one far above)
   are rejected and the solve repeated, up to ``max_rounds`` times, never below ``min_views``.
2. **Model choice** (``model="auto"``): every candidate model (:mod:`calib.models`) is scored by the
   hold-out check (:mod:`calib.holdout`: views left out, their error predicted by the model fitted to
   the others, and the spread over the image of the models fitted without them) and by its predicted
   pixel uncertainty over the image (:mod:`calib.uncertainty`). OpenCV's default model is kept unless
   the evidence clearly supports another (:func:`choose_model`): a richer model must predict the
   left-out views better; a simpler one is taken only when the default's extra terms are not
   determined at all (its predicted uncertainty over the image several times the simpler model's)
   and the simpler model agrees with the default wherever the default is determined. A model that is
   not a real lens over the image (it folds over, or puts the principal point outside it:
   :func:`calib.camera_io.camera_problem`, the check every camera file passes) is never chosen, and
   when no candidate is one the calibration is refused.
3. **Final solve** with the chosen model on all kept views, with the full intrinsic covariance
   (:mod:`calib.uncertainty`) and the hold-out cameras of that model for the report.

``cv2.calibrateCameraExtended`` does every solve; nothing here re-implements its optimiser.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib.camera import Camera
from calib.camera_io import camera_problem
from calib.holdout import HoldoutResult, holdout_check
from calib.models import OPENCV_DEFAULT, DistortionModel, candidate_models
from calib.solve import Solve, solve
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
    tolerance_px: float = 1.0  # hold-out spread over the image that makes a model unstable
    # a simpler model replaces OpenCV's default only when all three hold (see choose_model):
    simpler_sigma_ratio: float = 3.5  # default's max predicted uncertainty / the simpler model's, at least
    simpler_agreement: float = 0.5  # |simpler - default| <= this * sqrt(sigma_default^2 - sigma_simpler^2)
    simpler_holdout_tolerance: float = 0.05  # simpler model's hold-out RMS at most 5 % above the default's
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
    model_evidence: dict[str, ModelEvidence] = field(default_factory=dict)  # per candidate model
    holdout: HoldoutResult | None = None  # the chosen model's hold-out check
    implausible: dict[str, str] = field(default_factory=dict)  # candidate models not used: what is wrong with each
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
    # a model that folds over inside the image (or puts its principal point outside it, ...) is not a lens:
    # `capture run` refuses such a camera file, so it is never chosen (plain OpenCV would return it)
    implausible = {}
    for m in candidates:
        problem = camera_problem(Camera(solves[m.name].K, solves[m.name].dist, image_size))
        if problem:
            implausible[m.name] = problem[0]
    if implausible and len(implausible) == len(candidates):
        name = first.name if first.name in implausible else next(iter(implausible))
        problem = implausible[name]
        raise CaptureError(
            f"no lens model fitted to these {len(active)} views is a real lens ({name}: {problem}); record more views "
            "over the whole image" if options.model == "auto" else
            f"the {name} lens model fitted to these {len(active)} views is not a real lens ({problem}); record more "
            "views over the whole image, or choose a model with fewer terms (--model k1-k2)"
        )
    candidates = [m for m in candidates if m.name not in implausible]
    evidence = model_evidence(candidates, solves, obj_a, img_a, image_size, first, options) \
        if len(candidates) > 1 else {}
    model = choose_model(candidates, checks, first, options, evidence)
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
    return CalibrationResult(camera, s.rms, views, rejected, std, model, scores, evidence, checks[model.name],
                             implausible, s.rvecs, s.tvecs, rounds, obj_a, img_a)


def base_model(candidates: list[DistortionModel]) -> DistortionModel:
    """OpenCV's default model, or the richest non-rational candidate the flags allow (the rational one
    only when nothing else is allowed): what plain OpenCV would fit with the same flags."""
    if OPENCV_DEFAULT in candidates:
        return OPENCV_DEFAULT
    plain = [m for m in candidates if m.radial != 6] or candidates
    return max(plain, key=lambda m: m.num_params)


@dataclass(frozen=True)
class ModelEvidence:
    """What the covariance says about one candidate model, over a pixel grid covering the image.

    ``sigma_px``: predicted 1-sigma of where the model sends each pixel's ray
    (:func:`calib.uncertainty.pixel_uncertainty`); ``difference_px``: how far the model fitted to all
    views projects from the base model (OpenCV's default) fitted to the same views
    (:func:`calib.uncertainty.projection_difference`; zeros for the base itself). Both are in the camera's
    fixed frame: :func:`choose_model`'s thresholds were set on them. ``difference_aligned_px`` is the same
    difference up to the camera's rotation, what the report and its warnings show (:mod:`calib.uncertainty`).
    """

    sigma_px: np.ndarray = field(repr=False)
    difference_px: np.ndarray = field(repr=False)
    difference_aligned_px: np.ndarray = field(repr=False)

    @property
    def sigma_max_px(self) -> float:
        return float(np.max(self.sigma_px))

    @property
    def difference_max_px(self) -> float:
        return float(np.max(self.difference_px))

    @property
    def difference_aligned_max_px(self) -> float:
        return float(np.max(self.difference_aligned_px))


def model_evidence(models: list[DistortionModel], solves: dict[str, Solve], obj: list[np.ndarray],
                   img: list[np.ndarray], image_size: tuple[int, int], base: DistortionModel,
                   options: CalibrationOptions) -> dict[str, ModelEvidence]:
    """:class:`ModelEvidence` of every model in ``models`` (each must have a full solve in ``solves``)."""
    from calib.uncertainty import (
        intrinsic_covariance,
        pixel_grid,
        pixel_uncertainty,
        projection_difference,
    )

    grid, _ = pixel_grid(image_size, max(4.0, float(np.hypot(*image_size)) / 100.0))
    fpp, far = options.fix_principal_point, options.fix_aspect_ratio
    cams = {m.name: Camera(solves[m.name].K, solves[m.name].dist, image_size) for m in models}
    out = {}
    for m in models:
        s = solves[m.name]
        cov = intrinsic_covariance(cams[m.name], m, obj, img, s.rvecs, s.tvecs, fpp, far)
        sigma = pixel_uncertainty(cams[m.name], m, cov, grid, fpp, far)
        compared = base.name in cams and m != base
        diff = projection_difference(cams[base.name], cams[m.name], grid) if compared else np.zeros(len(grid))
        aligned = (projection_difference(cams[base.name], cams[m.name], grid, align=True) if compared
                   else np.zeros(len(grid)))
        out[m.name] = ModelEvidence(sigma, diff, aligned)
    return out


def choose_model(models: list[DistortionModel], checks: dict[str, HoldoutResult], base: DistortionModel,
                 options: CalibrationOptions = CalibrationOptions(),
                 evidence: dict[str, ModelEvidence] | None = None, gain: float = 0.03) -> DistortionModel:
    """The lens model the evidence supports, starting from ``base`` (OpenCV's default model).

    ``models`` must all have a full solve and an entry in ``checks`` (and in ``evidence`` when given).

    - A model with more terms replaces it only when it predicts the left-out views clearly better
      (hold-out RMS lower by ``gain``, 3 %) without being less stable over the image (spread). That
      is evidence from data the model did not see.
    - A model with fewer terms can never be shown better by the data: it fits worse, and its hold-out
      error hardly differs (the left-out views' own poses absorb what it gets wrong). Where the data
      do not determine the extra terms (image corners without board corners) the default may be
      wrong by many pixels or exactly right, and no statistic tells which. So a simpler model
      replaces the default only when all of these hold:

      - the default's extra terms are not determined: its largest predicted uncertainty over the
        image is at least ``options.simpler_sigma_ratio`` (3.5) times the simpler model's;
      - the simpler model is consistent with the default where the data determine both: at every
        pixel ``|simpler - default| <= options.simpler_agreement * sqrt(sigma_default^2 -
        sigma_simpler^2)`` (a Hausman-type test: if the simpler model were right, the two would
        differ by about the default's excess uncertainty);
      - it predicts the left-out views about as well (hold-out RMS at most
        ``options.simpler_holdout_tolerance``, 5 %, above the default's).

      Of several such models the one with the smallest predicted uncertainty is taken. Thresholds
      were set on rendered footage (seeds 10-19 of benchmarks/bench_calib.py, 240 runs): with them
      no run came out more than 0.5 px worse than OpenCV's default on the same views; looser ones
      (ratio 3, agreement 1) won more runs by several px but lost up to 4.9 px in others.
    """
    ok = [m for m in models if np.isfinite(checks[m.name].rms_px)]
    if not ok:  # no model could be checked (the diagnostics warn): keep OpenCV's default
        return base if base in models else models[0]
    chosen = base if base in ok else min(ok, key=lambda m: checks[m.name].rms_px)
    c = checks[chosen.name]
    richer = [m for m in ok if m.num_params > chosen.num_params
              and checks[m.name].rms_px < c.rms_px * (1.0 - gain)
              and checks[m.name].spread_px <= max(c.spread_px, options.tolerance_px)]
    if richer:
        return min(richer, key=lambda m: checks[m.name].rms_px)
    if not evidence or chosen.name not in evidence:
        return chosen
    e0 = evidence[chosen.name]
    simpler = []
    for m in ok:
        if m.num_params >= chosen.num_params or m.name not in evidence or m.radial == 6:
            continue
        e = evidence[m.name]
        excess = np.maximum(e0.sigma_px ** 2 - e.sigma_px ** 2, 0.01)  # px^2, floored at (0.1 px)^2
        with np.errstate(invalid="ignore"):
            agrees = bool(np.all(e.difference_px ** 2 <= options.simpler_agreement ** 2 * excess))
        if (e0.sigma_max_px >= options.simpler_sigma_ratio * e.sigma_max_px and agrees
                and checks[m.name].rms_px <= c.rms_px * (1.0 + options.simpler_holdout_tolerance)):
            simpler.append(m)
    if simpler:
        chosen = min(simpler, key=lambda m: evidence[m.name].sigma_max_px)
    return chosen
