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
    python benchmarks/bench_retarget.py --ict            # also: a second ICT identity (trained here, ~10 min)

``--ict`` makes a second ICT FaceKit identity (the sample identity's coefficients negated on the 100 identity
modes; the same 19 expressions: ICT is linear, so each shape is the sample's shape plus the identity
difference), learns it with estimated bones at reduced settings, retargets the demo run onto it and
compares, in the head frame, with that actor posed with the take's known parameters (truth_params.npz):
the retargeting error beside the demo actor's own fit error against its truth.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the repo's packages


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
    ap.add_argument("--ict", action="store_true", help="also retarget onto a second ICT identity (trained here)")
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
    if args.ict:
        ict_identity_check(work, demo, run, quick=args.quick)
    print(f"working folder: {work}")


def _ict_identity_b(work: Path) -> Path:
    """Shapes of a second ICT identity in the sample's topology (mm); returns the shapes folder."""
    from benchmarks.heldout import write_identity_shapes
    from capture.actor.sample import sample_shapes_dir

    return write_identity_shapes("b", sample_shapes_dir(), work / "ict_b_shapes")


def ict_identity_check(work: Path, demo: Path, run: Path, quick: bool) -> None:
    import torch

    from capture.actor.package import load_actor
    from models.rotation import matrix_to_rot6d

    shapes = _ict_identity_b(work)
    b = work / "actors" / "ict_b"
    t_train = 0.0
    if not (b / "actor.json").is_file():
        t_train = _cli(["actor", "train", str(b), "--shapes", str(shapes), "--width", "64", "--iterations",
                        "60" if quick else "600", "--points-per-step", "2000", "--no-progress"])
    t_rt = _cli(["retarget", str(run), "--to", str(b), "--out", str(work / "rt_ict"), "--formats", "obj",
                 "--mesh-frame", "head", "--no-progress", "--overwrite"])
    tp = np.load(demo / "take" / "truth_params.npz", allow_pickle=False)
    frames = json.loads((run / "report.json").read_text())["per_frame"]
    idx = [r["frame"] for r in frames]
    errs = {}
    for name, actor, folder in (("demo actor's own fit", demo / "actor", None), ("retargeted onto ICT identity 2", b,
                                                                               work / "rt_ict" / "meshes")):
        act = load_actor(str(actor))
        assert list(tp["shape_names"]) == act.shape_names[1:], "the take's expressions must be the actor's"
        v = torch.tensor(np.asarray(act.template.vertices), dtype=torch.float32)
        with torch.no_grad():
            truth = act.model.shape(act.model(v), matrix_to_rot6d(torch.tensor(tp["jaw_R"][idx], dtype=torch.float32)),
                                    torch.tensor(tp["jaw_t"][idx], dtype=torch.float32),
                                    torch.tensor(tp["coefficients"][idx], dtype=torch.float32)).numpy()
        if folder is None:  # the run's camera-frame meshes, taken to the head frame with the run's head pose
            with np.load(run / "params.npz", allow_pickle=False) as p:
                got = np.einsum("tji,tvj->tvi", p["head_R"], _meshes(run / "meshes") - p["head_t_mm"][:, None])
        else:
            got = _meshes(folder)
        diff = got - truth
        e = np.linalg.norm(diff, axis=-1).mean(1)
        e_shift = np.linalg.norm(diff - diff.mean(1, keepdims=True), axis=-1).mean(1)  # per-frame offset removed
        moving = np.linalg.norm(truth - truth.mean(0), axis=-1).max(0) > 1.0       # vertices that move > 1 mm
        e_moving = np.linalg.norm(diff[:, moving], axis=-1).mean()
        errs[name] = e
        print(f"ICT check, {name}: head-frame mean vertex error {e.mean():.3f} mm (worst frame {e.max():.3f} mm); "
              f"{e_shift.mean():.3f} mm with each frame's mean offset removed; {e_moving:.3f} mm over the "
              f"{int(moving.sum())} vertices that move more than 1 mm")
    meta = json.loads((b / "actor.json").read_text())
    print(f"ICT identity 2: trained {t_train:.0f} s (mean training error {meta['quality']['mean_mm']:.3f} mm, "
          f"estimated bones); retarget {t_rt:.1f} s for {len(idx)} frames")


if __name__ == "__main__":
    main()
