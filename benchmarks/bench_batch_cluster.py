"""``capture batch`` on a real local Ray cluster, and on a busy machine (issue 19).

Every shoot runs as a user runs it: ``python -m capture.cli batch SHOOT --out FRESH --no-progress``
(``--address`` for the cluster), from scratch, timed from the command's start to its end (Python's
and Ray's start-up included). The cluster is :class:`tests.ray_cluster.LocalCluster`: separate
GCS/raylet processes per node on 127.0.0.1, token authentication on. The shoot: ``--takes`` synthetic
takes of the tiny test actor (``tests.tiny_actor``), ``--frames`` each, 20 fit iterations, window 8,
1 thread per take.

The machine is shared with other jobs, so no "idle" time exists: the conditions compared are run
alternately (``--rounds`` times each) in one go, and ``uptime``'s load is printed with every run.

* **scaling**: the shoot through ``--address`` on 1 node x 1 CPU and on 2 nodes x 1 CPU; takes per
  minute of each and their ratio (target >= 1.6x).
* **contention**: the shoot alone and with one competing 2-thread CPU job (torch matmuls on 2 threads
  in a process of its own), in embedded mode and in cluster mode (2 nodes x 1 CPU); the ratio of the
  wall times (target <= 2.5x). ``--baseline`` adds the same pair with Ray's default worker niceness
  (``RAY_worker_niceness=15``), the behaviour before issue 19.

Usage:
    python benchmarks/bench_batch_cluster.py [--takes 4] [--frames 30] [--rounds 2] [--baseline]
    python benchmarks/bench_batch_cluster.py --only contention --modes embedded
    python benchmarks/bench_batch_cluster.py --quick     # 2 takes x 8 frames, one run of each: checks it runs
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HOG = ("import torch\ntorch.set_num_threads(2)\na = torch.randn(512, 512)\n"
       "while True:\n    a = torch.tanh(a @ a)\n")


def load() -> str:
    return " ".join(Path("/proc/loadavg").read_text().split()[:3])


def make_shoot(work: Path, takes: int, frames: int) -> Path:
    import torch

    from tests.tiny_actor import synth_tiny_take, train_tiny_actor

    torch.set_num_threads(1)
    actor = work / "actors" / "tiny"
    if not (actor / "actor.json").is_file():
        train_tiny_actor(work)
    lines = ["[defaults]", f'actor = "{actor}"', "iterations = 20", "window = 8", 'formats = ["obj", "npz"]', ""]
    for k in range(takes):
        take = work / "takes" / f"t{k}_{frames}"
        if not (take / "take.mp4").is_file():
            synth_tiny_take(actor, take, frames=frames)
        lines += ["[[take]]", f'name = "t{k}"', f'video = "{take / "take.mp4"}"',
                  f'camera = "{take / "camera.json"}"', ""]
    path = work / f"shoot_{takes}x{frames}.toml"
    path.write_text("\n".join(lines))
    return path


def run_shoot(shoot: Path, out: Path, env: dict, address: str | None = None, hog: bool = False) -> dict:
    """One ``capture batch`` from scratch; its wall time, takes per minute and what the tasks got."""
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-m", "capture.cli", "batch", str(shoot), "--out", str(out), "--no-progress"]
    if address:
        cmd += ["--address", address]
    competitor = subprocess.Popen([sys.executable, "-c", HOG], env=env) if hog else None
    before = load()
    try:
        if competitor is not None:
            time.sleep(1.0)   # the job is running before the shoot starts
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, check=False)
        wall = time.perf_counter() - t0
    finally:
        if competitor is not None:
            competitor.kill()
            competitor.wait()
    if proc.returncode != 0:
        raise RuntimeError(f"capture batch failed ({proc.returncode}): {proc.stdout[-1500:]} {proc.stderr[-1500:]}")
    report = json.loads((out / "batch_report.json").read_text())
    takes = report["takes"]
    cpu = sum(t["cpu_seconds"] or 0.0 for t in takes)
    busy = sum(t["seconds"] or 0.0 for t in takes)
    return {"wall": wall, "takes": len(takes), "per_minute": 60.0 * len(takes) / wall, "cpu": cpu,
            "cores_per_task": cpu / busy if busy else 0.0, "load_before": before, "load_after": load(),
            "nodes": (report.get("ray") or {}).get("nodes")}


def show(label: str, r: dict) -> None:
    print(f"  {label:<34} {r['wall']:6.1f} s  {r['per_minute']:5.2f} takes/min  tasks got {r['cores_per_task']:.2f} "
          f"cores while running ({r['cpu']:.0f} CPU s)  load {r['load_before']} -> {r['load_after']}", flush=True)


def base_env() -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p)
    return env


def scaling(shoot: Path, work: Path, rounds: int) -> dict:
    from tests.ray_cluster import LocalCluster

    print("scaling: 1 node x 1 CPU vs 2 nodes x 1 CPU, through --address (alternating)", flush=True)
    res: dict[int, list[dict]] = {1: [], 2: []}
    for r in range(rounds):
        for nodes in (1, 2):
            with LocalCluster(nodes=nodes, cpus=1) as c:
                res[nodes].append(run_shoot(shoot, work / f"scale_{nodes}", c.driver_env(), c.address))
            show(f"round {r + 1}, {nodes} node(s) x 1 CPU", res[nodes][-1])
    per_min = {n: sum(x["per_minute"] for x in v) / len(v) for n, v in res.items()}
    print(f"scaling: {per_min[1]:.2f} -> {per_min[2]:.2f} takes/min: {per_min[2] / per_min[1]:.2f}x "
          f"(mean of {rounds} round(s); target >= 1.6x)", flush=True)
    return {"runs": res, "ratio": per_min[2] / per_min[1]}


def contention(shoot: Path, work: Path, rounds: int, modes: list[str], baseline: bool) -> list[dict]:
    from tests.ray_cluster import LocalCluster

    out = []
    niceness = [("fixed", None)] + ([("ray default niceness 15", "15")] if baseline else [])
    for mode in modes:
        cluster = LocalCluster(nodes=2, cpus=1) if mode == "cluster" else None
        try:
            env = cluster.driver_env() if cluster else base_env()
            address = cluster.address if cluster else None
            for label, nice in niceness:
                e = dict(env) if nice is None else {**env, "RAY_worker_niceness": nice}
                print(f"contention, {mode} mode, {label}: alone vs with a 2-thread CPU job (alternating)", flush=True)
                alone, busy = [], []
                for r in range(rounds):
                    alone.append(run_shoot(shoot, work / f"cont_{mode}", e, address))
                    show(f"round {r + 1}, alone", alone[-1])
                    busy.append(run_shoot(shoot, work / f"cont_{mode}", e, address, hog=True))
                    show(f"round {r + 1}, with the competing job", busy[-1])
                a = sum(x["wall"] for x in alone) / rounds
                b = sum(x["wall"] for x in busy) / rounds
                print(f"contention, {mode} mode, {label}: {a:.1f} s alone, {b:.1f} s with the job: {b / a:.2f}x "
                      f"(target <= 2.5x)", flush=True)
                out.append({"mode": mode, "niceness": label, "alone": alone, "busy": busy, "ratio": b / a})
        finally:
            if cluster is not None:
                cluster.close()
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--takes", type=int, default=4)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--only", choices=("scaling", "contention"))
    ap.add_argument("--modes", default="embedded,cluster")
    ap.add_argument("--baseline", action="store_true")
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_batch_cluster"))
    a = ap.parse_args(argv)
    if a.quick:
        a.takes, a.frames, a.rounds, a.baseline = 2, 8, 1, False
    a.work.mkdir(parents=True, exist_ok=True)
    shoot = make_shoot(a.work, a.takes, a.frames)
    print(f"shoot: {a.takes} takes x {a.frames} frames of the tiny actor, 20 iterations, window 8, 1 thread per "
          f"take; {os.cpu_count()} cores; load {load()}", flush=True)
    res = {}
    if a.only in (None, "scaling") and not a.quick:
        res["scaling"] = scaling(shoot, a.work, a.rounds)
    if a.only in (None, "contention"):
        modes = ["cluster"] if a.quick else a.modes.split(",")
        res["contention"] = contention(shoot, a.work, a.rounds, modes, a.baseline)
    return res


if __name__ == "__main__":
    main()
