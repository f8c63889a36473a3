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


def save_coverage_plot(path: str | os.PathLike, diag, view_points: list[np.ndarray], title: str = "") -> Path:
    """Write a PNG of what the calibration knows where (``diag``: a :class:`calib.diagnostics.Diagnostics`):
    left, used corners per cell as a heat map (white: no corner); middle, the predicted 1-sigma pixel
    uncertainty; right, the hold-out spread (both up to the camera's rotation, :mod:`calib.uncertainty`).
    The middle and right panels share a colour scale in px, with the ``tolerance_px`` contour drawn; black
    dots are the used corners. With ``diag.missed`` (:func:`calib.diagnostics.missed_corners`) the left panel
    also marks in red the board corners that were in view but not detected, and says which share was found."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    w, h = diag.image_size
    nx, ny = diag.grid_shape
    fig = Figure(figsize=(18, 5.0), dpi=90, layout="constrained")
    axes = fig.subplots(1, 3)
    counts = diag.coverage.counts.astype(float)
    shown = np.where(counts > 0, counts, np.nan)
    im = axes[0].imshow(shown, extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap="inferno_r", vmin=0,
                        vmax=max(2.0, float(counts.max())), interpolation="nearest")
    fig.colorbar(im, ax=axes[0], shrink=0.8, label="used corners per cell")
    gaps = ", ".join(f"{v:.0f}" for v in diag.coverage.corner_gaps_px.values())
    found = ""
    if diag.missed is not None:
        found = (f"\nboard corners in view detected: {diag.missed.fraction:.0%} "
                 f"({len(diag.missed.missed_px)} missed, red x)")
        axes[0].scatter(diag.missed.missed_px[:, 0], diag.missed.missed_px[:, 1], s=14, c="#ff0000", marker="x",
                        linewidths=1.0, zorder=3)
    axes[0].set_title(f"coverage: {1 - diag.coverage.uncovered_fraction:.0%} of the image within "
                      f"{diag.coverage.reach_px:.0f} px of a corner\nimage-corner gaps TL, TR, BL, BR: {gaps} px"
                      + found, fontsize=9)
    vmax = max(diag.tolerance_px, float(diag.uncertainty_px.max()), float(diag.spread_px.max()))
    for ax, values, name in ((axes[1], diag.uncertainty_px, "predicted uncertainty (1 sigma, up to rotation)"),
                             (axes[2], diag.spread_px, "hold-out spread (max over folds, up to rotation)")):
        img = values.reshape(ny, nx)
        im = ax.imshow(img, extent=(-0.5, w - 0.5, h - 0.5, -0.5), cmap="viridis", vmin=0, vmax=vmax,
                       interpolation="bilinear")
        xs, ys = diag.grid[:nx, 0], diag.grid[::nx, 1]
        if img.max() > diag.tolerance_px > img.min():
            ax.contour(xs, ys, img, levels=[diag.tolerance_px], colors="w", linewidths=1.2)
        fig.colorbar(im, ax=ax, shrink=0.8, label="px")
        ax.set_title(f"{name}: max {values.max():.2f} px (white: {diag.tolerance_px:g} px)", fontsize=9)
    for ax in axes:
        if view_points:
            pts = np.concatenate(view_points)
            ax.scatter(pts[:, 0], pts[:, 1], s=1.5, c="k", linewidths=0)
        ax.set_xlim(-0.5, w - 0.5)
        ax.set_ylim(h - 0.5, -0.5)
        ax.set_aspect("equal")
    if title or diag.warnings:
        fig.suptitle((title + ("  -  " if title and diag.warnings else "")
                      + (f"{len(diag.warnings)} warning(s), see report" if diag.warnings else "")), fontsize=10)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return Path(path)
