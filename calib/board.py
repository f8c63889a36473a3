"""Calibration boards: the ``--board SPEC`` grammar and the board's geometry.

Grammar (case-insensitive keys, lengths in millimetres, no spaces needed)::

    charuco:cols=C,rows=R,square=S,marker=M,dict=NAME[,legacy=0|1]
    checker:cols=C,rows=R,square=S

- ``charuco``: a ChArUco board of ``C x R`` *squares* (as OpenCV's ``CharucoBoard((C, R), ...)``),
  chessboard squares of side ``S`` mm and ArUco markers of side ``M`` mm (``M < S``), markers from
  the OpenCV dictionary ``NAME`` (e.g. ``DICT_5X5_100``; the ``DICT_`` prefix may be omitted).
  ``legacy=1`` selects the pre-4.6 OpenCV layout for boards with an even number of rows that were
  printed with old tools.
- ``checker``: a plain chessboard with ``C x R`` *inner corners* (as ``cv2.findChessboardCorners``'s
  pattern size) and squares of side ``S`` mm. The whole board must be visible in a view.

Example: ``charuco:cols=11,rows=8,square=30,marker=22,dict=DICT_5X5_100``.
This module only parses and describes; detection is in :mod:`calib.detect`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from capture.io.errors import CaptureError

GRAMMAR = (
    "charuco:cols=C,rows=R,square=S,marker=M,dict=NAME[,legacy=0|1] (C x R squares, mm) "
    "or checker:cols=C,rows=R,square=S (C x R inner corners, mm)"
)

_KEYS = {
    "charuco": ({"cols", "rows", "square", "marker", "dict"}, {"legacy"}),
    "checker": ({"cols", "rows", "square"}, set()),
}


@dataclass(frozen=True)
class BoardSpec:
    """A parsed board: ``kind`` is ``"charuco"`` or ``"checker"``; lengths in mm."""

    kind: str
    cols: int
    rows: int
    square_mm: float
    marker_mm: float | None = None
    dictionary: str | None = None
    legacy: bool = False

    @property
    def num_corners(self) -> int:
        """Corners a full view yields (inner chessboard corners)."""
        if self.kind == "charuco":
            return (self.cols - 1) * (self.rows - 1)
        return self.cols * self.rows

    @property
    def corner_grid(self) -> tuple[int, int]:
        """(columns, rows) of the inner-corner grid that corner ids number row by row."""
        return (self.cols - 1, self.rows - 1) if self.kind == "charuco" else (self.cols, self.rows)

    @property
    def size_mm(self) -> tuple[float, float]:
        """Width and height of the chessboard area in mm (checker: outer squares included)."""
        if self.kind == "charuco":
            return self.cols * self.square_mm, self.rows * self.square_mm
        return (self.cols + 1) * self.square_mm, (self.rows + 1) * self.square_mm

    def text(self) -> str:
        """The canonical SPEC string (parses back to an equal spec)."""
        if self.kind == "charuco":
            s = (f"charuco:cols={self.cols},rows={self.rows},square={self.square_mm:g},"
                 f"marker={self.marker_mm:g},dict={self.dictionary}")
            return s + (",legacy=1" if self.legacy else "")
        return f"checker:cols={self.cols},rows={self.rows},square={self.square_mm:g}"

    def corner_object_points(self) -> np.ndarray:
        """(num_corners, 3) float32 board coordinates (mm, z = 0) of corner ids 0, 1, ...

        Both kinds number inner corners row by row from the top-left; a corner at inner grid
        position (i, j) (column i, row j) sits at ``((i + 1) S, (j + 1) S, 0)`` for ChArUco (as
        OpenCV's ``CharucoBoard.getChessboardCorners``) and ``(i S, j S, 0)`` for a checker.
        """
        nx, ny = self.corner_grid
        off = 1.0 if self.kind == "charuco" else 0.0
        i, j = np.meshgrid(np.arange(nx), np.arange(ny))
        pts = np.stack([(i.ravel() + off) * self.square_mm, (j.ravel() + off) * self.square_mm,
                        np.zeros(nx * ny)], axis=1)
        return pts.astype(np.float32)


def aruco_dictionary_names() -> list[str]:
    import cv2

    return sorted(n for n in dir(cv2.aruco) if n.startswith("DICT_") and n == n.upper())


def parse_board(spec: str) -> BoardSpec:
    """Parse ``--board SPEC`` (grammar in the module docstring); one-line CaptureError if it does not parse."""
    text = (spec or "").strip()
    m = re.fullmatch(r"([A-Za-z]+)\s*:\s*(.*)", text)
    if not m:
        raise CaptureError(f"board spec {spec!r} does not parse; expected {GRAMMAR}")
    kind = m.group(1).lower()
    if kind not in _KEYS:
        raise CaptureError(f"board kind {m.group(1)!r} is unknown; expected {GRAMMAR}")
    values: dict[str, str] = {}
    for item in filter(None, (p.strip() for p in m.group(2).split(","))):
        if "=" not in item:
            raise CaptureError(f"board spec item {item!r} is not key=value; expected {GRAMMAR}")
        key, value = (s.strip() for s in item.split("=", 1))
        key = key.lower()
        if key in values:
            raise CaptureError(f"board spec gives {key!r} twice; expected {GRAMMAR}")
        values[key] = value
    required, optional = _KEYS[kind]
    unknown = sorted(set(values) - required - optional)
    if unknown:
        raise CaptureError(f"board spec key(s) {', '.join(unknown)} unknown for {kind}; expected {GRAMMAR}")
    missing = sorted(required - set(values))
    if missing:
        raise CaptureError(f"board spec for {kind} is missing {', '.join(missing)}; expected {GRAMMAR}")

    cols = _int(values["cols"], "cols")
    rows = _int(values["rows"], "rows")
    square = _length(values["square"], "square")
    if kind == "checker":
        if cols < 2 or rows < 2:
            raise CaptureError(f"checker board needs at least 2x2 inner corners, got {cols}x{rows}")
        return BoardSpec("checker", cols, rows, square)

    if cols < 3 or rows < 3:
        raise CaptureError(f"ChArUco board needs at least 3x3 squares, got {cols}x{rows}")
    marker = _length(values["marker"], "marker")
    if marker >= square:
        raise CaptureError(f"ChArUco marker size {marker:g} mm must be smaller than the square size {square:g} mm")
    name = values["dict"].upper()
    if not name.startswith("DICT_"):
        name = "DICT_" + name
    names = aruco_dictionary_names()
    if name not in names:
        raise CaptureError(f"ArUco dictionary {values['dict']!r} is unknown; use one of {', '.join(names)}")
    legacy_text = values.get("legacy", "0").lower()
    if legacy_text not in ("0", "1", "true", "false", "yes", "no"):
        raise CaptureError(f"board spec legacy={values['legacy']!r} must be 0 or 1")
    board = BoardSpec("charuco", cols, rows, square, marker, name, legacy_text in ("1", "true", "yes"))
    _check_dictionary_size(board)
    return board


def _check_dictionary_size(board: BoardSpec) -> None:
    import cv2

    needed = (board.cols * board.rows) // 2
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary))
    available = dictionary.bytesList.shape[0]
    if needed > available:
        raise CaptureError(
            f"a {board.cols}x{board.rows} ChArUco board needs {needed} markers but {board.dictionary} "
            f"has {available}; use a larger dictionary"
        )


def _int(text: str, key: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise CaptureError(f"board spec {key}={text!r} must be a whole number; expected {GRAMMAR}") from None


def _length(text: str, key: str) -> float:
    try:
        value = float(text.lower().removesuffix("mm"))
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value <= 0:
        raise CaptureError(f"board spec {key}={text!r} must be a positive length in mm; expected {GRAMMAR}")
    return value
