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

Bundled actors (``capture/data/<name>_actor/``, e.g. ``demo``) are first-class for reading:
:func:`resolve_actor` falls back to them when the user has no actor of that name, ``list_actors``
shows them, and a user copy (:func:`user_copy_of_bundled`, made when something is added to one)
shadows the bundled one. Writers (training, edits) use :func:`actor_dir` and never touch them.
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path
from typing import TYPE_CHECKING, NamedTuple

import numpy as np

from capture.io.atomic import atomic_path, write_json
from capture.io.errors import CaptureError
from models.aim_config import AIMConfig

if TYPE_CHECKING:
    import torch
    import trimesh

    from capture.export.rig import FaceRig
    from models.aim import AnatomicalFaceModel

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


BUNDLED_ROOT = Path(__file__).resolve().parent.parent / "data"
BUNDLED_SUFFIX = "_actor"


def bundled_actors() -> dict[str, Path]:
    """Bundled actors by name (``demo`` for ``capture/data/demo_actor``); only finished ones."""
    if not BUNDLED_ROOT.is_dir():
        return {}
    return {p.name[:-len(BUNDLED_SUFFIX)]: p for p in sorted(BUNDLED_ROOT.iterdir())
            if p.name.endswith(BUNDLED_SUFFIX) and (p / ACTOR_JSON).is_file()}


def bundled_actor(name: str) -> Path | None:
    """The bundled actor called ``name`` (``demo`` or its folder name ``demo_actor``), or None."""
    found = bundled_actors()
    key = name[:-len(BUNDLED_SUFFIX)] if name.endswith(BUNDLED_SUFFIX) else name
    return found.get(key)


def is_bundled(path: Path) -> bool:
    """Whether ``path`` is (inside) the bundled actors' folder, which is read-only."""
    try:
        return Path(path).resolve().is_relative_to(BUNDLED_ROOT)
    except OSError:
        return False


def resolve_actor(name: str) -> Path:
    """The folder of actor ``name`` for reading: :func:`actor_dir` when it holds an actor (or an
    unfinished training, or is a path), else a bundled actor of that name, else :func:`actor_dir`."""
    p = actor_dir(name)
    if p.exists() or Path(name).is_dir() or len(Path(name).parts) > 1 or name.startswith("."):
        return p
    return bundled_actor(name) or p


def user_copy_of_bundled(path: Path, name: str | None = None) -> tuple[Path, str | None]:
    """Where to add files to the actor at ``path``: itself, or for a bundled actor a copy under
    :func:`actors_root` (made now, if missing), with a one-line note saying so."""
    path = Path(path)
    if not is_bundled(path):
        return path, None
    key = name or path.name
    key = key[:-len(BUNDLED_SUFFIX)] if key.endswith(BUNDLED_SUFFIX) else key
    dest = actors_root() / key
    if is_actor(dest):
        return dest, f"actor '{key}' is bundled (read-only): using your copy {dest}, which shadows it"
    if dest.exists() and any(dest.iterdir()):
        raise CaptureError(f"actor '{key}' is bundled (read-only) and {dest} exists but holds no actor; move "
                           f"it away so that a copy of the bundled actor can be made there")
    tmp = dest.with_name(f".{dest.name}.copying")
    if tmp.exists():
        shutil.rmtree(tmp)
    shutil.copytree(path, tmp)
    meta = json.loads((tmp / ACTOR_JSON).read_text())
    meta["copied_from_bundled"] = str(path)
    (tmp / ACTOR_JSON).write_text(json.dumps(meta, indent=2))
    if dest.exists():
        dest.rmdir()
    tmp.rename(dest)
    return dest, (f"actor '{key}' is bundled (read-only): copied it to {dest}, which now shadows the bundled "
                  f"one (--actor {key} uses the copy)")


def is_actor(path: Path) -> bool:
    return (path / ACTOR_JSON).is_file()


class MeshArrays(NamedTuple):
    vertices: np.ndarray      # (V, 3) float64 mm
    faces: np.ndarray         # (F, 3) int64


class Actor:
    """A learned actor, loaded for use: its files checked, its model frozen and in eval mode.

    The parts that need torch or trimesh are made on first use: ``model``, ``jaw_rot6d`` and ``jaw_t``
    from the weights read (and checked) at load, ``template`` as a ``trimesh.Trimesh`` of
    ``template_vertices`` (V, 3) mm and ``template_faces`` (F, 3). A process that needs only the arrays,
    the metadata and the rig (``capture run``'s parent, whose fit runs in a process of its own, which
    hands the rig back with :meth:`set_face_rig`) starts without importing either.
    """

    def __init__(self, path: Path, metadata: dict, config: AIMConfig, template_vertices: np.ndarray,
                 template_faces: np.ndarray, weights: dict[str, np.ndarray], device="cpu"):
        self.path = Path(path)
        self.metadata = metadata
        self.config = config
        self.template_vertices = template_vertices
        self.template_faces = template_faces
        self.device = device
        self._weights = weights
        self._parts: dict = {}

    @property
    def name(self) -> str:
        return self.metadata["name"]

    @property
    def shape_names(self) -> list[str]:
        return list(self.metadata["shape_names"])

    @property
    def template_arrays(self) -> MeshArrays:
        """The template as arrays (``.vertices``, ``.faces``), for readers of either; no trimesh."""
        return MeshArrays(self.template_vertices, self.template_faces)

    @property
    def template(self) -> trimesh.Trimesh:
        if "template" not in self._parts:
            import trimesh

            self._parts["template"] = trimesh.Trimesh(self.template_vertices, self.template_faces, process=False)
        return self._parts["template"]

    @property
    def model(self) -> AnatomicalFaceModel:
        return self._built("model")

    @property
    def jaw_rot6d(self) -> torch.Tensor:
        """(N-1, 6) the learned jaw transforms of the training shapes."""
        return self._built("jaw_rot6d")

    @property
    def jaw_t(self) -> torch.Tensor:
        """(N-1, 3) mm."""
        return self._built("jaw_t")

    def _built(self, part: str):
        if "model" not in self._parts:
            self._build()
        return self._parts[part]

    def _build(self) -> None:
        import torch

        from models.aim import AnatomicalFaceModel
        from models.anatomy_edit import edits_from_state
        from models.input_chart import chart_from_state

        name, config = self.metadata.get("name", self.path.name), self.config
        tensors = {k: torch.from_numpy(np.array(v)) for k, v in self._weights.items()}
        try:
            model = AnatomicalFaceModel(config)
            state = {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}
            model.thickness_edits.extend(edits_from_state(state))  # an edited actor's edits
            model.chart = chart_from_state(state)                    # None for actors before the chart
            model.load_state_dict(state)
        except (RuntimeError, KeyError, ValueError, TypeError) as exc:
            first = str(exc).replace("\n", " ").replace("\t", " ")[:160]
            raise _bad(name, f"{self.path / WEIGHTS} does not match the model in actor.json (width "
                             f"{config.width}): {first}") from None
        model = model.to(self.device)
        model.eval().requires_grad_(False)
        self._parts.update(model=model, jaw_rot6d=tensors["jaw_rot6d"].to(self.device),
                           jaw_t=tensors["jaw_t"].to(self.device))

    def at_template(self):
        """The frozen model's outputs (:class:`models.aim.Anatomy`, float32, on the model's device) at every
        template vertex, evaluated once per loaded actor: the fit's output points, the rig export and the
        report all need them, and each evaluation costs a forward pass of the five networks. The first
        evaluation is kept in the user's cache (:mod:`capture.actor.template_cache`), so later loads read it."""
        cached = self._parts.get("at_template")
        if cached is None:
            import torch

            from capture.actor import template_cache

            device = torch.device(self.device)      # the model's (_build); not built for a cached read
            key = template_cache.cache_key(self.config.to_dict(), self.template_vertices, self._weights)
            cached = template_cache.read(key, device)
            if cached is None:
                pts = torch.as_tensor(self.template_vertices, dtype=torch.float32, device=device)
                with torch.no_grad():
                    cached = self.model(pts)
                template_cache.write(key, cached)
            self._parts["at_template"] = cached
        return cached

    def face_rig(self) -> FaceRig:
        """The actor as a blend-shape rig (:meth:`capture.export.rig.FaceRig.from_actor`), made once."""
        if "rig" not in self._parts:
            from capture.export.rig import FaceRig

            self._parts["rig"] = FaceRig.from_actor(self)
        return self._parts["rig"]

    def set_face_rig(self, rig: FaceRig) -> None:
        """Adopt the rig another process made of this actor (its arrays are the same numbers)."""
        self._parts["rig"] = rig


def _bad(name: str, what: str, fix: str = "retrain the actor or restore its package from a backup") -> CaptureError:
    return CaptureError(f"actor '{name}': {what}; {fix}")


def validate_metadata(meta: object, name: str, meta_path: Path) -> dict:
    """The checks every reader of ``actor.json`` relies on (an object, format, name, model, shape names)."""
    if not isinstance(meta, dict):
        raise _bad(name, f"{meta_path} holds a JSON {type(meta).__name__}, not an object")
    version = meta.get("format_version")
    if version != FORMAT_VERSION:
        raise CaptureError(f"actor '{name}' has package format {version}; this build reads format "
                           f"{FORMAT_VERSION}: retrain the actor with this version")
    if not isinstance(meta.get("model"), dict):
        raise _bad(name, f"{meta_path} lacks its model settings ('model' must be an object)")
    names = meta.get("shape_names")
    if not (isinstance(names, list) and len(names) >= 2 and all(isinstance(n, str) for n in names)):
        raise _bad(name, f"{meta_path}: shape_names must be a list of the shape names (neutral first), got "
                         f"{str(names)[:60]}")
    if not isinstance(meta.get("name", ""), str):
        raise _bad(name, f"{meta_path}: name must be a string")
    meta.setdefault("name", Path(meta_path).parent.name)
    return meta


def read_metadata(name: str) -> dict:
    """``actor.json`` of actor ``name`` (see :func:`resolve_actor`), checked (:func:`validate_metadata`); one
    line when it does not exist or cannot be used."""
    return _metadata_at(resolve_actor(name), name)


def _metadata_at(path: Path, name: str) -> dict:
    meta_path = path / ACTOR_JSON
    if not meta_path.is_file():
        hint = (" (its training is unfinished: rerun capture actor train to resume)"
                if (path / TRAINING_DIR).is_dir() else "")
        known = ", ".join(bundled_actors()) or "none"
        raise CaptureError(f"unknown actor '{name}': no {meta_path}{hint}; train it with "
                           f"'capture actor train {name} --shapes DIR', give the actor's folder, or use a bundled "
                           f"actor ({known}; see 'capture actor list')")
    try:
        meta = json.loads(meta_path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
        detail = str(exc).splitlines()[0][:120] if str(exc) else exc.__class__.__name__
        raise CaptureError(f"actor '{name}' has an unreadable {meta_path} ({detail}); retrain the actor or restore "
                           f"its package") from None
    return validate_metadata(meta, name, meta_path)


def load_actor(name: str, device: str | torch.device = "cpu") -> Actor:
    """Load actor ``name`` (see :func:`resolve_actor`, resolved once) for use on ``device``.

    Every file of the package is checked: weights present, readable, finite and with jaw transforms of
    the right shapes; a template with triangles, finite, of the model's vertex count and a face's size.
    The networks are built from the weights on first use (:class:`Actor`), where a weights file of
    another architecture than ``actor.json``'s is reported.
    """
    from safetensors.numpy import load_file

    from capture.io.meshes import check_face_size

    path = resolve_actor(name)          # resolved once: everything below reads this folder
    meta = _metadata_at(path, name)
    try:
        config = AIMConfig.from_dict(meta["model"])
    except (TypeError, ValueError) as exc:
        raise _bad(name, f"its actor.json has an invalid model ({str(exc).splitlines()[0][:100]})") from None
    wpath = path / WEIGHTS
    if not wpath.is_file():
        raise _bad(name, f"{wpath} is missing")
    try:
        tensors = load_file(str(wpath))
    except Exception as exc:  # safetensors raises its own error type for truncated or foreign files
        raise _bad(name, f"{wpath} is damaged or not a safetensors file ({str(exc).splitlines()[0][:80]})") from None
    for k in ("jaw_rot6d", "jaw_t"):
        if k not in tensors:
            raise _bad(name, f"{wpath} lacks '{k}'")
    bad = [k for k, v in tensors.items() if v.dtype.kind == "f" and not np.isfinite(v).all()]
    if bad:
        raise _bad(name, f"{wpath} holds NaN or infinite values (in {bad[0]})")
    n_exp = len(meta["shape_names"]) - 1
    if tensors["jaw_rot6d"].shape != (n_exp, 6) or tensors["jaw_t"].shape != (n_exp, 3):
        raise _bad(name, f"{wpath} has jaw transforms of shape {tuple(tensors['jaw_rot6d'].shape)} for "
                         f"{n_exp} expressions")
    tpath = path / TEMPLATE
    if not tpath.is_file():
        raise _bad(name, f"{tpath} is missing")
    vertices, faces = _read_template(tpath, name)
    if len(faces) == 0 or not np.isfinite(vertices).all():
        raise _bad(name, f"{tpath} has no triangles or non-finite vertices")
    nv = meta.get("n_vertices")
    if isinstance(nv, int) and nv != len(vertices):
        raise _bad(name, f"{tpath} has {len(vertices)} vertices but actor.json says {nv}")
    check_face_size(vertices, "mm", f"actor '{name}': its template", flag="the actor's units")
    return Actor(path, meta, config, vertices, faces, tensors, device=device)


def _read_template(tpath: Path, name: str) -> tuple[np.ndarray, np.ndarray]:
    """``(vertices (V, 3) float64, faces (F, 3) int64)`` of the template, in file order.

    A triangle PLY (what :func:`save_actor` writes) is read with plyfile, which imports in milliseconds;
    anything else (other formats, polygons) through trimesh, as it always was.
    """
    try:
        from plyfile import PlyData

        ply = PlyData.read(str(tpath), known_list_len={"face": {"vertex_indices": 3}})
        v = ply["vertex"].data
        vertices = np.stack([np.asarray(v[c], np.float64) for c in ("x", "y", "z")], 1)
        faces = np.array(ply["face"].data["vertex_indices"], np.int64)      # a copy: the file is not kept open
        if faces.ndim != 2 or faces.shape[1] != 3 or (len(faces) and (faces.min() < 0 or faces.max() >= len(vertices))):
            raise ValueError("not triangles of these vertices")
        return vertices, faces
    except Exception:  # not a plain triangle PLY (or damaged): trimesh reads it or says why not
        pass
    import trimesh

    try:
        mesh = trimesh.load(tpath, process=False, maintain_order=True, force="mesh")
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise _bad(name, f"{tpath} is not a readable mesh ({exc.__class__.__name__})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise _bad(name, f"{tpath} has no triangles or non-finite vertices")
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def list_actors(root: Path | None = None, bundled: bool = True) -> list[dict]:
    """Metadata of every finished actor under ``root`` (default :func:`actors_root`), by name, then the
    bundled actors that no user actor of the same name shadows (``"bundled": true``).

    An actor whose ``actor.json`` cannot be read is listed with ``error`` (one bad actor does not break the list).
    """
    root = root or actors_root()
    out = []
    if root.is_dir():
        for p in sorted(root.iterdir()):
            if is_actor(p):
                try:
                    meta = read_metadata(str(p))
                except CaptureError as exc:
                    meta = {"name": p.name, "error": str(exc)}
                meta["path"] = str(p)
                meta["call_name"] = p.name
                out.append(meta)
            elif (p / TRAINING_DIR).is_dir():
                out.append({"name": p.name, "path": str(p), "status": "training unfinished", "call_name": p.name})
    if bundled:
        taken = {m["call_name"] for m in out}
        for key, p in bundled_actors().items():
            if key in taken:
                continue
            try:
                meta = read_metadata(str(p))
            except CaptureError as exc:
                meta = {"name": key, "error": str(exc)}
            meta.update(path=str(p), call_name=key, bundled=True)
            meta.setdefault("name", key)
            out.append(meta)
    return out


def write_mesh(path: Path, mesh: trimesh.Trimesh) -> None:
    """Write a mesh atomically in the format of its suffix."""
    with atomic_path(path) as tmp:
        mesh.export(tmp, file_type=path.suffix.lstrip("."))


def save_actor(path: Path, metadata: dict, model: AnatomicalFaceModel, jaw_rot6d: torch.Tensor,
               jaw_t: torch.Tensor, template: trimesh.Trimesh, bones: dict[str, trimesh.Trimesh],
               constraints: dict[str, np.ndarray]) -> Path:
    """Write a finished actor package; ``actor.json`` goes last (it marks the package complete)."""
    from safetensors.torch import save_file

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
