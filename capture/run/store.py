"""On-disk state of a run folder: ``run.json``, fingerprints, and the stored frame fits.

``run.json`` names the take (the video's identity) and holds the resolved settings and the
fingerprints of the inputs; it is written before any work, so a folder that holds another take is
recognised and refused without ``--overwrite``. Frame fits are stored as plain arrays in chunks
(``fit/<key>/frames_<first>.npz``, listed by ``fit/<key>/done.json``) so that exports can be redone
without fitting again, and memory stays flat in the take's length.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

from capture.io.atomic import atomic_path, write_json
from capture.io.errors import CaptureError

RUN_JSON = "run.json"
RUN_FORMAT = "capture-run"
#: What a run folder may hold (removed by ``--overwrite`` when the folder holds another take).
OWNED = ("run.json", "report.json", "export.json", "landmarks.npz", "detections", "fit", "meshes",
         "params.npz", "take.usd", "take.usda", "take.usdc", "overlay.mp4")
#: Files ``capture batch`` keeps in a take's run folder (its log and state); they may be there before
#: the folder is claimed (a take that failed on its input) and are not removed by ``--overwrite``.
BATCH_FILES = ("batch_take.json", "batch_take.log")


def digest(obj: Any) -> str:
    """sha256 of the canonical JSON of ``obj`` (plain data)."""
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def file_sha256(path: Path) -> str:
    """sha256 of a file's bytes, read in 1 MiB chunks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def array_digest(*arrays: np.ndarray | None) -> str:
    h = hashlib.sha256()
    for a in arrays:
        if a is None:
            h.update(b"none")
            continue
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def read_json(path: Path) -> dict | None:
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError):
        return None


def claim_run_dir(out: Path, take_id: str, take_label: str, overwrite: bool) -> None:
    """Make sure ``out`` may hold this take: empty, new, or a run of the same take.

    A folder whose ``run.json`` names another take is refused without ``overwrite``; with it, the
    previous run's files (:data:`OWNED`) are removed. A non-empty folder that is not a run folder is
    always refused (nothing of the user's is deleted).
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise CaptureError(f"--out {out} is a file; give a folder")
    # Hidden files (such as the temporary sibling of an atomic write in progress by a concurrent task of
    # the same take) and the batch's files do not make a folder "not empty".
    if not out.exists() or not any(p.name not in BATCH_FILES and not p.name.startswith(".") for p in out.iterdir()):
        return
    prev = read_json(out / RUN_JSON)
    if prev is None or prev.get("format") != RUN_FORMAT:
        raise CaptureError(f"output folder {out} is not empty and holds no run ({RUN_JSON}); choose an empty "
                           f"or new folder with --out")
    same = prev.get("take_id") == take_id
    if same and not overwrite:
        return
    if not same and not overwrite:
        raise CaptureError(f"output folder {out} holds the run of another take ({prev.get('take_label', '?')}); "
                           f"choose another --out or pass --overwrite to replace it")
    exported = read_json(out / "export.json") or {}
    for rel in list(exported.get("files", [])) + list(exported.get("previous_files", [])):
        p = out / rel
        if p.is_file() and p.resolve().is_relative_to(out.resolve()):
            p.unlink()
    for name in OWNED:
        p = out / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()


def write_run_json(out: Path, take_id: str, take_label: str, settings: dict, fingerprints: dict,
                   status: str) -> Path:
    return write_json(Path(out) / RUN_JSON, {"format": RUN_FORMAT, "version": 1, "take_id": take_id,
                                             "take_label": take_label, "status": status, "settings": settings,
                                             "fingerprints": fingerprints})


# ------------------------------------------------------------------------------------ frame fits
def save_frame_fits(path: Path, fits: Sequence[Any]) -> Path:
    """Stack the fields of dataclass frame fits into one NPZ (None -> NaN; strings as unicode arrays)."""
    if not fits:
        raise ValueError("no frame fits to save")
    arrays: dict[str, np.ndarray] = {}
    for f in dataclasses.fields(fits[0]):
        values = [getattr(x, f.name) for x in fits]
        if all(v is None for v in values):
            continue
        if any(isinstance(v, str) for v in values):
            arrays[f.name] = np.array(["" if v is None else str(v) for v in values])
            continue
        arrs = [None if v is None else np.asarray(_to_numpy(v)) for v in values]
        ref = next(a for a in arrs if a is not None)
        if any(a is None for a in arrs):
            arrs = [np.full(ref.shape, np.nan) if a is None else a.astype(np.float64) for a in arrs]
        arrays[f.name] = np.stack(arrs)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
    return Path(path)


def _to_numpy(v):
    if hasattr(v, "detach"):
        return v.detach().cpu().numpy()
    return v


def load_frame_fits(path: Path, cls) -> list[Any]:
    """The frame fits saved by :func:`save_frame_fits`, as instances of the dataclass ``cls``."""
    with np.load(path, allow_pickle=False) as z:
        g = {k: z[k] for k in z.files}
    n = len(next(iter(g.values())))
    out = []
    for i in range(n):
        kw = {}
        for f in dataclasses.fields(cls):
            if f.name not in g:
                kw[f.name] = None
                continue
            v = g[f.name][i]
            if v.dtype.kind == "U":
                v = str(v)
            elif v.ndim == 0:
                v = v.item()
            kw[f.name] = v
        out.append(cls(**kw))
    return out


def frames_of(fits: Iterable[Any]) -> list[int]:
    return [int(f.frame) for f in fits]
