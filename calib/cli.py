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
    max_views: Annotated[int, typer.Option(help="Use at most this many views (chosen for coverage and tilt).")] = 40,
    max_frames: Annotated[int, typer.Option(
        help="Examine at most this many evenly spaced frames of a video (or images of a folder).")] = 300,
    min_views: Annotated[int, typer.Option(help="Fail unless at least this many usable views remain.")] = 6,
    min_corners: Annotated[int, typer.Option(help="Ignore ChArUco views with fewer detected corners.")] = 6,
    blur_threshold: Annotated[float, typer.Option(
        help="Drop views less sharp than this fraction of the sharpest views (90th percentile); 0 keeps all.")] = 0.6,
    outlier_factor: Annotated[float, typer.Option(
        help="Reject views whose RMS exceeds this multiple of the median view RMS, then recalibrate; 0 = off.")] = 3.0,
    fix_principal_point: Annotated[bool, typer.Option(
        help="Keep the principal point at the image centre ((w-1)/2, (h-1)/2).")] = False,
    fix_aspect_ratio: Annotated[bool, typer.Option(help="Force fx = fy (square pixels).")] = False,
    fix_k3: Annotated[bool, typer.Option(
        help="Estimate k1, k2, p1, p2 only (k3 = 0): for narrow lenses or few views.")] = False,
    zero_tangent: Annotated[bool, typer.Option(help="Force p1 = p2 = 0.")] = False,
    rational: Annotated[bool, typer.Option(help="Also estimate k4, k5, k6 (wide lenses, many views).")] = False,
    progress: Annotated[bool, typer.Option(help="Show a progress bar on stderr.")] = True,
    duplicate_px: Annotated[Optional[float], typer.Option(
        help="Views whose shared corners moved less than this (pixels) are near-duplicates "
        "(default: 1% of the image diagonal).", show_default=False)] = None,
) -> None:
    """Intrinsics and distortion from ChArUco or checkerboard footage.

    INPUT is a video file or a folder of images. Detects the board with
    OpenCV, keeps sharp, non-duplicate views covering the image and many
    board tilts, calibrates with OpenCV (rejecting outlier views), and
    writes the camera file, a JSON report (views used and dropped and why,
    per-view errors, standard deviations of fx, fy, cx, cy) and a PNG.

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
        min_views=min_views, min_corners=min_corners, blur_threshold=blur_threshold,
        duplicate_px=duplicate_px, outlier_factor=outlier_factor,
        fix_principal_point=fix_principal_point, fix_aspect_ratio=fix_aspect_ratio, fix_k3=fix_k3,
        zero_tangent=zero_tangent, rational=rational, progress=progress,
    ))
