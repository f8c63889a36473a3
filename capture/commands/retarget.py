"""``capture retarget RUN_DIR --to B``: the options of a retarget; the work is :func:`capture.retarget.retarget_run`."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer



def _split(text: str | None) -> tuple[str, ...] | None:
    return None if text is None or not text.strip() else tuple(t.strip() for t in text.split(",") if t.strip())


def retarget_command(
    run_dir: Path = typer.Argument(..., help="Folder of a finished 'capture run' or 'capture fit3d' of actor A."),
    to: str = typer.Option(..., "--to", help="Target actor B (name or folder), learned from blendshapes in "
                           "correspondence with A's (same topology and expression names)."),
    out: Optional[Path] = typer.Option(None, "--out", help="Output folder (default ./runs/<run name>_on_<B>)."),
    formats: Optional[str] = typer.Option(None, "--formats", help="Exports: comma-separated obj, ply, usd, npz, "
                                          "overlay (default: the source run's)."),
    parts: str = typer.Option("full", "--parts", help="Comma-separated: full (B's performance), jaw (the rigid jaw "
                              "motion only, in OUT/jaw/), soft_tissue (non-rigid, jaw at rest, in OUT/soft_tissue/)."),
    mesh_frame: str = typer.Option("camera", "--mesh-frame", help="OBJ/PLY vertices in the camera frame (as the "
                                   "video saw them) or the head frame (head motion removed)."),
    source_actor: Optional[str] = typer.Option(None, "--source-actor", help="Actor A, if it moved since the run "
                                               "(default: the one named in RUN_DIR/run.json)."),
    threads: int = typer.Option(1, "--threads", help="CPU threads (1 is safest on a shared machine)."),
    device: str = typer.Option("cpu", "--device", help="Torch device (cpu, cuda)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace another run in --out."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars."),
) -> None:
    """Play a run of actor A on actor B: the same head and jaw motion and expression coefficients."""
    from rich.console import Console

    from capture.retarget import RetargetConfig, retarget_run

    cfg = RetargetConfig(run_dir=run_dir, to=to, out=out, source_actor=source_actor, formats=_split(formats),
                         parts=_split(parts) or (), mesh_frame=mesh_frame, device=device, threads=threads,
                         overwrite=overwrite, progress=progress)
    report = retarget_run(cfg)
    c = Console()
    a, b = report["actors"]["source"]["name"], report["actors"]["target"]["name"]
    c.print(f"retargeted {report['frames']['count']} frames of {report['source_run']['take']} from actor '{a}' onto "
            f"'{b}' in {report['seconds_total']:.1f} s", highlight=False)
    for part, v in report["parts"].items():
        c.print(f"  {part}: {v['dir']} ({v['meshes']} meshes, {v['files']} files)", highlight=False)
    c.print(f"  report: {Path(report['out_dir']) / 'report.json'}", highlight=False)
