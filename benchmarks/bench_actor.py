"""Benchmark: learn the bundled ICT sample actor with the project's defaults and the paper's settings.

Prints, per preset: mean and max training error per shape (mm), constraint coverage, anatomy
residuals, wall time and peak memory (each preset runs in its own process, so its peak RSS is its
own). The paper's 1e4 iterations take hours on 2 CPU cores, so by default the paper preset runs
``--paper-iterations`` steps and its full-length time is extrapolated (and labelled as such).

    python benchmarks/bench_actor.py                       # ~35 min on 2 cores
    python benchmarks/bench_actor.py --quick               # checks that it runs (CI): a few steps
    python benchmarks/bench_actor.py --paper-iterations 10000   # the paper's run in full
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def worker(actor: str, preset: str, iterations: int | None, width: int | None) -> None:
    from capture.cli import main

    args = ["actor", "train", actor, "--sample", "--preset", preset, "--overwrite", "--no-progress"]
    if iterations:
        args += ["--iterations", str(iterations)]
    if width:
        args += ["--width", str(width)]
    t = time.perf_counter()
    rc = main(args)
    wall = time.perf_counter() - t
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(json.dumps({"rc": rc, "wall_s": wall, "peak_mb": peak_mb}))


def run(preset: str, out: Path, iterations: int | None, width: int | None) -> dict:
    actor = out / f"ict_{preset}"
    cmd = [sys.executable, __file__, "--worker", str(actor), preset, str(iterations or 0), str(width or 0)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"{preset} training failed:\n{proc.stderr[-2000:]}")
    stats = json.loads(proc.stdout.strip().splitlines()[-1])
    if stats["rc"] != 0:
        sys.exit(f"{preset} training failed:\n{proc.stderr[-2000:]}")
    stats["meta"] = json.loads((actor / "actor.json").read_text())
    return stats


def report(preset: str, stats: dict, full_iterations: int | None = None) -> None:
    meta = stats["meta"]
    q, tr, con = meta["quality"], meta["training"], meta["anatomy_constraints"]
    s = tr["settings"]
    print(f"\n== preset {preset}: width {s['width']}, depth {s['depth']}, {tr['iterations']} iterations, lr {s['lr']}, "
          f"omega_0 {s['first_omega_0']}/{s['hidden_omega_0']}")
    print(f"{'shape':<18}{'mean mm':>10}{'max mm':>10}")
    for name, e in q["per_shape"].items():
        print(f"{name:<18}{e['mean_mm']:>10.4f}{e['max_mm']:>10.3f}")
    print(f"{'ALL':<18}{q['mean_mm']:>10.4f}{q['max_mm']:>10.3f}")
    a = q["anatomy"]
    print(f"constraints: {con['count']} points, coverage {100 * con['coverage']:.1f} %, thickness median "
          f"{con['thickness_mm']['median']:.1f} mm")
    print(f"anatomy residuals: bone {a['bone_mm']:.3f} mm, thickness {a['thickness_mm']:.3f} mm, normal "
          f"{a['normal_deg']:.2f} deg; symmetry {q['symmetry_mm']:.3f} mm; forehead |k| {q['forehead_k']:.4f}")
    per_it = tr["train_seconds"] / max(tr["iterations"], 1)
    print(f"time: train {tr['train_seconds']:.0f} s ({per_it * 1000:.0f} ms/iteration), prepare "
          f"{tr['prepare_seconds']:.1f} s, wall {stats['wall_s']:.0f} s; peak memory {stats['peak_mb']:.0f} MB")
    if full_iterations and full_iterations > tr["iterations"]:
        print(f"EXTRAPOLATED: {full_iterations} iterations would take about {per_it * full_iterations / 60:.0f} min "
              f"(error above is after {tr['iterations']} iterations)")


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--worker":
        _, _, actor, preset, iterations, width = sys.argv
        worker(actor, preset, int(iterations) or None, int(width) or None)
        return
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="a few steps of each preset, narrow nets (CI check)")
    ap.add_argument("--paper-iterations", type=int, default=600)
    ap.add_argument("--out", type=Path, default=None, help="where the actors go (default: a temporary folder)")
    ap.add_argument("--only", choices=["default", "paper"], default=None)
    args = ap.parse_args()
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_actor_"))
    print(f"actors in {out}")
    if args.only != "paper":
        stats = run("default", out, 20 if args.quick else None, 32 if args.quick else None)
        report("default", stats)
    if args.only != "default":
        stats = run("paper", out, 5 if args.quick else args.paper_iterations, 32 if args.quick else None)
        report("paper", stats, None if args.quick else 10_000)


if __name__ == "__main__":
    main()
