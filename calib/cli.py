"""``capture calibrate``: camera intrinsics and distortion from ChArUco or checkerboard footage.

Only option declarations live here; the work is :func:`calib.pipeline.run_calibrate`. Heavy
imports (OpenCV, matplotlib) happen when the command runs, not when ``capture --help`` loads.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

_BOARD_HELP = "Board SPEC: charuco:... or checker:... (grammar above)."


def calibrate_command(
    input: Annotated[Path, typer.Argument(help="Board footage: a video file or a folder of images.",
                                          metavar="INPUT", show_default=False)],
    board: Annotated[str, typer.Option("--board", help=_BOARD_HELP, show_default=False)],
    out: Annotated[Path, typer.Option(
        "--out", help="Camera file to write: .json (capture format) or .yaml/.yml/.xml (OpenCV). "
        "<stem>.report.json and <stem>.report.png are written beside it.")] = Path("camera.json"),
    max_views: Annotated[int, typer.Option(
        help="Use at most this many views (bounds the cost; over it, distinct views chosen for coverage and "
        "tilt come first, near-duplicates last).")] = 60,
    max_frames: Annotated[int, typer.Option(
        help="Examine at most this many evenly spaced frames of a video (or images of a folder).")] = 300,
    min_views: Annotated[int, typer.Option(
        help="Fail unless at least this many usable views remain (fewer than 6 get warnings).")] = 4,
    min_corners: Annotated[int, typer.Option(help="Ignore ChArUco views with fewer detected corners.")] = 6,
    max_blur: Annotated[float, typer.Option(
        help="Drop views whose board edges are wider than this fraction of the board's square size in "
        "that view (too blurred for sub-pixel corners); 0 keeps all.")] = 0.4,
    outlier_factor: Annotated[float, typer.Option(
        help="After a first solve, reject views whose RMS exceeds this multiple of the median view RMS "
        "and 1 px, then recalibrate; 0 = off.")] = 3.0,
    model: Annotated[str, typer.Option(
        help="Lens distortion model: auto (OpenCV's default unless the hold-out check and the covariance "
        "clearly support another) or one of k1-k2, k1-k2+p, k1-k3, k1-k3+p (OpenCV's default), k1-k6, "
        "k1-k6+p (rational).")] = "auto",
    tolerance_px: Annotated[float, typer.Option(
        help="Warn when image corners are not covered, or when the predicted 2-sigma uncertainty, the "
        "hold-out spread or the difference to an equally good lens model exceeds this many pixels "
        "anywhere in the image.")] = 1.0,
    strict: Annotated[bool, typer.Option(
        help="Fail (no camera file) instead of warning when the model extrapolates or is not determined.")] = False,
    fix_principal_point: Annotated[bool, typer.Option(
        help="Keep the principal point at the image centre ((w-1)/2, (h-1)/2).")] = False,
    fix_aspect_ratio: Annotated[bool, typer.Option(help="Force fx = fy (square pixels).")] = False,
    fix_k3: Annotated[bool, typer.Option(
        help="Only consider models without k3 (k1-k2, k1-k2+p).")] = False,
    zero_tangent: Annotated[bool, typer.Option(help="Only consider models without p1, p2.")] = False,
    rational: Annotated[bool, typer.Option(
        help="Only consider the rational models (k1-k6, k1-k6+p; wide lenses, many views).")] = False,
    progress: Annotated[bool, typer.Option(help="Show a progress bar on stderr.")] = True,
    duplicate_px: Annotated[Optional[float], typer.Option(
        help="Views whose shared corners moved less than this (pixels) are near-duplicates "
        "(default: 1% of the image diagonal).", show_default=False)] = None,
) -> None:
    """Intrinsics and distortion from ChArUco or checkerboard footage.

    INPUT is a video file or a folder of images. Detects the board with
    OpenCV and drops only unusable views (too few corners, failed geometric
    check, too blurred for sub-pixel corners, near-duplicates, outliers
    after a first solve; over --max-views the most useful are kept).
    Calibrates with OpenCV, choosing the lens model by a hold-out check and
    the parameter covariance, and writes the camera file, a JSON report
    (views used and dropped and why, hold-out errors, uncertainty,
    warnings) and two PNGs (per-view errors; coverage heat map, predicted
    uncertainty, hold-out spread).
    Warns when the model extrapolates or is not determined; --strict fails.

    Board SPEC grammar (lengths in mm):

      charuco:cols=C,rows=R,square=S,marker=M,dict=NAME

        ChArUco board of C x R squares, square side S, marker side M < S,
        NAME an OpenCV ArUco dictionary such as DICT_5X5_100. Append
        ,legacy=1 for boards with an even number of rows printed with
        OpenCV older than 4.6.

      checker:cols=C,rows=R,square=S

        Chessboard of C x R inner corners, square side S; keep it fully
        in view.

    Example: --board charuco:cols=11,rows=8,square=30,marker=22,dict=DICT_5X5_100
    """
    from calib.pipeline import CalibrateSettings, run_calibrate

    run_calibrate(CalibrateSettings(
        input=input, board=board, out=out, max_views=max_views, max_candidates=max_frames,
        min_views=min_views, min_corners=min_corners, max_blur=max_blur,
        duplicate_px=duplicate_px, outlier_factor=outlier_factor, model=model,
        fix_principal_point=fix_principal_point, fix_aspect_ratio=fix_aspect_ratio, fix_k3=fix_k3,
        zero_tangent=zero_tangent, rational=rational, tolerance_px=tolerance_px, strict=strict,
        progress=progress,
    ))
