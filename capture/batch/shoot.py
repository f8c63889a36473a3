"""Shoot files: the takes of a ``capture batch`` run, with shared defaults (TOML, read with ``tomllib``).

A shoot file has three tables; any other key is an error naming the key, the table and the keys
allowed there (a typo must not silently fall back to a default)::

    [shoot]                      # optional
    name = "day1"                # default: the file's stem
    out = "runs/day1"            # batch output folder (default: runs/<shoot name>); each take -> out/<take name>
    segment_frames = 600         # split takes longer than this into segments fitted in parallel (default 0: off)

    [defaults]                   # optional: any take setting below, shared by every take
    actor = "anna"
    camera = "calib/cam_a.json"
    iterations = 300

    [[take]]                     # one per take
    name = "t001"                # default: the video's stem; unique; names the take's output folder
    video = "footage/t001.mp4"   # required
    frames = "0:300"             # and any other take setting, overriding [defaults]

Take settings (the options of ``capture run`` of the same name): ``actor``, ``camera``,
``detector``, ``frames``, ``formats`` (a list or ``"obj,usd"``), ``preset``, ``seed``,
``iterations``, ``window``, ``device``, ``overlay`` (the overlay's layers, a list or
``"mesh,landmarks"``); a take may also set ``out`` (its own output folder).

Relative paths are resolved against the shoot file's folder (not the current folder), so a shoot
folder can be moved or shared as a whole. An actor given as a plain name (no ``/``) is
``$CAPTURE_ACTORS/<name>`` when that variable is set, else ``<shoot folder>/actors/<name>``. Without a
``detector`` the one ONNX detector in the video's folder ``detector/`` is used, as in ``capture run``.

Parsing checks the file's structure and types only: a missing video or actor is reported as that
take's failure by the batch (the other takes still run).
"""

from __future__ import annotations

import os
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from capture.io.errors import CaptureError
from capture.run.inputs import DEFAULT_FORMATS, RunConfig, parse_formats, parse_overlay

#: Take settings allowed in ``[defaults]`` and ``[[take]]``, with their TOML types.
TAKE_SETTINGS: dict[str, tuple[type, ...]] = {
    "actor": (str,), "camera": (str,), "detector": (str,), "frames": (str,), "formats": (str, list),
    "preset": (str,), "seed": (int,), "iterations": (int,), "window": (int,), "device": (str,),
    "overlay": (str, list),
}
TAKE_ONLY: dict[str, tuple[type, ...]] = {"name": (str,), "video": (str,), "out": (str,)}
SHOOT_KEYS: dict[str, tuple[type, ...]] = {"name": (str,), "out": (str,), "segment_frames": (int,)}
TOP_KEYS = ("shoot", "defaults", "take")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


@dataclass
class Take:
    """One take of a shoot, resolved: absolute paths and the ``capture run`` settings it runs with."""

    name: str
    config: RunConfig            # video, actor, camera, detector, out, frames, fit settings (absolute paths)
    settings: dict               # the take's settings as written after defaults (for reports)


@dataclass
class Shoot:
    """A parsed shoot file."""

    path: Path                   # the shoot file (absolute)
    name: str
    out: Path                    # the batch output folder (absolute)
    takes: list[Take]
    segment_frames: int = 0      # 0: every take is one task; else longer takes are split (capture.batch.segments)
    defaults: dict = field(default_factory=dict)


def _check_table(table: Any, where: str, allowed: dict[str, tuple[type, ...]]) -> dict:
    if not isinstance(table, dict):
        raise CaptureError(f"{where} must be a table; see docs/shoot_example.toml")
    for key, value in table.items():
        if key not in allowed:
            raise CaptureError(f"unknown key '{key}' in {where}; allowed: {', '.join(allowed)}")
        types = allowed[key]
        # TOML booleans are not numbers here (isinstance(True, int) is true in Python).
        if isinstance(value, bool) or not isinstance(value, types):
            want = " or ".join({str: "a string", int: "an integer", list: "a list"}[t] for t in types)
            raise CaptureError(f"'{key}' in {where} must be {want}, got {value!r}")
    return table


def _resolve_path(base: Path, value: str) -> Path:
    p = Path(os.path.expanduser(value))
    return p if p.is_absolute() else (base / p)


def _resolve_actor(base: Path, value: str) -> str:
    if "/" in value or os.sep in value or value.startswith("."):
        return str(_resolve_path(base, value))
    root = os.environ.get("CAPTURE_ACTORS")
    return str((Path(root) if root else base / "actors") / value)


def _formats(value: Any, where: str) -> tuple[str, ...]:
    if isinstance(value, list):
        if not all(isinstance(v, str) for v in value):
            raise CaptureError(f"'formats' in {where} must be a list of strings, got {value!r}")
        value = ",".join(value)
    return parse_formats(value, DEFAULT_FORMATS)


def _overlay(value: Any, where: str) -> tuple[str, ...]:
    if isinstance(value, list):
        if not all(isinstance(v, str) for v in value):
            raise CaptureError(f"'overlay' in {where} must be a list of strings, got {value!r}")
        value = ",".join(value) or "none"
    return parse_overlay(value)


def load_shoot(path: str | os.PathLike, out: str | os.PathLike | None = None) -> Shoot:
    """Read and check a shoot file; ``out`` (the command's ``--out``) replaces ``[shoot] out``.

    Raises :class:`CaptureError` (one line) on a missing or malformed file, unknown keys, wrong
    types, a take without a video, duplicate take names or two takes writing to one folder.
    """
    path = Path(path).expanduser()
    if not path.is_file():
        raise CaptureError(f"shoot file {path} does not exist; check the path")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CaptureError(f"shoot file {path} is not valid TOML: {' '.join(str(exc).split())}") from None
    path = path.resolve()
    base = path.parent
    for key in data:
        if key not in TOP_KEYS:
            hint = " (use [[take]], one per take)" if key in ("takes", "takes_") else ""
            raise CaptureError(f"unknown key '{key}' at the top of {path.name}; allowed: [shoot], [defaults], "
                               f"[[take]]{hint}")
    shoot = _check_table(data.get("shoot", {}), "[shoot]", SHOOT_KEYS)
    defaults = _check_table(data.get("defaults", {}), "[defaults]", TAKE_SETTINGS)
    raw_takes = data.get("take", [])
    if isinstance(raw_takes, dict):
        raise CaptureError(f"'take' in {path.name} is a single table; write each take as [[take]] (two brackets)")
    if not isinstance(raw_takes, list) or not raw_takes:
        raise CaptureError(f"shoot file {path.name} lists no takes; add one [[take]] table per take with its video")
    name = shoot.get("name", path.stem)
    if shoot.get("segment_frames", 0) < 0:
        raise CaptureError(f"segment_frames in [shoot] must be 0 (off) or a number of frames, got "
                           f"{shoot['segment_frames']}")
    out_dir = Path(out).expanduser().resolve() if out is not None else \
        _resolve_path(base, shoot.get("out", f"runs/{name}")).resolve()

    takes, names, outs = [], {}, {}
    for i, raw in enumerate(raw_takes, 1):
        where = f"take {i}"
        if isinstance(raw, dict) and isinstance(raw.get("name"), str):
            where = f"take {i} ('{raw['name']}')"
        t = _check_table(raw, where, {**TAKE_ONLY, **TAKE_SETTINGS})
        if "video" not in t:
            raise CaptureError(f"{where} has no 'video'; give the path of its video file")
        video = _resolve_path(base, t["video"])
        tname = t.get("name", video.stem)
        if not _NAME.match(tname):
            raise CaptureError(f"take name '{tname}' ({where}) must be letters, digits, '.', '_' or '-' (it names "
                               f"the take's output folder)")
        if tname in names:
            raise CaptureError(f"take name '{tname}' is used by takes {names[tname]} and {i}; give each take a "
                               f"unique 'name'")
        names[tname] = i
        s = {**defaults, **{k: v for k, v in t.items() if k in TAKE_SETTINGS}}
        if "actor" not in s:
            raise CaptureError(f"{where} has no actor; set 'actor' in [defaults] or in the take")
        take_out = _resolve_path(base, t["out"]).resolve() if "out" in t else out_dir / tname
        if take_out in outs:
            raise CaptureError(f"takes {outs[take_out]} and {i} both write to {take_out}; give them different "
                               f"names or 'out' folders")
        outs[take_out] = i
        window = s.get("window", 30)
        cfg = RunConfig(
            video=video, actor=_resolve_actor(base, s["actor"]),
            camera=_resolve_path(base, s["camera"]) if "camera" in s else None,
            detector=_resolve_path(base, s["detector"]) if "detector" in s else None,
            out=take_out, frames=s.get("frames"), formats=_formats(s.get("formats"), where),
            preset=s.get("preset", "default"), seed=s.get("seed", 0), iterations=s.get("iterations"),
            device=s.get("device", "cpu"), window=window, overlap=min(6, max(0, window // 5)), progress=False,
            overlay=_overlay(s.get("overlay"), where))
        takes.append(Take(tname, cfg, {"video": str(video), **s}))
    return Shoot(path=path, name=name, out=out_dir, takes=takes, segment_frames=int(shoot.get("segment_frames", 0)),
                 defaults=dict(defaults))
