"""Where the shared third-party face data (ICT FaceKit, GRID clips; see README.md "Real face data") lies.

Not shipped with the package: benchmarks and some tests read it from ``$CAPTURE_SHARED_ASSETS`` when set,
else from ``../shared/assets`` beside the repository (the layout of the development machines), else from
``/work/shared/assets`` (a clone elsewhere on those machines, e.g. CI's). Tests that need it skip, saying
which path they looked at, when it is absent.
"""

from __future__ import annotations

import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def shared_assets() -> Path:
    """The shared assets folder (see the module docstring); the last candidate when none exists."""
    env = os.environ.get("CAPTURE_SHARED_ASSETS")
    if env:
        return Path(env).expanduser()
    candidates = [REPO.parent / "shared" / "assets", Path("/work/shared/assets")]
    return next((c for c in candidates if c.is_dir()), candidates[-1])


SHARED_ASSETS = shared_assets()
ICT_LIGHT_NPZ = SHARED_ASSETS / "ict_facekit" / "derived" / "ict_facekit_light.npz"
GRID_CLIPS = SHARED_ASSETS / "videos" / "grid_corpus"
