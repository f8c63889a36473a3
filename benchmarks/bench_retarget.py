"""Benchmark: anatomy editing and retargeting on the bundled ICT demo actor (9,409 vertices, 19 expressions).

1. ``capture demo`` (a synthetic take of the demo actor, ``capture run`` on it), or an existing demo folder.
2. ``capture actor edit``: the left cheek's soft tissue x1.5 (painted vertices within 20 mm of a cheek point).
3. ``capture retarget`` of the demo run onto the edited actor (the only second actor in correspondence the
   repository bundles), full performance, then with the jaw and soft-tissue parts; and onto the demo
   actor itself (must reproduce the run's meshes).

Prints wall times (edit; retarget per frame, against the run's fit per frame) and the displacement figures.

    python benchmarks/bench_retarget.py                  # ~2 min on 2 cores (60-frame demo)
    python benchmarks/bench_retarget.py --quick          # checks that it runs (10 frames, few iterations)
    python benchmarks/bench_retarget.py --demo DIR       # reuse a finished capture demo --out DIR
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np


def _meshes(folder: Path) -> np.ndarray:
    import trimesh

    return np.stack([trimesh.load(p, process=False, maintain_order=True).vertices
                     for p in sorted(folder.glob("frame_*.obj"))])


def _cli(args: list[str]) -> float:
    from capture.cli import main

    t = time.perf_counter()
    rc = main(args)
    if rc != 0:
        raise SystemExit(f"capture {' '.join(args)} failed with status {rc}")
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="10 frames, few fit iterations: checks that it runs")
    ap.add_argument("--demo", type=Path, help="a finished 'capture demo --out DIR' folder to reuse")
    ap.add_argument("--out", type=Path, help="working folder (default: a temporary one)")
    args = ap.parse_args()

    import torch
    import trimesh

    torch.set_num_threads(1)
    work = args.out or Path(tempfile.mkdtemp(prefix="bench_retarget_"))
    work.mkdir(parents=True, exist_ok=True)
    demo = args.demo
    if demo is None:
        from capture.demo import DemoConfig, run_demo

        demo = work / "demo"
        cfg = DemoConfig(out=demo, progress=False, **({"frames": 10, "fit_iterations": 30} if args.quick else {}))
        run_demo(cfg)
    run, actor = demo / "run", demo / "actor"
    report = json.loads((run / "report.json").read_text())
    fit_s = next(s["seconds"] for s in report["stages"] if s["stage"] == "fit")
    n = report["frames"]["requested"]

    v = np.asarray(trimesh.load(actor / "template.ply", process=False).vertices)
    tip = v[np.argmax(v[:, 2])]                                     # the nose tip faces +z
    cheek = v[np.argmin(np.linalg.norm(v - (tip + [45.0, -15.0, -30.0]), axis=1))]
    region = np.flatnonzero(np.linalg.norm(v - cheek, axis=1) < 20.0)
    (work / "cheek.json").write_text(json.dumps(region.tolist()))
    edited = work / "actors" / "demo_cheek"
    t_edit = _cli(["actor", "edit", str(actor), "--thickness-scale", "1.5", "--region", str(work / "cheek.json"),
                   "--out", str(edited), "--overwrite"])
    e = json.loads((edited / "actor.json").read_text())["edit"]

    t_full = _cli(["retarget", str(run), "--to", str(edited), "--out", str(work / "rt_full"), "--formats", "obj,npz",
                   "--no-progress", "--overwrite"])
    t_parts = _cli(["retarget", str(run), "--to", str(edited), "--out", str(work / "rt_parts"), "--formats",
                    "obj,npz", "--parts", "full,jaw,soft_tissue", "--no-progress", "--overwrite"])
    t_self = _cli(["retarget", str(run), "--to", str(actor), "--out", str(work / "rt_self"), "--formats", "obj",
                   "--no-progress", "--overwrite"])
    ref, got, same = _meshes(run / "meshes"), _meshes(work / "rt_full" / "meshes"), _meshes(work / "rt_self" / "meshes")
    move = np.linalg.norm(got - ref, axis=-1).max(0)
    f = e["figures"]
    print(f"demo run: {n} frames, fit {fit_s:.1f} s ({fit_s / n:.2f} s/frame)")
    print(f"edit: {len(region)} painted vertices, x1.5, falloff {e['falloff_mm']:g} mm, core {e['core_mm']:.2f} mm: "
          f"{t_edit:.2f} s; neutral moved up to {f['neutral_move_max_mm']:.2f} mm (region mean "
          f"{f['region']['neutral_move_mean_mm']:.2f} mm over {f['region']['vertices']} vertices; "
          f"{f['falloff']['vertices']} in the falloff; {f['outside']['vertices']} unchanged)")
    print(f"retarget onto the edit, full: {t_full:.2f} s ({t_full / n * 1000:.0f} ms/frame incl. OBJ export); "
          f"full+jaw+soft_tissue: {t_parts:.2f} s")
    print(f"retargeted meshes vs the run's: max move {move.max():.2f} mm; vertices moved > 0.01 mm: "
          f"{int((move > 0.01).sum())} (region + falloff {f['region']['vertices'] + f['falloff']['vertices']})")
    print(f"retarget onto the demo actor itself: {t_self:.2f} s; max difference to the run's meshes "
          f"{np.abs(same - ref).max():.5f} mm")
    print(f"working folder: {work}")


if __name__ == "__main__":
    main()
