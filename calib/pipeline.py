"""The ``capture calibrate`` stage: footage in; camera file, report JSON and figure out.

``run_calibrate(settings) -> Path`` reads the footage (:mod:`calib.frames`), detects the board
(:mod:`calib.detect`), chooses views (:mod:`calib.views`), calibrates (:mod:`calib.calibrate`) and
writes, all atomically:

- the camera file ``--out`` (``.json``: the project's format; ``.yaml``/``.yml``/``.xml``: OpenCV's),
- ``<stem>.report.json`` beside it: resolved settings, input, views used and dropped with reasons,
  per-view errors, standard deviations, coverage, timings and versions,
- ``<stem>.report.png`` beside it: corner coverage and per-view errors (:mod:`calib.plots`).
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
from calib.calibrate import CalibrationOptions, CalibrationResult, calibrate_views
from calib.camera_io import camera_to_dict, write_camera
from calib.detect import BoardDetector
from calib.frames import open_footage
from calib.plots import save_calibration_plot
from calib.views import Candidate, Dropped, coverage_fraction, make_candidate, select_views
from capture.io.atomic import write_json
from capture.io.errors import CaptureError

REPORT_VERSION = 1


@dataclass(frozen=True)
class CalibrateSettings:
    """Resolved settings of one ``capture calibrate`` run (saved verbatim in the report)."""

    input: Path
    board: str
    out: Path = Path("camera.json")
    max_views: int = 40
    max_candidates: int = 300
    min_views: int = 6
    min_corners: int = 6
    blur_threshold: float = 0.6
    duplicate_px: float | None = None
    outlier_factor: float = 3.0
    fix_principal_point: bool = False
    fix_aspect_ratio: bool = False
    fix_k3: bool = False
    zero_tangent: bool = False
    rational: bool = False
    progress: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "input", Path(self.input))
        object.__setattr__(self, "out", Path(self.out))

    def options(self) -> CalibrationOptions:
        return CalibrationOptions(
            fix_principal_point=self.fix_principal_point, fix_aspect_ratio=self.fix_aspect_ratio,
            fix_k3=self.fix_k3, zero_tangent=self.zero_tangent, rational=self.rational,
            min_views=self.min_views, outlier_factor=self.outlier_factor,
        )

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        return {k: (str(v) if isinstance(v, Path) else v) for k, v in d.items()}


@dataclass(frozen=True)
class CalibrateOutputs:
    camera: Path
    report: Path
    plot: Path
    result: CalibrationResult


def report_paths(out: Path) -> tuple[Path, Path]:
    return out.with_name(out.stem + ".report.json"), out.with_name(out.stem + ".report.png")


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
    if not 0.0 <= s.blur_threshold < 1.0:
        raise CaptureError(f"--blur-threshold must be in [0, 1), got {s.blur_threshold}")
    if s.outlier_factor != 0 and s.outlier_factor < 1.5:
        raise CaptureError(f"--outlier-factor must be 0 (off) or at least 1.5, got {s.outlier_factor}")
    return board


def _detect_all(footage, detector, settings) -> tuple[list[Candidate], list[Dropped], int]:
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    total = min(footage.count, -(-footage.count // footage.stride(settings.max_candidates)))
    candidates: list[Candidate] = []
    dropped: list[Dropped] = []
    examined = 0
    progress = Progress(TextColumn("detecting board"), BarColumn(), MofNCompleteColumn(),
                        TimeRemainingColumn(), console=Console(stderr=True), disable=not settings.progress,
                        transient=True)
    with progress:
        task = progress.add_task("detect", total=total)
        for label, frame, gray in footage.frames(settings.max_candidates):
            examined += 1
            detection, reason = detector.detect(gray)
            if detection is None:
                dropped.append(Dropped(label, frame, reason))
            else:
                candidates.append(make_candidate(label, frame, gray, detection))
            progress.advance(task)
    return candidates, dropped, examined


def run_calibrate(settings: CalibrateSettings) -> CalibrateOutputs:
    """Run the whole stage (see the module docstring); returns the paths written and the result."""
    t0 = time.perf_counter()
    board = _check_settings(settings)
    footage = open_footage(settings.input)
    detector = BoardDetector(board, settings.min_corners)

    t_detect = time.perf_counter()
    candidates, dropped, examined = _detect_all(footage, detector, settings)
    t_select = time.perf_counter()
    if not candidates:
        reasons = collections.Counter(d.reason for d in dropped)
        raise CaptureError(
            f"no board found in any of the {examined} frames examined in {settings.input} "
            f"({_summary(reasons)}); check --board {board.text()} (charuco cols/rows count squares, "
            "checker cols/rows count inner corners) and the ArUco dictionary"
        )
    chosen, more_dropped = select_views(candidates, footage.image_size, settings.max_views,
                                        settings.blur_threshold, settings.duplicate_px)
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
    result = calibrate_views(
        [c.detection.object_points for c in chosen], [c.detection.image_points for c in chosen],
        [c.label for c in chosen], footage.image_size, settings.options(), provenance,
    )
    rejected = {v.label for v in result.rejected}
    for c in chosen:
        if c.label in rejected:
            err = next(v.rms_px for v in result.rejected if v.label == c.label)
            dropped.append(Dropped(c.label, c.frame, f"outlier (view RMS {err:.3f} px)"))
    dropped.sort(key=lambda d: d.frame)
    used = [c for c in chosen if c.label not in rejected]
    provenance += f", {len(used)} views, RMS {result.rms_px:.3f} px"
    camera = result.camera.with_provenance(provenance)
    t_write = time.perf_counter()

    report_path, plot_path = report_paths(settings.out)
    coverage = coverage_fraction([c.detection.image_points for c in used], footage.image_size)
    write_camera(settings.out, camera)
    save_calibration_plot(
        plot_path, footage.image_size, [c.detection.image_points for c in used],
        [v.label for v in result.views], [v.rms_px for v in result.views],
        [v.label for v in result.rejected], [v.rms_px for v in result.rejected], result.rms_px,
        title=f"{settings.input.name}: RMS {result.rms_px:.3f} px, {len(used)} views, coverage {coverage:.0%}",
    )
    timings = {
        "open_s": t_detect - t0, "detect_s": t_select - t_detect, "select_s": t_calib - t_select,
        "calibrate_s": t_write - t_calib, "write_s": time.perf_counter() - t_write,
    }
    report = _report(settings, board, footage, examined, used, dropped, result, camera, coverage, timings)
    write_json(report_path, report)
    _print_summary(settings, camera, result, used, dropped, coverage, report_path, plot_path)
    return CalibrateOutputs(settings.out, report_path, plot_path, result)


def _category(reason: str) -> str:
    """'near-duplicate of frame 3' -> 'near-duplicate', 'blurred (sharpness ...)' -> 'blurred'."""
    return reason.split(" (")[0].split(" of ")[0]


def _summary(counter: collections.Counter) -> str:
    return ", ".join(f"{n} {reason}" for reason, n in counter.most_common()) or "none"


def _report(settings, board, footage, examined, used, dropped, result, camera, coverage, timings) -> dict:
    import cv2
    import numpy as np

    errors = {v.label: v for v in result.views}
    return {
        "format": "capture-calibration-report",
        "version": REPORT_VERSION,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "settings": settings.as_dict(),
        "board": {"spec": board.text(), "kind": board.kind, "corners_per_full_view": board.num_corners},
        "input": {"path": str(settings.input), "kind": footage.kind, "frames": footage.count,
                  "frames_examined": examined, "image_size": list(footage.image_size)},
        "camera": camera_to_dict(camera),
        "rms_px": result.rms_px,
        "num_views": len(used),
        "coverage": coverage,
        "coverage_note": "fraction of a 16-column grid over the image holding at least one used corner",
        "std_dev": result.std_dev,
        "flags": {k: getattr(settings, k) for k in
                  ("fix_principal_point", "fix_aspect_ratio", "fix_k3", "zero_tangent", "rational")},
        "outlier_rounds": result.rounds,
        "views": [
            {"label": c.label, "frame": c.frame, "corners": errors[c.label].corners,
             "rms_px": errors[c.label].rms_px, "sharpness": round(c.sharpness, 4),
             "tilt_deg": [round(t, 1) for t in c.tilt_deg]}
            for c in used
        ],
        "dropped": [{"label": d.label, "frame": d.frame, "reason": d.reason} for d in dropped],
        "timings": timings,
        "versions": {"opencv": cv2.__version__, "numpy": np.__version__, "python": sys.version.split()[0]},
    }


def _print_summary(settings, camera, result, used, dropped, coverage, report_path, plot_path) -> None:
    s = result.std_dev
    reasons = collections.Counter(_category(d.reason) for d in dropped)
    lines = [
        f"calibrated {camera.width}x{camera.height} from {len(used)} views: RMS {result.rms_px:.3f} px, "
        f"coverage {coverage:.0%}",
        f"  fx {camera.fx:.2f} ± {s.get('fx', 0):.2f}  fy {camera.fy:.2f} ± {s.get('fy', 0):.2f}  "
        f"cx {camera.cx:.2f} ± {s.get('cx', 0):.2f}  cy {camera.cy:.2f} ± {s.get('cy', 0):.2f} px",
        "  dist " + " ".join(f"{v:+.5f}" for v in camera.dist),
        f"  views used: {', '.join(c.label for c in used)}",
        f"  dropped: {_summary(reasons)}",
        f"wrote {settings.out}, {report_path}, {plot_path}",
    ]
    print("\n".join(lines))
