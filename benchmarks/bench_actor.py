"""Benchmark: learn the bundled ICT sample actor with the project's defaults and the paper's settings.

Prints, per run: mean and max training error per shape (mm), constraint coverage, anatomy
residuals, training wall time AND process CPU time (the machine is often shared: CPU seconds of a
1-thread run are what one idle core would take), the load average, time per step and peak memory
(each run is its own process, so its peak RSS is its own).

Actors (``--actors``, comma separated):
  fitted      the sample's shapes with its fitted skull and jaw (``capture actor train A --sample``)
  estimated   the same shapes without bones (estimated bone surface)
  sub1        the fitted actor with every mesh subdivided once (~37k vertices; the paper's scale)

The paper's 1e4 iterations take hours on 2 CPU cores, so by default the paper preset runs
``--paper-iterations`` steps and its full-length time is extrapolated (and labelled as such).

    python benchmarks/bench_actor.py                              # fast preset, fitted, + paper 600 steps
    python benchmarks/bench_actor.py --actors fitted,estimated,sub1 --presets fast
    python benchmarks/bench_actor.py --presets default            # the accurate default (~55 min CPU)
    python benchmarks/bench_actor.py --quick                      # checks that it runs (CI): a few steps
    python benchmarks/bench_actor.py --presets default --outofspan 0,1,2,3,4,5

``--outofspan SEEDS``: a lower training error is a better actor only if it is no worse where its training
stops. Each trained actor of the sample's topology (fitted, estimated) is then fitted out of span as
``benchmarks/bench_outofspan.py --seeds SEEDS --configs 1000:0.5 --no-bound`` measures it (held-out ICT
expressions, 2D, the default fit), side by side on the same landmarks with the bundled demo actor and the
plain blendshape baseline GBS19; the means over all sequences are printed and kept in the JSON.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ACTORS = ("fitted", "estimated", "sub1")
DEMO_ACTOR = Path(__file__).resolve().parents[1] / "capture" / "data" / "demo_actor"


def subdivided_sample(out: Path, times: int = 1) -> Path:
    """The sample's shapes with each mesh subdivided ``times`` times (midpoint subdivision: the new
    vertices depend on the triangle list only, so every shape stays in correspondence)."""
    import numpy as np
    import trimesh

    from capture.actor.sample import sample_shapes_dir
    from capture.io.meshes import load_shape_dir

    shapes = load_shape_dir(sample_shapes_dir())
    out.mkdir(parents=True, exist_ok=True)
    for name, v in zip(shapes.names, shapes.vertices):
        f = shapes.faces
        for _ in range(times):
            v, f_new = trimesh.remesh.subdivide(v, f)
        trimesh.Trimesh(np.asarray(v), f_new if times else f, process=False).export(out / f"{name}.ply")
    return out


def worker(actor: str, preset: str, kind: str, iterations: int, width: int, threads: int, hidden_matmul: str) -> None:
    import torch

    from capture.cli import main

    args = ["actor", "train", actor, "--preset", preset, "--overwrite", "--no-progress", "--threads", str(threads)]
    if hidden_matmul:
        args += ["--hidden-matmul", hidden_matmul]
    if kind == "estimated":
        from capture.actor.sample import sample_shapes_dir

        args += ["--shapes", str(sample_shapes_dir())]
    elif kind.startswith("sub"):
        from capture.actor.sample import sample_bones

        skull, jaw = sample_bones()
        shapes = subdivided_sample(Path(actor).parent / f"shapes_{kind}", int(kind[3:]))
        args += ["--shapes", str(shapes), "--skull", str(skull), "--jaw", str(jaw)]
    else:
        args += ["--sample"]
    if iterations:
        args += ["--iterations", str(iterations)]
    if width:
        args += ["--width", str(width)]
    load0 = os.getloadavg()
    t, cpu = time.perf_counter(), time.process_time()
    rc = main(args)
    wall, cpu = time.perf_counter() - t, time.process_time() - cpu
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"rc": rc, "wall_s": wall, "cpu_s": cpu, "peak_mb": peak_mb, "threads": threads or torch.get_num_threads(),
                      "load_before": load0, "load_after": os.getloadavg()}))


def run(preset: str, kind: str, out: Path, iterations: int | None, width: int | None, threads: int,
        hidden_matmul: str = "") -> dict:
    actor = out / f"{kind}_{preset}{'_' + hidden_matmul if hidden_matmul else ''}"
    cmd = [sys.executable, __file__, "--worker", str(actor), preset, kind, str(iterations or 0), str(width or 0),
           str(threads), hidden_matmul]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"{preset} training failed:\n{proc.stderr[-2000:]}")
    stats = json.loads(proc.stdout.strip().splitlines()[-1])
    if stats["rc"] != 0:
        sys.exit(f"{preset} training failed:\n{proc.stderr[-2000:]}")
    stats["meta"] = json.loads((actor / "actor.json").read_text())
    stats["actor"] = str(actor)
    return stats


def report(preset: str, kind: str, stats: dict, full_iterations: int | None = None) -> None:
    meta = stats["meta"]
    q, tr, con = meta["quality"], meta["training"], meta["anatomy_constraints"]
    s = tr["settings"]
    print(f"\n== {kind} actor ({meta['n_vertices']} vertices), preset {preset}: width {s['width']}, depth {s['depth']}, "
          f"{tr['iterations']} iterations, lr {s['lr']}, omega_0 {s['first_omega_0']}/{s['hidden_omega_0']}, "
          f"points per step {s['points_per_step'] or 'all'}, hidden products {tr.get('hidden_matmul', 'fp32')}"
          f" (setting {s.get('hidden_matmul', 'fp32')})")
    print(f"{'shape':<18}{'mean mm':>10}{'max mm':>10}")
    for name, e in q["per_shape"].items():
        print(f"{name:<18}{e['mean_mm']:>10.4f}{e['max_mm']:>10.3f}")
    print(f"{'ALL':<18}{q['mean_mm']:>10.4f}{q['max_mm']:>10.3f}")
    worst = max(q["per_shape"].items(), key=lambda kv: kv[1]["mean_mm"])
    print(f"targets: mean {q['mean_mm']:.4f} <= 0.05 mm {'OK' if q['mean_mm'] <= 0.05 else 'MISSED'}; worst shape "
          f"{worst[0]} {worst[1]['mean_mm']:.4f} <= 0.08 mm {'OK' if worst[1]['mean_mm'] <= 0.08 else 'MISSED'}; "
          f"worst vertex {q['max_mm']:.2f} <= 2 mm {'OK' if q['max_mm'] <= 2 else 'MISSED'}")
    a = q["anatomy"]
    print(f"constraints: {con['count']} points, coverage {100 * con['coverage']:.1f} %, thickness median "
          f"{con['thickness_mm']['median']:.1f} mm{' (ESTIMATED bones)' if con.get('bones_estimated') else ''}")
    print(f"anatomy residuals: bone {a['bone_mm']:.3f} mm, thickness {a['thickness_mm']:.3f} mm, normal "
          f"{a['normal_deg']:.2f} deg; symmetry {q['symmetry_mm']:.3f} mm; forehead |k| {q['forehead_k']:.4f}")
    per_it = tr["train_seconds"] / max(tr["iterations"], 1)
    cpu = tr.get("train_cpu_seconds", float("nan"))
    print(f"time: train {tr['train_seconds']:.0f} s wall, {cpu:.0f} s CPU ({1000 * cpu / max(tr['iterations'], 1):.0f} "
          f"ms CPU/iteration) with {stats['threads']} thread(s); prepare {tr['prepare_seconds']:.1f} s; process "
          f"wall {stats['wall_s']:.0f} s, CPU {stats['cpu_s']:.0f} s; load average {stats['load_before'][0]:.1f} -> "
          f"{stats['load_after'][0]:.1f}; peak memory {stats['peak_mb']:.0f} MB; CPU "
          f"{tr.get('machine', {}).get('cpu')}")
    if full_iterations and full_iterations > tr["iterations"]:
        print(f"EXTRAPOLATED: {full_iterations} iterations would take about {per_it * full_iterations / 60:.0f} min wall "
              f"at this load, {cpu / max(tr['iterations'], 1) * full_iterations / 60:.0f} min CPU "
              f"(error above is after {tr['iterations']} iterations)")


def out_of_span(actor: Path, seeds: str, out: Path, quick: bool = False) -> dict:
    """``bench_outofspan.py --seeds SEEDS`` for ``actor`` beside the bundled demo actor (its own process: it
    fixes the thread count before torch loads): per method its mean and median mm over all sequences, the
    sequence count and the per-seed means; the trained actor as ``"trained"``, the demo as ``"demo"``."""
    folder = out / f"outofspan_{actor.name}"
    cmd = [sys.executable, str(Path(__file__).with_name("bench_outofspan.py")), "--actor", str(actor),
           "--compare-actor", str(DEMO_ACTOR), "--seeds", seeds, "--configs", "1000:0.5", "--no-bound",
           "--out", str(folder)] + (["--quick"] if quick else [])
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"out-of-span fits of {actor} failed:\n{proc.stderr[-2000:]}")
    seed_list = [s.strip() for s in seeds.split(",")]
    summary = json.loads((folder / f"outofspan_seeds{seed_list[0]}-{seed_list[-1]}.json").read_text())["summary"]
    names = {"AIM default": "trained", f"AIM default [{DEMO_ACTOR.name}]": "demo"}
    return {names.get(r["method"], r["method"]): {"mean_mm": r["mean_mm"], "median_mm": r["median_mm"],
                                                  "sequences": r["sequences"], "per_seed_mean_mm": r["per_seed_mean_mm"]}
            for r in summary}


def report_out_of_span(kind: str, preset: str, figures: dict) -> None:
    t, d, g = figures["trained"], figures["demo"], figures["GBS19 [0,1]"]
    print(f"out of span ({t['sequences']} sequences, 1000 landmarks, 0.5 px): {kind}/{preset} {t['mean_mm']:.3f} mm "
          f"(median {t['median_mm']:.3f}), bundled demo actor {d['mean_mm']:.3f} (median {d['median_mm']:.3f}), "
          f"GBS19 {g['mean_mm']:.3f}; trained / demo {t['mean_mm'] / d['mean_mm']:.3f}, trained / GBS19 "
          f"{t['mean_mm'] / g['mean_mm']:.2f}; per seed trained / demo: "
          + ", ".join(f"{t['per_seed_mean_mm'][k]:.3f} / {d['per_seed_mean_mm'][k]:.3f}" for k in t["per_seed_mean_mm"]))


def main(argv: list[str] | None = None) -> dict:
    """Run the benchmark; returns ``{"out": folder, "runs": [{"preset", "kind", stats + actor metadata}]}``."""
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "--worker":
        _, actor, preset, kind, iterations, width, threads, hidden_matmul = argv
        worker(actor, preset, kind, int(iterations), int(width), int(threads), hidden_matmul)
        return {}
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a few steps of each preset, narrow nets (CI check)")
    ap.add_argument("--actors", default="fitted", help=f"comma-separated, of {', '.join(ACTORS)}")
    ap.add_argument("--paper-iterations", type=int, default=600)
    ap.add_argument("--iterations", type=int, default=None, help="override the iterations of the default/fast presets")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per run (0 = torch's default)")
    ap.add_argument("--out", type=Path, default=None, help="where the actors go (default: a temporary folder)")
    ap.add_argument("--presets", default="fast,paper", help="comma-separated, of fast, default, paper")
    ap.add_argument("--hidden-matmul", default="", help="comma-separated precisions of the hidden products to run "
                    "side by side (fp32, bf16, auto; default: the preset's)")
    ap.add_argument("--outofspan", default="", metavar="SEEDS",
                    help="also fit each trained actor out of span on these seeds (e.g. 0,1,2,3,4,5), beside the "
                         "bundled demo actor and GBS19")
    args = ap.parse_args(argv)
    kinds = [k.strip() for k in args.actors.split(",") if k.strip()]
    bad = [k for k in kinds if k not in ACTORS]
    if bad:
        sys.exit(f"unknown actor(s) {bad}: use {', '.join(ACTORS)}")
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_actor_"))
    print(f"actors in {out}")
    runs = []
    precisions = [p.strip() for p in args.hidden_matmul.split(",") if p.strip()] or [""]
    for kind in kinds:
        for preset in [p.strip() for p in args.presets.split(",") if p.strip()]:
            if preset == "paper":
                iters, full = (5 if args.quick else args.paper_iterations), (None if args.quick else 10_000)
            else:
                iters, full = (20 if args.quick else args.iterations), None
            for hidden_matmul in precisions:
                stats = run(preset, kind, out, iters, 32 if args.quick else None, args.threads, hidden_matmul)
                report(preset, kind, stats, full)
                if args.outofspan and kind != "sub1":       # the held-out performance is in the sample's topology
                    stats["outofspan"] = out_of_span(Path(stats["actor"]), args.outofspan, out, args.quick)
                    report_out_of_span(kind, preset, stats["outofspan"])
                runs.append({"preset": preset, "kind": kind, "hidden_matmul": hidden_matmul, **stats})
    return {"out": str(out), "runs": runs}


if __name__ == "__main__":
    main()
