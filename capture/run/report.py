"""``report.json`` of a run and the one-screen summary printed at the end.

The report holds per-frame errors (reprojection in pixels for video, 3D in mm for fit3d), the skipped
frames and why, timings per stage (``status: skipped`` when a stage found its work done), versions,
the resolved settings and the camera's provenance (including the default-camera flag).
"""

from __future__ import annotations

import math
import platform
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from capture.io.atomic import write_json

REPORT_JSON = "report.json"


def versions() -> dict:
    import capture

    out = {"python": platform.python_version(), "capture": capture.__version__}
    from importlib.metadata import PackageNotFoundError, version

    for mod, key in (("torch", "torch"), ("onnxruntime", "onnxruntime"), ("cv2", "opencv"), ("numpy", "numpy")):
        try:
            if mod == "torch" and mod not in sys.modules:
                out[key] = version("torch")     # without importing it: a run's parent process need not
            else:
                out[key] = __import__(mod).__version__
        except (ImportError, PackageNotFoundError, AttributeError):  # pragma: no cover - optional
            out[key] = None
    return out


@dataclass
class FrameSummary:
    """What the report keeps of one frame's fit (the meshes stay on disk)."""

    frame: int
    status: str
    error: float | None        # confident-landmark reprojection RMS (px) or 3D error (mm)
    error_all: float | None = None


def finite_or_none(v) -> float | None:
    """``v`` as a float where it is a finite number, else None (a frame's error in the report's rows)."""
    try:
        v = float(v)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def frame_table(fits: Sequence[Any], error_key: str, errors: Sequence[float | None],
                skip_reasons: dict[int, str]) -> tuple[list[dict], list[dict]]:
    """Per-frame rows and the skipped frames with their reason.

    A frame is skipped when it has a reason in ``skip_reasons`` (no face found) or the fit says so.
    Such a frame is not fitted to any detection; when the fit bridged it (``status: bridged``: the
    temporal prior carries the neighbours' motion through it) its mesh is still exported, and the
    skipped entry says so.
    """
    rows, skipped = [], []
    for f, e in zip(fits, errors):
        i = int(f.frame)
        status = str(getattr(f, "status", "fitted"))
        reason = skip_reasons.get(i)
        rows.append({"frame": i, "status": status, error_key: finite_or_none(e), "face_found": i not in skip_reasons})
        if reason is not None or status == "skipped":
            entry = {"frame": i, "reason": reason or "not fitted"}
            if status == "bridged":
                entry["output"] = "mesh bridged from the neighbouring frames by the temporal prior"
            skipped.append(entry)
    return rows, skipped


def error_stats(values: Sequence[float | None]) -> dict:
    v = np.array([x for x in values if x is not None and math.isfinite(x)], np.float64)
    if v.size == 0:
        return {"mean": None, "median": None, "max": None, "worst_frame": None}
    return {"mean": float(v.mean()), "median": float(np.median(v)), "max": float(v.max())}


def write_report(out_dir: Path, report: dict) -> Path:
    return write_json(Path(out_dir) / REPORT_JSON, report)


def summary_lines(report: dict) -> list[str]:
    """The one-screen summary (plain text lines)."""
    fr = report["frames"]
    unit = report["error"]["unit"]
    stats = report["error"]
    lines = [f"{report['command']}: {fr['requested']} frames requested, {fr['fitted']} fitted, "
             f"{fr['skipped']} skipped"]
    if stats["mean"] is not None:
        worst = stats.get("worst_frame")
        which = f" ({stats['landmarks']} landmarks)" if stats.get("landmarks") else ""
        lines.append(f"{report['error']['kind']}{which}: mean {stats['mean']:.2f} {unit}, worst {stats['max']:.2f} {unit}"
                     + (f" (frame {worst})" if worst is not None else ""))
    for s in report["skipped_frames"][:5]:
        lines.append(f"  skipped frame {s['frame']}: {s['reason']}")
    if len(report["skipped_frames"]) > 5:
        lines.append(f"  ... {len(report['skipped_frames']) - 5} more skipped frames in report.json")
    cam = report.get("camera")
    if cam is not None and cam.get("is_default"):
        lines.append("camera: DEFAULT GUESS (60 deg field of view, no distortion); pass --camera for accurate results")
    for n in report.get("notes", []):
        if n and not n.startswith("no --camera"):
            lines.append(n)
    t = ", ".join(f"{s['stage']} {s['status']} {s['seconds']:.1f}s" for s in report["stages"])
    lines.append(f"stages: {t}")
    lines.append(f"outputs in {report['out_dir']}: " + ", ".join(report["outputs"][:6])
                 + (", ..." if len(report["outputs"]) > 6 else ""))
    return lines


def unexplained_section(tally, fps: float, max_notes: int = 3) -> tuple[dict, list[str]]:
    """The report's ``unexplained`` section and its notes, from a :class:`capture.fit.unexplained.ResidualTally`
    of the take's fitted frames: the landmark noise it read and the runs of frames where a face region's landmarks
    are fitted well above it (the first ``max_notes`` of them also as notes, with the reading)."""
    from capture.fit.unexplained import MAX_GAP, MIN_FRAMES, MIN_LANDMARKS, MIN_SIGMA_PX, P_FALSE, RATIO, REGIONS

    if tally is None:
        return {"noise_px": None, "spans": []}, []
    rule = {"ratio": RATIO, "min_frames": MIN_FRAMES, "max_gap": MAX_GAP, "p_false": P_FALSE}
    sigma, spans = tally.spans(**rule)
    section = {"noise_px": round(sigma, 4) if np.isfinite(sigma) else None,
               "regions": {name: int((tally.labels == k).sum()) for k, name in enumerate(REGIONS)},
               "rule": {**rule, "min_landmarks": MIN_LANDMARKS, "min_noise_px": MIN_SIGMA_PX,
                        "meaning": "a region's RMS residual over ratio x the noise's (sqrt(2) max(noise_px, "
                                   "min_noise_px)) and over "
                                   "what its landmark count reaches by chance with probability p_false, for "
                                   "min_frames frames or more (gaps of max_gap frames joined)"},
               "spans": [{**sp.to_dict(), "first_s": round(sp.first / fps, 3), "last_s": round(sp.last / fps, 3)}
                         for sp in spans]}
    if not spans:
        return section, []
    named = {"mouth": "the mouth", "eyes": "the eyes", "face": "the rest of the face"}
    regions = [named[r] for r in sorted({sp.region for sp in spans}, key=REGIONS.index)]
    where = regions[0] if len(regions) == 1 else ", ".join(regions[:-1]) + " and " + regions[-1]
    notes = [f"the actor does not explain the landmarks of {where} in {len(spans)} run(s) of frames "
             f"({unexplained_frames(section)} frames): there the fit stays above the take's landmark noise "
             f"({max(sigma, MIN_SIGMA_PX):.2f} px per axis). Either the performance goes beyond the actor's "
             f"training shapes, and the mesh can be about a millimetre off there, mostly in depth (add a scan of "
             f"that expression to the actor), or the detector erred there (the overlay shows which); report.json "
             f"'unexplained'"]
    for sp in spans[:max_notes]:
        notes.append(f"  {sp.region}, frames {sp.first}-{sp.last} ({sp.first / fps:.1f}-{sp.last / fps:.1f} s): "
                     f"{sp.mean_ratio:.1f}x the noise, at most {sp.peak_ratio:.1f}x (frame {sp.peak_frame})")
    if len(spans) > max_notes:
        notes.append(f"  ... {len(spans) - max_notes} more run(s) in report.json")
    return section, notes


def unexplained_frames(section: dict | None) -> int | None:
    """How many frames the runs of a report's ``unexplained`` section cover (a frame in runs of two regions
    once); None for a report without the section (made before it existed)."""
    if not section:
        return None
    return len({f for sp in section.get("spans", []) for f in range(int(sp["first"]), int(sp["last"]) + 1)})


def print_summary(report: dict) -> None:
    from rich.console import Console
    from rich.panel import Panel

    Console(stderr=False).print(Panel("\n".join(summary_lines(report)), title="capture", expand=False))
