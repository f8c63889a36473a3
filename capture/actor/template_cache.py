"""The actor's networks evaluated at its template vertices, kept in a user cache.

Every take fit, rig export and report needs the five networks' outputs at every template vertex
(:meth:`capture.actor.package.Actor.at_template`): on the bundled demo actor (9,409 vertices) a forward
pass of 0.3-0.6 s on one core, and in ``capture run`` it lies on the fit's critical path, between
torch's import and the first window. The outputs depend only on the weights, the template and the
model's configuration, so the first evaluation is written to ``<cache>/at_template/<key>.safetensors``,
named by a key of those inputs, and later loads read it (a few ms). ``<cache>`` is ``$CAPTURE_CACHE``,
else ``$XDG_CACHE_HOME/capture``, else ``~/.cache/capture``; it can be deleted at any time. The actor's
package is never written (bundled actors stay as shipped). A file that cannot be read is ignored and
written again; where the cache cannot be written (read-only home), the actor is evaluated every time, as
before, and nothing fails for it.

The numbers read are the numbers that were evaluated (float32, bit for bit); on another device or
with another thread count a fresh evaluation could differ in the last bits.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from capture.io.atomic import atomic_path

if TYPE_CHECKING:
    from models.aim import Anatomy

SUBDIR = "at_template"
VERSION = 1
FIELDS = ("bone", "thickness", "normal", "neutral", "skin_weight", "expressions")


def cache_key(config: dict, template_vertices: np.ndarray, weights: dict[str, np.ndarray]) -> str:
    """SHA-256 of what the evaluation depends on: the model's configuration, the template vertices and
    every weight array (name, dtype, shape, bytes)."""
    h = hashlib.sha256(json.dumps({"version": VERSION, "config": config}, sort_keys=True).encode())
    h.update(np.ascontiguousarray(template_vertices, np.float64).tobytes())
    for name in sorted(weights):
        w = np.ascontiguousarray(weights[name])
        h.update(f"|{name}|{w.dtype.str}|{w.shape}|".encode())
        h.update(w.tobytes())
    return h.hexdigest()


def cache_root() -> Path:
    """``$CAPTURE_CACHE``, else ``$XDG_CACHE_HOME/capture``, else ``~/.cache/capture``."""
    if os.environ.get("CAPTURE_CACHE"):
        return Path(os.environ["CAPTURE_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "capture"


def cache_path(key: str) -> Path:
    return cache_root() / SUBDIR / f"{key}.safetensors"


def read(key: str, device) -> Anatomy | None:
    """The cached outputs of ``key`` on ``device``; None when there are none or they cannot be read."""
    from safetensors import SafetensorError, safe_open

    from models.aim import Anatomy

    path = cache_path(key)
    if not path.is_file():
        return None
    try:
        with safe_open(str(path), framework="pt", device=str(device)) as f:
            if (f.metadata() or {}).get("key") != key:
                return None
            parts = {k: f.get_tensor(k) if k in f.keys() else None for k in FIELDS}
    except (OSError, SafetensorError, ValueError, RuntimeError):
        return None
    return Anatomy(**parts)


def write(key: str, anatomy: Anatomy) -> bool:
    """Write ``anatomy`` under ``key`` (atomically); False when the cache cannot be written."""
    from safetensors.torch import save_file

    tensors = {k: getattr(anatomy, k).detach().cpu().contiguous() for k in FIELDS if getattr(anatomy, k) is not None}
    try:
        with atomic_path(cache_path(key)) as tmp:
            save_file(tensors, str(tmp), metadata={"key": key, "version": str(VERSION)})
    except OSError:
        return False
    return True
