"""The bundled sample actor (``capture/data/sample_actor``), made by ``scripts/make_sample_actor.py``.

Neutral + 19 expression meshes of one ICT FaceKit identity (face region, 9,409 vertices, binary
PLY, millimetres), a fitted skull and jaw, and ``sample.json`` with shape names, held-out
expressions, landmark vertex ids, provenance and the bone fit report.
"""

from __future__ import annotations

import json
from importlib import resources
from pathlib import Path

from capture.io.errors import CaptureError

_REGENERATE = "regenerate it with: python scripts/make_sample_actor.py"


def sample_actor_dir() -> Path:
    """The bundled sample actor folder inside the installed ``capture`` package."""
    try:
        root = Path(str(resources.files("capture"))) / "data" / "sample_actor"
    except (ModuleNotFoundError, TypeError):  # pragma: no cover - unusual loaders
        root = Path(__file__).resolve().parents[1] / "data" / "sample_actor"
    if not (root / "sample.json").is_file():
        raise CaptureError(f"bundled sample actor not found at {root}; {_REGENERATE}")
    return root


def sample_shapes_dir() -> Path:
    """Folder of the sample's training meshes (``neutral.ply`` and one PLY per expression)."""
    shapes = sample_actor_dir() / "shapes"
    if not (shapes / "neutral.ply").is_file():
        raise CaptureError(f"sample actor shapes missing in {shapes}; {_REGENERATE}")
    return shapes


def sample_bones() -> tuple[Path, Path]:
    """Paths of the sample's fitted skull and jaw meshes (PLY, mm, same frame as the shapes)."""
    bones = sample_actor_dir() / "bones"
    skull, jaw = bones / "skull.ply", bones / "jaw.ply"
    for p in (skull, jaw):
        if not p.is_file():
            raise CaptureError(f"sample actor bone mesh missing: {p}; {_REGENERATE}")
    return skull, jaw


def load_sample_info() -> dict:
    """Contents of ``sample.json`` (shape names, held-out expressions, landmarks, fit report)."""
    path = sample_actor_dir() / "sample.json"
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, json.JSONDecodeError) as exc:
        raise CaptureError(f"cannot read {path}: {exc}; {_REGENERATE}") from None
