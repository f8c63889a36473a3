"""Actor packages on disk: one directory per actor.

Layout (format version 1)::

    A/
      actor.json                metadata: units, shape names, model config, training settings and
                                time, per-shape training error (mm), anatomy figures, jaw transforms
      weights.safetensors       network weights and per-shape jaw transforms (no code on load)
      template.ply              template mesh C (mm); its vertices are the query points c
      bones/skull.ply, jaw.ply  the bones the constraints came from (mm), or bones/estimated.ply
      anatomy_constraints.npz   sparse skin-to-bone constraints (numpy, loaded without pickle)
      landmarks/<detector>.json landmark embeddings per detector (added by later stages)
      training/                 checkpoint and log of an unfinished training (removed when done)

``actor.json`` is written last, so a folder without it is an unfinished training. Names resolve
as DESIGN.md says: a path given as such, else ``$CAPTURE_ACTORS/A``, else ``./actors/A``.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh
from safetensors.torch import load_file, save_file

from capture.io.atomic import atomic_path, write_json
from capture.io.errors import CaptureError
from models.aim import AIMConfig, AnatomicalFaceModel
from models.anatomy_edit import edits_from_state

FORMAT_VERSION = 1
ACTOR_JSON = "actor.json"
WEIGHTS = "weights.safetensors"
TEMPLATE = "template.ply"
CONSTRAINTS = "anatomy_constraints.npz"
BONES_DIR = "bones"
TRAINING_DIR = "training"


def actors_root() -> Path:
    """Where actors named without a path live: ``$CAPTURE_ACTORS`` or ``./actors``."""
    return Path(os.environ.get("CAPTURE_ACTORS") or "actors")


def actor_dir(name: str) -> Path:
    """The directory of actor ``name`` (a path given as such, else under :func:`actors_root`)."""
    p = Path(name)
    if p.is_dir() or len(p.parts) > 1 or name.startswith("."):
        return p
    return actors_root() / name


def is_actor(path: Path) -> bool:
    return (path / ACTOR_JSON).is_file()


@dataclass
class Actor:
    """A learned actor, loaded for use (the model is frozen and in eval mode)."""

    path: Path
    metadata: dict
    config: AIMConfig
    model: AnatomicalFaceModel
    jaw_rot6d: torch.Tensor   # (N-1, 6) learned jaw transforms of the training shapes
    jaw_t: torch.Tensor       # (N-1, 3) mm
    template: trimesh.Trimesh

    @property
    def name(self) -> str:
        return self.metadata["name"]

    @property
    def shape_names(self) -> list[str]:
        return list(self.metadata["shape_names"])


def read_metadata(name: str) -> dict:
    """``actor.json`` of actor ``name``; a one-line error when the actor does not exist."""
    path = actor_dir(name)
    meta_path = path / ACTOR_JSON
    if not meta_path.is_file():
        hint = (" (its training is unfinished: rerun capture actor train to resume)"
                if (path / TRAINING_DIR).is_dir() else "")
        raise CaptureError(f"unknown actor '{name}': no {meta_path}{hint}; train it with "
                           f"'capture actor train {name} --shapes DIR' or give the actor's folder")
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise CaptureError(f"actor '{name}' has an unreadable {meta_path}: {exc}") from None
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise CaptureError(f"actor '{name}' has package format {version}; this build reads format "
                           f"{FORMAT_VERSION}: retrain the actor with this version")
    return meta


def load_actor(name: str, device: str | torch.device = "cpu") -> Actor:
    """Load actor ``name`` (see :func:`actor_dir`) with its frozen model on ``device``."""
    path = actor_dir(name)
    meta = read_metadata(name)
    config = AIMConfig.from_dict(meta["model"])
    tensors = load_file(str(path / WEIGHTS), device=str(device))
    model = AnatomicalFaceModel(config).to(device)
    state = {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}
    model.thickness_edits.extend(e.to(device) for e in edits_from_state(state))  # an edited actor's edits
    model.load_state_dict(state)
    model.eval().requires_grad_(False)
    template = trimesh.load(path / TEMPLATE, process=False, maintain_order=True, force="mesh")
    return Actor(path=path, metadata=meta, config=config, model=model, jaw_rot6d=tensors["jaw_rot6d"],
                 jaw_t=tensors["jaw_t"], template=template)


def list_actors(root: Path | None = None) -> list[dict]:
    """Metadata of every finished actor under ``root`` (default :func:`actors_root`), by name."""
    root = root or actors_root()
    if not root.is_dir():
        return []
    out = []
    for p in sorted(root.iterdir()):
        if is_actor(p):
            try:
                meta = json.loads((p / ACTOR_JSON).read_text())
            except (OSError, json.JSONDecodeError):
                meta = {"name": p.name, "error": "unreadable actor.json"}
            meta["path"] = str(p)
            out.append(meta)
        elif (p / TRAINING_DIR).is_dir():
            out.append({"name": p.name, "path": str(p), "status": "training unfinished"})
    return out


def write_mesh(path: Path, mesh: trimesh.Trimesh) -> None:
    """Write a mesh atomically in the format of its suffix."""
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=path.suffix.lstrip("."))


def save_actor(path: Path, metadata: dict, model: AnatomicalFaceModel, jaw_rot6d: torch.Tensor,
               jaw_t: torch.Tensor, template: trimesh.Trimesh, bones: dict[str, trimesh.Trimesh],
               constraints: dict[str, np.ndarray]) -> Path:
    """Write a finished actor package; ``actor.json`` goes last (it marks the package complete)."""
    path.mkdir(parents=True, exist_ok=True)
    tensors = {f"model.{k}": v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    tensors["jaw_rot6d"] = jaw_rot6d.detach().cpu().contiguous()
    tensors["jaw_t"] = jaw_t.detach().cpu().contiguous()
    with atomic_path(path / WEIGHTS) as tmp:
        save_file(tensors, str(tmp), metadata={"format_version": str(FORMAT_VERSION), "units": "mm"})
    write_mesh(path / TEMPLATE, template)
    for name, mesh in bones.items():
        write_mesh(path / BONES_DIR / f"{name}.ply", mesh)
    with atomic_path(path / CONSTRAINTS) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **constraints)
    meta = dict(metadata)
    meta["format_version"] = FORMAT_VERSION
    write_json(path / ACTOR_JSON, meta)
    return path


def remove_actor(path: Path) -> None:
    """Delete an actor folder (used by ``--overwrite``); refuses folders that are not actors."""
    if not path.exists():
        return
    if not (is_actor(path) or (path / TRAINING_DIR).is_dir()):
        raise CaptureError(f"{path} exists and is not an actor package; choose another name or remove it")
    shutil.rmtree(path)
