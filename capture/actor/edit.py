"""``capture actor edit A --thickness-scale S --region FILE --out A2``: sculpt an actor through its anatomy.

Scales the learned soft-tissue thickness d of actor A in a painted region (paper, Sec. 5.2, "Anatomy
Manipulation") and writes a new actor A2 whose neutral and expressions follow through the model
(``s0 = b + d n``, then jaw LBS and expression offsets). The edit is a function of the template point
c (:class:`models.anatomy_edit.ThicknessEdit`), stored inside A2's ``weights.safetensors``, so A2 works
wherever an actor does (``capture run``, ``fit3d``, ``synth``, retargeting, another edit).

**Region file** (the template's vertex order):

* ``.json``: a list of vertex indices ``[12, 13, ...]``, or ``{"vertices": [...], "weights": [...]}``
  with optional mask values in (0, 1] per listed vertex (a soft painted mask);
* ``.txt`` (any other suffix): vertex indices separated by spaces, commas or newlines;
* ``.ply`` / ``.obj``: the template mesh painted with vertex colours: mask = mean(R, G, B) / 255
  (black = untouched, white = full scale); vertices with mask 0 are outside the region.

The new actor keeps A's template, bones, constraints and landmark embeddings (the template points c are
unchanged), and its ``actor.json`` says it is an edit (``edit``: source actor and its weights' sha256,
scale, region file and its sha256, falloff and core radii, displacement figures) with the history of
earlier edits in ``edits``.
"""

from __future__ import annotations

import datetime as dt
import json
import shutil
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from capture.io.errors import CaptureError

DEFAULT_FALLOFF_MM = 10.0


@dataclass
class EditOptions:
    """Settings of ``capture actor edit`` (saved resolved in the new actor's ``actor.json``)."""

    actor: str
    out: str
    thickness_scale: float
    region: Path
    falloff_mm: float = DEFAULT_FALLOFF_MM
    core_mm: float | None = None       # None: half the template's mean edge length
    overwrite: bool = False

    def to_dict(self) -> dict:
        d = asdict(self)
        d["region"] = str(self.region)
        return d


def read_region(path: Path, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """A region file (see the module docstring) -> (vertex indices (M,), mask values (M,) in (0, 1])."""
    from capture.actor.training import read_vertex_list

    path = Path(path)
    if not path.is_file():
        raise CaptureError(f"region file not found: {path}; give a vertex list (.json/.txt) or a painted mesh (.ply/.obj)")
    suffix = path.suffix.lower()
    if suffix in (".ply", ".obj"):
        mesh = trimesh.load(path, process=False, maintain_order=True, force="mesh")
        if len(mesh.vertices) != n_vertices:
            raise CaptureError(f"painted region mesh {path} has {len(mesh.vertices)} vertices but the actor's template "
                               f"has {n_vertices}; paint the actor's template.ply")
        if getattr(mesh.visual, "kind", None) != "vertex":
            raise CaptureError(f"painted region mesh {path} has no vertex colours; paint the region white on black "
                               f"and export vertex colours")
        mask = np.asarray(mesh.visual.vertex_colors, np.float64)[:, :3].mean(1) / 255.0
        idx = np.flatnonzero(mask > 0)
        values = mask[idx]
    elif suffix == ".json" and path.read_text().lstrip().startswith("{"):
        try:
            d = json.loads(path.read_text())
            idx = np.asarray(d["vertices"], np.int64).reshape(-1)
            values = np.asarray(d.get("weights", np.ones(len(idx))), np.float64).reshape(-1)
            unknown = set(d) - {"vertices", "weights"}
        except (KeyError, ValueError, TypeError, json.JSONDecodeError):
            raise CaptureError(f"region file {path} must be a JSON object {{\"vertices\": [...], \"weights\": [...]}} "
                               f"or a list of vertex indices") from None
        if unknown:
            raise CaptureError(f"region file {path} has unknown keys {sorted(unknown)}; allowed: vertices, weights")
        if len(values) != len(idx):
            raise CaptureError(f"region file {path}: {len(values)} weights for {len(idx)} vertices; give one per vertex")
        if idx.size == 0 or idx.min() < 0 or idx.max() >= n_vertices:
            raise CaptureError(f"region file {path}: vertex indices must lie in 0..{n_vertices - 1}")
        if len(np.unique(idx)) != len(idx):
            raise CaptureError(f"region file {path} lists a vertex more than once")
        if not np.all((values > 0) & (values <= 1)):
            raise CaptureError(f"region file {path}: weights must lie in (0, 1]")
    else:
        idx = read_vertex_list(path, n_vertices, "region")
        values = np.ones(len(idx))
    if idx.size == 0:
        raise CaptureError(f"region {path} selects no vertex; paint or list at least one")
    return idx, values


def _displacement_figures(before, after, region_w: np.ndarray) -> dict:
    """How far the neutral moved (mm), in the region (w = 1), the falloff (0 < w < 1) and outside."""
    move = np.linalg.norm(after.neutral.numpy() - before.neutral.numpy(), axis=1)
    dthick = after.thickness.numpy() - before.thickness.numpy()
    parts = {"region": region_w >= 1.0, "falloff": (region_w > 0) & (region_w < 1.0), "outside": region_w <= 0}
    out = {name: {"vertices": int(m.sum()), "neutral_move_max_mm": float(move[m].max()) if m.any() else 0.0,
                  "neutral_move_mean_mm": float(move[m].mean()) if m.any() else 0.0,
                  "thickness_change_mean_mm": float(dthick[m].mean()) if m.any() else 0.0}
           for name, m in parts.items()}
    out["neutral_move_max_mm"] = float(move.max())
    return out


def edit_actor(opts: EditOptions, report=print) -> Path:
    """Write the edited actor ``opts.out``; returns its folder. Nothing is written on bad input."""
    from capture.actor.package import (ACTOR_JSON, BONES_DIR, CONSTRAINTS, WEIGHTS, actor_dir, is_actor, load_actor,
                                       remove_actor, save_actor)
    from capture.run.store import file_sha256
    from models.anatomy_edit import ThicknessEdit

    t0 = time.perf_counter()
    if not (np.isfinite(opts.thickness_scale) and opts.thickness_scale > 0):
        raise CaptureError(f"--thickness-scale must be a positive number (1 = unchanged), got {opts.thickness_scale}")
    if not (np.isfinite(opts.falloff_mm) and opts.falloff_mm >= 0):
        raise CaptureError(f"--falloff must be >= 0 mm, got {opts.falloff_mm}")
    if opts.core_mm is not None and not (np.isfinite(opts.core_mm) and opts.core_mm >= 0):
        raise CaptureError(f"--core must be >= 0 mm, got {opts.core_mm}")
    src = load_actor(opts.actor)
    out = actor_dir(opts.out)
    if out.resolve() == Path(src.path).resolve():
        raise CaptureError(f"--out {opts.out} is the source actor itself; give a new actor name")
    if out.exists() and any(out.iterdir()):
        if not opts.overwrite:
            raise CaptureError(f"actor folder {out} already exists; choose another --out or pass --overwrite")
        if not is_actor(out):
            raise CaptureError(f"{out} exists and is not an actor package; choose another --out")
    template = src.template
    V = len(template.vertices)
    idx, mask = read_region(opts.region, V)
    core = 0.5 * float(template.edges_unique_length.mean()) if opts.core_mm is None else float(opts.core_mm)

    verts = torch.as_tensor(np.asarray(template.vertices), dtype=torch.float32)
    edit = ThicknessEdit(verts[idx], torch.as_tensor(mask, dtype=torch.float32), float(opts.thickness_scale),
                         float(opts.falloff_mm), core)
    with torch.no_grad():
        before = src.model(verts)
        src.model.thickness_edits.append(edit)
        after = src.model(verts)
        w = edit.weight(verts).numpy()
    figures = _displacement_figures(before, after, w)

    meta = json.loads(json.dumps(src.metadata))  # a deep copy, plain data
    entry = {"source_actor": src.name, "source_path": str(src.path),
             "source_weights_sha256": file_sha256(Path(src.path) / WEIGHTS),
             "operation": "thickness_scale", "thickness_scale": float(opts.thickness_scale),
             "region_file": str(opts.region), "region_sha256": file_sha256(Path(opts.region)),
             "region_vertices": int(len(idx)), "region_soft": bool(np.any(mask < 1)),
             "falloff_mm": float(opts.falloff_mm), "core_mm": core,
             "core_source": "half the template's mean edge length" if opts.core_mm is None else "--core",
             "formula": "d'(c) = d(c) * (1 + (S - 1) w(c)), w(c) = max_i m_i (1 - smoothstep((|c - v_i| - core) / falloff))",
             "figures": figures, "settings": opts.to_dict(),
             "created": dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")}
    meta["name"] = out.name
    meta["created"] = entry["created"]
    meta["edits"] = list(meta.get("edits", [])) + [entry]
    meta["edit"] = entry
    meta["quality"]["note"] = (f"training errors are those of the source actor '{src.name}' before the edit "
                               f"(the edited actor reproduces its shapes outside the edited region)")

    bones = {p.stem: trimesh.load(p, process=False, maintain_order=True, force="mesh")
             for p in sorted((Path(src.path) / BONES_DIR).glob("*.ply"))}
    with np.load(Path(src.path) / CONSTRAINTS, allow_pickle=False) as z:
        constraints = {k: z[k] for k in z.files}
    if out.exists() and opts.overwrite:
        remove_actor(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / ACTOR_JSON).unlink(missing_ok=True)
    landmarks = Path(src.path) / "landmarks"
    if landmarks.is_dir():  # embeddings live on the template, which the edit keeps
        shutil.copytree(landmarks, out / "landmarks", dirs_exist_ok=True)
    entry["seconds"] = time.perf_counter() - t0
    save_actor(out, meta, src.model, src.jaw_rot6d, src.jaw_t, template, bones, constraints)
    r = figures["region"]
    report(f"actor '{out.name}' written to {out}: thickness x{opts.thickness_scale:g} over {len(idx)} painted vertices "
           f"(falloff {opts.falloff_mm:g} mm, core {core:.2f} mm); neutral moved up to "
           f"{figures['neutral_move_max_mm']:.2f} mm ({r['vertices']} vertices fully scaled, "
           f"{figures['falloff']['vertices']} in the falloff, {figures['outside']['vertices']} unchanged)")
    return out


def edit_summary(meta: dict) -> str | None:
    """One line for ``capture actor show``: what this actor is an edit of, with which settings."""
    e = meta.get("edit")
    if not e:
        return None
    history = meta.get("edits", [])
    chain = " <- ".join([meta["name"]] + [x["source_actor"] for x in reversed(history)])
    return (f"EDITED from actor '{e['source_actor']}' ({e['source_path']}): thickness x{e['thickness_scale']:g} in "
            f"region {e['region_file']} ({e['region_vertices']} vertices{', soft mask' if e.get('region_soft') else ''}), "
            f"falloff {e['falloff_mm']:g} mm, core {e['core_mm']:.2f} mm; neutral moved up to "
            f"{e['figures']['neutral_move_max_mm']:.2f} mm; {e['created']}"
            + (f"; {len(history)} edits in all ({chain})" if len(history) > 1 else ""))
