"""The ``capture calibrate`` stage: footage in; camera file, report JSON and figure out.

``run_calibrate(settings)`` reads the footage (:mod:`calib.frames`), detects the board
(:mod:`calib.detect`) and checks each detection's geometry (:mod:`calib.checks`), chooses views
(:mod:`calib.views`), calibrates and picks the lens model by hold-out (:mod:`calib.calibrate`),
measures what the result knows (:mod:`calib.diagnostics`) and writes, all atomically:

- the camera file ``--out`` (``.json``: the project's format; ``.yaml``/``.yml``/``.xml``: OpenCV's),
- ``<stem>.report.json`` beside it: resolved settings, input, views used and dropped with reasons,
  per-view errors, standard deviations, coverage, timings and versions,
- ``<stem>.report.png`` beside it: corner coverage and per-view errors (:mod:`calib.plots`),
- ``<stem>.coverage.png`` beside it: corner density heat map, predicted pixel uncertainty and hold-out
  spread over the image (:mod:`calib.diagnostics`).

Every doubt about the result (image corners without data, a model uncertain or unstable somewhere in
the image by more than ``--tolerance-px``) is printed as a warning and stored in the report; with
``--strict`` the run then fails (exit 2) after writing the report and figures but not the camera file.
"""

from __future__ import annotations

import collections
import dataclasses
import datetime as _dt
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from calib.board import BoardSpec, parse_board
from calib.board_hint import board_hint, sample_evenly
from calib.calibrate import CalibrationOptions, CalibrationResult, calibrate_views
from calib.camera_io import camera_to_dict, write_camera
from calib.detect import BoardDetector
from calib.frames import open_footage
from calib.checks import check_detection
from calib.diagnostics import Diagnostics, diagnose
from calib.plots import save_calibration_plot, save_coverage_plot
from calib.views import MAX_BLUR, Candidate, Dropped, coverage_fraction, make_candidate, select_views
from capture.io.atomic import write_json
from capture.io.errors import CaptureError

REPORT_VERSION = 2


@dataclass(frozen=True)
class CalibrateSettings:
    """Resolved settings of one ``capture calibrate`` run (saved verbatim in the report)."""

    input: Path
    board: str
    out: Path = Path("camera.json")
    max_views: int = 60
    max_candidates: int = 300
    min_views: int = 4
    min_corners: int = 6
    max_blur: float = MAX_BLUR
    duplicate_px: float | None = None
    outlier_factor: float = 3.0
    model: str = "auto"
    fix_principal_point: bool = False
    fix_aspect_ratio: bool = False
    fix_k3: bool = False
    zero_tangent: bool = False
    rational: bool = False
    tolerance_px: float = 1.0
    strict: bool = False
    progress: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "input", Path(self.input))
        object.__setattr__(self, "out", Path(self.out))

    def options(self) -> CalibrationOptions:
        return CalibrationOptions(
            fix_principal_point=self.fix_principal_point, fix_aspect_ratio=self.fix_aspect_ratio,
            model=self.model, fix_k3=self.fix_k3, zero_tangent=self.zero_tangent, rational=self.rational,
            min_views=self.min_views, outlier_factor=self.outlier_factor, tolerance_px=self.tolerance_px,
        )

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in d.items()}


@dataclass(frozen=True)
class CalibrateOutputs:
    camera: Path
    report: Path
    plot: Path
    coverage_plot: Path
    result: CalibrationResult
    diagnostics: Diagnostics


def report_paths(out: Path) -> tuple[Path, Path]:
    return out.with_name(out.stem + ".report.json"), out.with_name(out.stem + ".report.png")


def coverage_plot_path(out: Path) -> Path:
    return out.with_name(out.stem + ".coverage.png")


def _check_settings(s: CalibrateSettings) -> BoardSpec:
    board = parse_board(s.board)
    if s.out.suffix.lower() not in (".json", ".yaml", ".yml", ".xml"):
        raise CaptureError(f"--out {s.out} must end in .json (capture) or .yaml/.yml/.xml (OpenCV)")
    if s.min_views < 3:
        raise CaptureError(f"--min-views must be at least 3 (OpenCV needs several views), got {s.min_views}")
    if s.max_views < s.min_views:
        raise CaptureError(f"--max-views ({s.max_views}) must be at least --min-views ({s.min_views})")
    if s.max_candidates < s.min_views:
        raise CaptureError(f"--max-frames ({s.max_candidates}) must be at least --min-views ({s.min_views})")
    if not 0.0 <= s.max_blur <= 2.0:
        raise CaptureError(f"--max-blur must be in [0, 2] (edge width / square size; 0 keeps all), got {s.max_blur}")
    if not s.tolerance_px > 0:
        raise CaptureError(f"--tolerance-px must be positive, got {s.tolerance_px}")
    s.options().candidates()  # --model and the constraint flags agree
    if s.outlier_factor != 0 and s.outlier_factor < 1.5:
        raise CaptureError(f"--outlier-factor must be 0 (off) or at least 1.5, got {s.outlier_factor}")
    return board


#: Frames without a board kept to say what they show when no frame has the board (calib.board_hint).
HINT_FRAMES = 5


def _detect_all(footage, detector, board, settings) -> tuple[list[Candidate], list[Dropped], int, list]:
    """Candidates, dropped frames, frames examined, and up to :data:`HINT_FRAMES` grayscale frames spread over
    the footage in which no board was found (for :func:`calib.board_hint.board_hint`; empty once one is)."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    total = min(footage.count, -(-footage.count // footage.stride(settings.max_candidates)))
    candidates: list[Candidate] = []
    dropped: list[Dropped] = []
    examined = 0
    kept = set(sample_evenly(list(range(total)), HINT_FRAMES))   # frames kept for board_hint if nothing is found
    without_board: list = []                                      # their grayscale images (uint8)
    progress = Progress(TextColumn("detecting board"), BarColumn(), MofNCompleteColumn(),
                        TimeRemainingColumn(), console=Console(stderr=True), disable=not settings.progress,
                        transient=True)
    with progress:
        task = progress.add_task("detect", total=total)
        for label, frame, gray in footage.frames(settings.max_candidates):
            examined += 1
            detection, reason = detector.detect(gray)
            if detection is not None:
                detection, reason = check_detection(detection, board.square_mm, detector.min_corners)
            if detection is None:
                dropped.append(Dropped(label, frame, reason))
                if examined - 1 in kept and not candidates:
                    without_board.append(gray)
            else:
                candidates.append(make_candidate(label, frame, gray, detection, board.square_mm))
            progress.advance(task)
    return candidates, dropped, examined, ([] if candidates else without_board)


def run_calibrate(settings: CalibrateSettings) -> CalibrateOutputs:
    """Run the whole stage (see the module docstring); returns the paths written and the result."""
    t0 = time.perf_counter()
    board = _check_settings(settings)
    footage = open_footage(settings.input)
    detector = BoardDetector(board, settings.min_corners)

    t_detect = time.perf_counter()
    candidates, dropped, examined, without_board = _detect_all(footage, detector, board, settings)
    t_select = time.perf_counter()
    if not candidates:
        reasons = collections.Counter(_category(d.reason) for d in dropped)
        hint = board_hint(without_board, board)
        raise CaptureError(
            f"no board found in any of the {examined} frames examined in {settings.input} "
            f"({_summary(reasons)}); " + (hint if hint else
                                          f"check --board {board.text()} (charuco cols/rows count squares, "
                                          "checker cols/rows count inner corners) and the ArUco dictionary")
        )
    chosen, more_dropped = select_views(candidates, footage.image_size, settings.max_views,
                                        settings.max_blur, settings.duplicate_px)
    dropped = sorted(dropped + more_dropped, key=lambda d: d.frame)
    if len(chosen) < settings.min_views:
        reasons = collections.Counter(_category(d.reason) for d in dropped)
        raise CaptureError(
            f"too few usable views: found {len(chosen)}, need at least {settings.min_views} "
            f"({examined} frames examined; dropped: {_summary(reasons)}); record the board at more "
            "positions and tilts"
        )

    t_calib = time.perf_counter()
    w, h = footage.image_size
    provenance = (f"capture calibrate of {settings.input.name} ({footage.kind}, {w}x{h}) with "
                  f"{board.text()} on {_dt.date.today().isoformat()}")
    options = settings.options()
    if settings.progress:
        print(f"calibrating {len(chosen)} views; hold-out check of {len(options.candidates())} lens model(s)...",
              file=sys.stderr, flush=True)
    result = calibrate_views(
        [c.detection.object_points for c in chosen], [c.detection.image_points for c in chosen],
        [c.label for c in chosen], footage.image_size, options, provenance,
    )
    rejected = {v.label: v for v in result.rejected}
    for c in chosen:
        if c.label in rejected:
            dropped.append(Dropped(c.label, c.frame, f"outlier after a first solve (view RMS "
                                                     f"{rejected[c.label].rms_px:.3f} px)"))
    dropped.sort(key=lambda d: d.frame)
    used = [c for c in chosen if c.label not in rejected]
    provenance += f", {len(used)} views, model {result.model.name}, RMS {result.rms_px:.3f} px"
    camera = result.camera.with_provenance(provenance)
    t_diag = time.perf_counter()
    diag = diagnose(result, options, settings.tolerance_px, board_points=board.corner_object_points(),
                    square_mm=board.square_mm)
    t_write = time.perf_counter()

    report_path, plot_path = report_paths(settings.out)
    cov_plot = coverage_plot_path(settings.out)
    coverage = coverage_fraction([c.detection.image_points for c in used], footage.image_size)
    save_calibration_plot(
        plot_path, footage.image_size, [c.detection.image_points for c in used],
        [v.label for v in result.views], [v.rms_px for v in result.views],
        [v.label for v in result.rejected], [v.rms_px for v in result.rejected], result.rms_px,
        title=f"{settings.input.name}: RMS {result.rms_px:.3f} px, {len(used)} views, coverage {coverage:.0%}",
    )
    save_coverage_plot(cov_plot, diag, [c.detection.image_points for c in used],
                       title=f"{settings.input.name}: {len(used)} views, model {result.model.name}")
    failed = settings.strict and bool(diag.warnings)
    if not failed:
        write_camera(settings.out, camera)
    timings = {
        "open_s": t_detect - t0, "detect_s": t_select - t_detect, "select_s": t_calib - t_select,
        "calibrate_s": t_diag - t_calib, "diagnose_s": t_write - t_diag, "write_s": time.perf_counter() - t_write,
    }
    report = _report(settings, board, footage, examined, used, dropped, result, camera, coverage, diag,
                     timings, written=not failed)
    write_json(report_path, _json_safe(report))
    _print_summary(settings, camera, result, used, dropped, coverage, diag, report_path, plot_path, cov_plot,
                   written=not failed)
    if failed:
        raise CaptureError(
            f"calibration not trusted (--strict): {'; '.join(diag.warnings)}; camera file not written, "
            f"see {report_path} and {cov_plot}"
        )
    return CalibrateOutputs(settings.out, report_path, plot_path, cov_plot, result, diag)


def _json_safe(obj):
    """``obj`` with every non-finite float (a hold-out fold that failed, the covariance of a model the
    views cannot determine) as None: JSON has no inf or NaN, and the report must still be written."""
    import math

    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_json_safe(v) for v in obj]
    return obj


def _category(reason: str) -> str:
    """'near-duplicate of frame 3' -> 'near-duplicate', 'blurred (edges ...)' -> 'blurred'."""
    return reason.split(" (")[0].split(" of ")[0]


def _summary(counter: collections.Counter) -> str:
    return ", ".join(f"{n} {reason}" for reason, n in counter.most_common()) or "none"


def _report(settings, board, footage, examined, used, dropped, result, camera, coverage, diag, timings,
            written) -> dict:
    import cv2
    import numpy as np

    errors = {v.label: v for v in result.views}
    holdout = {v: e for v, e in zip([v.label for v in result.views], result.holdout.view_rms_px)}
    in_view = {v.label: int(n) for v, n in zip(result.views, diag.missed.in_view)}
    return {
        "format": "capture-calibration-report",
        "version": REPORT_VERSION,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "settings": settings.as_dict(),
        "board": {"spec": board.text(), "kind": board.kind, "corners_per_full_view": board.num_corners},
        "input": {"path": str(settings.input), "kind": footage.kind, "frames": footage.count,
                  "frames_examined": examined, "image_size": list(footage.image_size)},
        "camera_written": written,
        "camera": camera_to_dict(camera),
        "rms_px": result.rms_px,
        "num_views": len(used),
        "model": result.model.name,
        "model_holdout_rms_px": result.model_scores,
        "model_not_a_lens": result.implausible,
        "model_predicted_uncertainty_max_px": {k: e.sigma_max_px for k, e in result.model_evidence.items()},
        "model_difference_from_default_max_px": {k: e.difference_aligned_max_px
                                                 for k, e in result.model_evidence.items()},
        "model_note": "hold-out RMS (px), largest predicted 1-sigma over the image (in the camera's fixed frame, "
                      "as the choice uses it) and largest distance from OpenCV's default model (k1-k3+p, up to the "
                      "camera's rotation) of each candidate lens model; OpenCV's default is used unless a richer "
                      "model predicts the left-out views 3 % better, or its own extra terms are not determined "
                      "(predicted uncertainty 3.5x a simpler model's, which agrees with it); a model in "
                      "model_not_a_lens (what is wrong with it) folds over inside the image or is otherwise no real "
                      "lens: never used",
        "holdout": {"folds": result.holdout.folds, "rms_px": result.holdout.rms_px,
                    "spread_max_px": diag.spread_max_px, "spread_at_px": diag.spread_at,
                    "spread_fixed_frame_max_px": diag.spread_fixed_frame_max_px},
        "uncertainty": {"max_px": diag.uncertainty_max_px, "at_px": diag.uncertainty_at,
                        "median_px": diag.uncertainty_median_px, "residual_sigma_px": diag.covariance.sigma_px,
                        "fixed_frame_max_px": diag.uncertainty_fixed_frame_max_px,
                        "note": "1-sigma of where the model sends a ray, from the parameter covariance, up to the "
                                "rotation of the camera frame that the views cannot pin (a take's head poses absorb "
                                "it); fixed_frame_max_px counts that rotation too"},
        "distortion_term_effect_px": diag.term_effects_px,
        "coverage": coverage,
        "coverage_note": "fraction of a 16-column grid over the image holding at least one used corner",
        "coverage_gaps_px": diag.coverage.corner_gaps_px,
        "corners_in_view": int(diag.missed.in_view.sum()),
        "corners_detected": int(diag.missed.detected.sum()),
        "corners_detected_fraction": diag.missed.fraction,
        "corners_note": "board corners that the used views had in view (the corner and its neighbouring squares "
                        "inside the image, by the calibrated camera and each view's pose), and how many of them "
                        "the detector found",
        "uncovered_fraction": diag.coverage.uncovered_fraction,
        "warnings": diag.warnings,
        "std_dev": result.std_dev,
        "flags": {k: getattr(settings, k) for k in
                  ("fix_principal_point", "fix_aspect_ratio", "fix_k3", "zero_tangent", "rational")},
        "outlier_rounds": result.rounds,
        "views": [
            {"label": c.label, "frame": c.frame, "corners": errors[c.label].corners,
             "rms_px": errors[c.label].rms_px, "holdout_rms_px": holdout.get(c.label),
             "corners_in_view": in_view.get(c.label),
             "edge_width_px": round(c.edge_width_px, 2), "square_px": round(c.square_px, 1),
             "tilt_deg": [round(t, 1) for t in c.tilt_deg]}
            for c in used
        ],
        "dropped": [{"label": d.label, "frame": d.frame, "reason": d.reason} for d in dropped],
        "timings": timings,
        "versions": {"opencv": cv2.__version__, "numpy": np.__version__, "python": sys.version.split()[0]},
    }


def _print_summary(settings, camera, result, used, dropped, coverage, diag, report_path, plot_path, cov_plot,
                   written) -> None:
    s = result.std_dev
    reasons = collections.Counter(_category(d.reason) for d in dropped)
    lines = [
        f"calibrated {camera.width}x{camera.height} from {len(used)} views: RMS {result.rms_px:.3f} px, "
        f"hold-out RMS {result.holdout.rms_px:.3f} px, coverage {coverage:.0%}",
        f"  fx {camera.fx:.2f} ± {s.get('fx', 0):.2f}  fy {camera.fy:.2f} ± {s.get('fy', 0):.2f}  "
        f"cx {camera.cx:.2f} ± {s.get('cx', 0):.2f}  cy {camera.cy:.2f} ± {s.get('cy', 0):.2f} px",
        f"  lens model {result.model.name} (hold-out: "
        + ", ".join(f"{k} {v:.3f}" for k, v in result.model_scores.items()) + " px)",
        "  dist " + " ".join(f"{v:+.5f}" for v in camera.dist),
        f"  uncertainty over the image, up to the camera's rotation: median {diag.uncertainty_median_px:.2f} px, "
        f"max {diag.uncertainty_max_px:.2f} px; leaving views out moves it by up to {diag.spread_max_px:.2f} px",
        f"  views used: {', '.join(c.label for c in used)}",
        f"  dropped: {_summary(reasons)}",
    ]
    listed = [d for d in dropped if _category(d.reason) not in ("near-duplicate", "over the cap")]
    lines += [f"    {d.label}: {d.reason}" for d in listed[:20]]
    if len(listed) > 20:
        lines.append(f"    ... {len(listed) - 20} more in {report_path.name}")
    lines += [f"warning: {w}" for w in diag.warnings]
    written_files = ([str(settings.out)] if written else []) + [str(report_path), str(plot_path), str(cov_plot)]
    lines.append(f"wrote {', '.join(written_files)}")
    print("\n".join(lines))
