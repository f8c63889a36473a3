"""``capture actor embed A --detector X.onnx ...``: the work is :func:`capture.detector.embed_actor.run_embed`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def embed_command(
    actor: str = typer.Argument(..., help="Actor name or folder (a bundled actor gets a user copy)."),
    detector: Path = typer.Option(..., "--detector", help="The landmark detector FILE.onnx (with FILE.json)."),
    vertices: Optional[Path] = typer.Option(None, "--vertices", help="One template vertex id per landmark "
                                            "(JSON list, .npy or text)."),
    triangles: Optional[Path] = typer.Option(None, "--triangles", help="Triangle id + barycentrics per landmark "
                                             "(JSON {face_index, barycentric} or rows 't b0 b1 b2')."),
    topology: Optional[Path] = typer.Option(None, "--topology", help="With --triangles: the mesh (OBJ/PLY, the "
                                            "template's vertices) whose triangles they index; default the template."),
    points: Optional[Path] = typer.Option(None, "--points", help="One 3D point per landmark near the template "
                                          "(template frame; JSON, .npy or text rows x y z)."),
    mesh: Optional[Path] = typer.Option(None, "--mesh", help="The detector's canonical mesh (OBJ/PLY), vertex l = "
                                        "landmark l; aligned by a similarity, then moved to the surface."),
    pairs: Optional[Path] = typer.Option(None, "--pairs", help="With --mesh: rows 'landmark_id template_vertex_id' "
                                         "(3 or more) for the alignment; default automatic (ICP)."),
    units: str = typer.Option("mm", "--units", help="Units of --points / --mesh: mm, cm, m or in."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing embedding for this detector."),
    refine: Optional[Path] = typer.Option(None, "--refine", help="A take of the actor: refine the embedding on a "
                                          "few well-spread frames (alone: refine the existing embedding)."),
    camera: Optional[Path] = typer.Option(None, "--camera", help="With --refine: the take's camera file "
                                          "(default: the documented guess)."),
    refine_frames: int = typer.Option(8, "--refine-frames", help="With --refine: how many frames."),
) -> None:
    """Write A/landmarks/<detector>.json: where each landmark of the detector sits on A's template."""
    from rich.console import Console

    from capture.detector.embed_actor import EmbedConfig, report_lines, run_embed

    console = Console(soft_wrap=True)
    out, report = run_embed(EmbedConfig(actor=actor, detector=detector, vertices=vertices, triangles=triangles,
                                        topology=topology, points=points, mesh=mesh, pairs=pairs, units=units,
                                        overwrite=overwrite, refine=refine, camera=camera,
                                        refine_frames=refine_frames), say=lambda m: console.print(m, highlight=False))
    for line in report_lines(report):
        console.print(line, highlight=False)
    console.print(f"wrote {out}", highlight=False)
