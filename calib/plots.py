"""The calibration figure a person looks at: corner coverage over the image and per-view errors."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from calib.views import COVERAGE_COLS, cells_of, grid_shape
from capture.io.atomic import atomic_path


def save_calibration_plot(
    path: str | os.PathLike,
    image_size: tuple[int, int],
    view_points: list[np.ndarray],
    view_labels: list[str],
    view_errors: list[float],
    rejected_labels: list[str],
    rejected_errors: list[float],
    rms_px: float,
    title: str = "",
) -> Path:
    """Write a PNG: left, every used corner over the image frame (one colour per view); right,
    per-view RMS reprojection error bars (rejected outlier views in red) with the overall RMS."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure  # no pyplot: no global state, no GUI backend

    w, h = image_size
    fig = Figure(figsize=(13, 5.2), dpi=100, layout="constrained")
    ax0, ax1 = fig.subplots(1, 2, width_ratios=[1.15, 1])
    cmap = matplotlib.colormaps["viridis"]
    gx, gy = grid_shape(image_size, COVERAGE_COLS)
    covered = cells_of(np.concatenate(view_points), image_size, COVERAGE_COLS) if view_points else set()
    for cell in covered:  # the coverage grid the report's "coverage" counts
        cx, cy = cell % gx, cell // gx
        ax0.add_patch(matplotlib.patches.Rectangle(
            (cx * w / gx - 0.5, cy * h / gy - 0.5), w / gx, h / gy, color="tab:green", alpha=0.12, lw=0))
    for k, pts in enumerate(view_points):
        ax0.scatter(pts[:, 0], pts[:, 1], s=6, color=cmap(k / max(1, len(view_points) - 1)), linewidths=0)
    ax0.add_patch(matplotlib.patches.Rectangle((-0.5, -0.5), w, h, fill=False, color="k", lw=1.5))
    ax0.set_xlim(-0.02 * w, 1.02 * w)
    ax0.set_ylim(1.02 * h, -0.02 * h)  # image rows grow downwards
    ax0.set_aspect("equal")
    ax0.set_title(f"corners of {len(view_points)} views over the {w}x{h} image "
                  f"(green: covered cells, {len(covered) / (gx * gy):.0%})")
    ax0.set_xlabel("u (px)")
    ax0.set_ylabel("v (px)")

    labels = list(view_labels) + list(rejected_labels)
    errors = list(view_errors) + list(rejected_errors)
    colours = ["tab:blue"] * len(view_labels) + ["tab:red"] * len(rejected_labels)
    x = np.arange(len(labels))
    ax1.bar(x, errors, color=colours)
    ax1.axhline(rms_px, color="k", ls="--", lw=1, label=f"overall RMS {rms_px:.3f} px")
    ax1.set_xticks(x, labels, rotation=90, fontsize=7 if len(labels) < 40 else 5)
    ax1.set_ylabel("RMS reprojection error (px)")
    ax1.set_title("per-view error" + (" (red: rejected outliers)" if rejected_labels else ""))
    ax1.legend(loc="upper right")
    if title:
        fig.suptitle(title)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)
