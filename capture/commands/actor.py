"""``capture actor train | list | show``: learn actors and inspect them."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from capture.io.errors import CaptureError

actor_app = typer.Typer(help="Learn actors from registered blendshape meshes and inspect them.",
                        no_args_is_help=True)


def _parse_plane(spec: Optional[str]):
    if spec is None:
        return None
    try:
        values = tuple(float(v) for v in spec.split(","))
    except ValueError:
        values = ()
    if len(values) != 4:
        raise CaptureError(f"--symmetry-plane '{spec}' must be four numbers nx,ny,nz,offset_mm "
                           f"(the plane of points x with x . n = offset)")
    return values


@actor_app.command("train")
def train_command(
    actor: str = typer.Argument(..., help="Actor name (stored under $CAPTURE_ACTORS or ./actors) or a folder path."),
    shapes: Optional[Path] = typer.Option(None, "--shapes", help="Folder of registered meshes (OBJ/PLY), one topology; file stem = shape name."),
    sample: bool = typer.Option(False, "--sample", help="Train on the bundled sample actor (ICT FaceKit identity, fitted skull and jaw)."),
    neutral: Optional[str] = typer.Option(None, help="Name (file stem) of the neutral shape (default: neutral)."),
    skull: Optional[Path] = typer.Option(None, help="Skull (with maxilla) mesh fitted to the neutral, same units as the shapes unless --bone-units."),
    jaw: Optional[Path] = typer.Option(None, help="Jaw (mandible) mesh fitted to the neutral."),
    units: str = typer.Option("mm", help="Units of the shape files: mm, cm, m or in."),
    bone_units: Optional[str] = typer.Option(None, help="Units of the bone files (default: same as --units)."),
    preset: str = typer.Option("default", help="Training preset: 'default' (the project's, most accurate), 'fast' (~9 min of one core, higher error) or 'paper' (the paper's settings)."),
    iterations: Optional[int] = typer.Option(None, help="Adam iterations (default: from the preset)."),
    lr: Optional[float] = typer.Option(None, help="Adam learning rate (default: from the preset)."),
    width: Optional[int] = typer.Option(None, help="SIREN hidden width (default: from the preset; the paper uses 256)."),
    depth: Optional[int] = typer.Option(None, help="Number of SIREN sine layers (default: from the preset)."),
    points_per_step: Optional[int] = typer.Option(None, help="Template points drawn per step, 0 = all (default: from the preset; the default preset draws 4,096 in the first 85 % of the steps, then steps on every point)."),
    seed: Optional[int] = typer.Option(None, help="Random seed (default: from the preset)."),
    hidden_matmul: Optional[str] = typer.Option(None, "--hidden-matmul", help="Precision of the hidden layers' products in the first 85 % of the steps: fp32, bf16, or auto (bf16 where the CPU multiplies it in hardware: AMX, AVX-512 BF16, ARM BF16; elsewhere where it is timed 2x faster; default: from the preset). Solves, evaluations and the last steps are float32."),
    input_chart: Optional[float] = typer.Option(None, "--input-chart", help="The networks read each point this fraction of the way to the shape that parts the neutral's touching lips (jawOpen), so that the lips are apart where the networks look; 0 = at the point itself, as in the paper (default: from the preset, 0.3; paper 0)."),
    symmetry_plane: Optional[str] = typer.Option(None, help="Override the estimated symmetry plane: nx,ny,nz,offset_mm."),
    mirror: bool = typer.Option(True, "--mirror/--no-mirror", help="Also learn the other side of one-sided expressions (mouthStretch_L without mouthStretch_R: its scan reflected across the symmetry plane), so that fits can use both sides."),
    jaw_from_motion: bool = typer.Option(True, "--jaw-from-motion/--no-jaw-from-motion", help="Without --jaw: find the jaw in the shape that opens it (the points that turn with it, and the pivot its turn is about), so that the actor turns a jaw; off, such an actor opens its mouth by displacements."),
    forehead: Optional[Path] = typer.Option(None, help="File of forehead vertex indices (JSON list or integers) overriding the automatic region."),
    trusted: Optional[Path] = typer.Option(None, help="File of vertex indices where skin-to-bone constraints are trusted (default: automatic, away from open borders)."),
    device: str = typer.Option("cpu", help="Torch device, e.g. cpu or cuda."),
    threads: int = typer.Option(0, "--threads", help="CPU threads (0 = all cores; use 1 on a machine shared with other jobs)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing actor or an unfinished training with other settings."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar (off: a line a minute)."),
) -> None:
    """Learn actor A from registered blendshape meshes (neutral + expressions); resumes if interrupted."""
    from capture.actor.training import TrainOptions, TrainingProgress, train_actor

    if sample:
        from capture.actor.sample import sample_bones, sample_shapes_dir

        if shapes is not None or skull is not None or jaw is not None:
            raise CaptureError("--sample brings its own shapes and bones: drop --shapes, --skull and --jaw")
        shapes = sample_shapes_dir()
        skull, jaw = sample_bones()
        units = "mm"
    if shapes is None:
        raise CaptureError("give the registered meshes with --shapes DIR (or --sample for the bundled actor)")

    options = TrainOptions(
        actor=actor, shapes=shapes, neutral=neutral, skull=skull, jaw=jaw, units=units, bone_units=bone_units,
        preset=preset, overrides=dict(iterations=iterations, lr=lr, width=width, depth=depth,
                                      points_per_step=points_per_step, seed=seed, hidden_matmul=hidden_matmul,
                                      input_chart=input_chart),
        symmetry_plane=_parse_plane(symmetry_plane), forehead=forehead, trusted=trusted, device=device,
        overwrite=overwrite, threads=threads, mirror=mirror, jaw_from_motion=jaw_from_motion)
    console = Console(stderr=True)
    path = train_actor(options, TrainingProgress(enabled=progress), report=lambda m: console.print(m, highlight=False))
    _show(str(path), Console())


@actor_app.command("edit")
def edit_command(
    actor: str = typer.Argument(..., help="Source actor name or folder."),
    thickness_scale: float = typer.Option(..., "--thickness-scale", help="Factor on the learned soft-tissue thickness in the region (1 = unchanged, 1.3 = 30 % thicker)."),
    region: Path = typer.Option(..., "--region", help="Painted region: vertex list (.json/.txt) or the template painted with vertex colours (.ply/.obj); see README."),
    out: str = typer.Option(..., "--out", help="The new actor: a name (under $CAPTURE_ACTORS or ./actors) or a folder."),
    falloff: float = typer.Option(10.0, "--falloff", help="Width (mm) of the smooth falloff around the region; 0 = hard edge."),
    core: Optional[float] = typer.Option(None, "--core", help="Points within this distance (mm) of a painted vertex get its full weight (default: half the template's mean edge length)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing actor --out."),
) -> None:
    """Scale the learned soft-tissue thickness in a painted region: a new actor whose neutral and expressions follow."""
    from capture.actor.edit import EditOptions, edit_actor

    console = Console(stderr=True)
    path = edit_actor(EditOptions(actor=actor, out=out, thickness_scale=thickness_scale, region=region,
                                  falloff_mm=falloff, core_mm=core, overwrite=overwrite),
                      report=lambda m: console.print(m, highlight=False))
    _show(str(path), Console())


@actor_app.command("list")
def list_command() -> None:
    """List the actors under $CAPTURE_ACTORS (or ./actors) and the bundled ones (e.g. demo)."""
    from capture.actor.package import list_actors

    actors = list_actors()
    console = Console()
    if not actors:
        console.print("no actors found (train one with 'capture actor train A --shapes DIR')")
        return
    table = Table("actor", "shapes", "vertices", "mean error mm", "max error mm", "trained", "landmarks", "path")
    for a in actors:
        name = str(a.get("call_name", a.get("name", "?")))
        if a.get("bundled"):
            name += " (bundled)"
        if a.get("error"):
            table.add_row(name, "-", "-", "-", "-", "unusable: " + a["error"], "-", a["path"])
            continue
        q = a.get("quality") if isinstance(a.get("quality"), dict) else {}
        edit = a.get("edit") if isinstance(a.get("edit"), dict) else {}
        if edit:
            name += f" (edit of {edit.get('source_actor', '?')})"
        lm_dir = Path(a["path"]) / "landmarks"
        landmarks = ", ".join(sorted(p.stem for p in lm_dir.glob("*.json") if not p.name.endswith(".report.json"))) or "-"
        table.add_row(name, str(len(a["shape_names"])) if isinstance(a.get("shape_names"), list) else "-",
                      str(a.get("n_vertices", "-")), _fmt(q.get("mean_mm")), _fmt(q.get("max_mm")),
                      str(a.get("created", a.get("status", "-"))), landmarks, a["path"])
    console.print(table)


@actor_app.command("show")
def show_command(
    actor: str = typer.Argument(..., help="Actor name or folder."),
    as_json: bool = typer.Option(False, "--json", help="Print the actor's metadata as JSON."),
) -> None:
    """One actor's metadata and quality figures."""
    if as_json:
        from capture.actor.package import read_metadata

        meta = read_metadata(actor)
        meta.get("forehead", {}).pop("vertices", None)
        print(json.dumps(meta, indent=2))
        return
    _show(actor, Console())


def _fmt(v) -> str:
    return f"{v:.3f}" if isinstance(v, (int, float)) else "-"


def _show(actor, console: Console) -> None:
    from capture.actor.package import read_metadata

    try:
        _show_metadata(actor, read_metadata(str(actor)), console)
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        what = (f"lacks '{exc.args[0]}'" if isinstance(exc, KeyError)
                else f"has a malformed entry ({exc.__class__.__name__})")
        raise CaptureError(f"actor '{actor}': its actor.json {what}; retrain the actor or restore its "
                           f"package") from None


def _why_no_jaw(source: dict) -> str:
    """What ``capture actor show`` adds when an actor trained without a jaw mesh has no jaw: why, from its
    ``source.jaw_source`` record, and what to do."""
    why = (source.get("jaw_source") or {}).get("why")
    if why == "--no-jaw-from-motion":
        return ("; it was trained without a jaw mesh and with --no-jaw-from-motion: train it again without that flag "
                "to read the jaw from the shapes' motion, or give --jaw (and --skull) for an anatomical one")
    if why is None:
        return ("; it was trained without a jaw mesh before the jaw was read from the shapes' motion: train it again "
                "to read one, or give --jaw (and --skull) for an anatomical one")
    return ("; it was trained without a jaw mesh, and no shape opened a jaw that it could read, so give --jaw (and "
            "--skull) for an anatomical one")


def _show_metadata(actor, meta: dict, console: Console) -> None:
    from capture.actor.package import resolve_actor

    q, tr, con = meta["quality"], meta["training"], meta["anatomy_constraints"]
    console.print(f"[bold]{meta['name']}[/]  {meta['n_vertices']} vertices, {len(meta['shape_names'])} shapes "
                  f"(neutral '{meta['neutral']}'), units {meta['units']}, {resolve_actor(str(actor))}")
    from capture.actor.edit import edit_summary

    if edit_summary(meta):
        console.print(edit_summary(meta), highlight=False)
    mirrored = meta.get("source", {}).get("mirrored_shapes") or {}
    if mirrored:
        console.print("mirrored shapes (the other side of one-sided scans, learned from their reflection): " +
                      ", ".join(f"{n} from {m['from']}" for n, m in mirrored.items()), highlight=False)
    chart = meta.get("training", {}).get("input_chart") or {}
    if chart.get("fraction"):
        console.print(f"input chart: the networks read the template {chart['fraction']:g} of the way to {chart['shape']} "
                      f"(where {chart['tearing_pairs']} touching vertex pairs part)", highlight=False)
    table = Table("shape", "mean error mm", "max error mm", title="training error per shape")
    for name, e in q["per_shape"].items():
        table.add_row(name, f"{e['mean_mm']:.4f}", f"{e['max_mm']:.3f}")
    table.add_row("[bold]all[/]", f"[bold]{q['mean_mm']:.4f}[/]", f"[bold]{q['max_mm']:.3f}[/]")
    console.print(table)
    a = q["anatomy"]
    est = " (ESTIMATED bones)" if con.get("bones_estimated") else ""
    console.print(f"anatomy constraints{est}: {con['count']} points, coverage {100 * con['coverage']:.1f} %, "
                  f"thickness median {con['thickness_mm']['median']:.1f} mm")
    console.print(f"anatomy residuals on constrained points: bone {a['bone_mm']:.3f} mm, thickness "
                  f"{a['thickness_mm']:.3f} mm, normal {a['normal_deg']:.2f} deg")
    console.print(f"symmetry residual of B: {q['symmetry_mm']:.3f} mm; forehead skinning weight |k|: {q['forehead_k']:.4f}")
    if "jaw_vertices" in q:       # actors trained before it was recorded have no such figure
        if q["jaw_vertices"]:
            src = meta["source"].get("jaw_source") or {}
            how = (f"; read from the shapes' motion ({src['shape']} turns it {src['angle_deg']:.1f} degrees), not from a "
                   f"jaw mesh" if src.get("from") == "motion" else "")
            console.print(f"jaw: {q['jaw_vertices']} of {meta['n_vertices']} template vertices follow it (skinning "
                          f"weight > 0.5){how}", highlight=False)
        else:
            console.print("[yellow]warning:[/] no template vertex follows the jaw (skinning weight > 0.5 nowhere): this "
                          "actor opens its mouth by displacements, as a blendshape rig does, and does not turn a jaw"
                          + (_why_no_jaw(meta["source"]) if not meta["source"].get("jaw") else ""),
                          highlight=False)
    s = tr["settings"]
    console.print(f"training: preset {tr['preset']}, {tr['iterations']} iterations, width {s['width']}, depth {s['depth']}, "
                  f"lr {s['lr']}, {tr['train_seconds'] / 60:.1f} min on {tr['device']}"
                  + (f" ({tr['train_cpu_seconds'] / 60:.1f} min CPU, {tr.get('torch_threads', '?')} thread(s)"
                     + (f" of {tr['machine']['cpu']}" if (tr.get("machine") or {}).get("cpu") else "") + ")"
                     if "train_cpu_seconds" in tr else "")
                  + (", bfloat16 hidden products" if tr.get("hidden_matmul") == "bf16" else "")
                  + (f"; weights of iteration {tr['weights_of_iteration']} (the best evaluated)"
                     if tr.get("weights_of_iteration", tr["iterations"]) != tr["iterations"] else ""))
