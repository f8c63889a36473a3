"""Throughput of ``capture batch`` with 1 and 2 workers on this machine (embedded local Ray).

A shoot of a few synthetic takes (``capture synth``, preset ``talk``, one seed per take) of the
bundled demo actor (a copy: synthesis writes the detector's landmark embedding into the actor) is
run twice from scratch, with ``--workers 1`` and ``--workers 2`` (1 thread per take), each into a
fresh output folder. Printed per run: wall time (including Ray's start and the workers' imports),
frames per second over the whole shoot, the per-take times, how many cores the tasks got while they
ran (their CPU time over their wall time: on a machine shared with other jobs, 2 workers cannot
gain more than that), and the speed-up of 2 workers over 1.

Usage:
    python benchmarks/bench_batch.py [--takes 4] [--frames 40] [--size 640x360] [--iterations 300]
    python benchmarks/bench_batch.py --quick      # the tiny test actor, 2 takes of 8 frames: checks it runs
Takes are kept in ``--work`` (default /tmp/bench_batch) and reused by later runs.
"""

from __future__ import annotations

import argparse
import shutil
import time
from pathlib import Path

from capture.batch.runner import BatchConfig, run_batch
from capture.cli import main as capture_main


def make_actor(work: Path, quick: bool) -> Path:
    if quick:
        from tests.tiny_actor import train_tiny_actor

        actor = work / "actors" / "tiny"
        if not (actor / "actor.json").is_file():
            train_tiny_actor(work)
        return actor
    from capture.demo import bundled_demo_actor

    actor = work / "actors" / "demo"
    if not (actor / "actor.json").is_file():
        shutil.copytree(bundled_demo_actor(), actor)
    return actor


def make_takes(work: Path, actor: Path, n: int, frames: int, size: str, landmarks: int) -> list[Path]:
    takes = []
    for k in range(n):
        out = work / "takes" / f"{actor.name}_{size}_{frames}_{k}"
        if not (out / "take.mp4").is_file():
            assert capture_main(["synth", "--actor", str(actor), "--out", str(out), "--frames", str(frames),
                                 "--size", size, "--preset", "talk", "--seed", str(k), "--landmarks", str(landmarks),
                                 "--no-progress"]) == 0
        takes.append(out)
    return takes


def write_shoot(work: Path, actor: Path, takes: list[Path], iterations: int, window: int) -> Path:
    lines = ["[defaults]", f'actor = "{actor}"', f"iterations = {iterations}", f"window = {window}",
             'formats = ["obj", "npz"]', ""]
    for t in takes:
        lines += ["[[take]]", f'name = "{t.name}"', f'video = "{t / "take.mp4"}"', f'camera = "{t / "camera.json"}"',
                  ""]
    path = work / "shoot.toml"
    path.write_text("\n".join(lines))
    return path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--takes", type=int, default=4)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--landmarks", type=int, default=500)
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--window", type=int, default=30)
    ap.add_argument("--work", type=Path, default=Path("/tmp/bench_batch"))
    a = ap.parse_args()
    if a.quick:
        a.takes, a.frames, a.size, a.landmarks, a.iterations, a.window = 2, 8, "320x240", 200, 20, 8
    work = a.work
    work.mkdir(parents=True, exist_ok=True)
    import torch

    torch.set_num_threads(1)
    actor = make_actor(work, a.quick)
    takes = make_takes(work, actor, a.takes, a.frames, a.size, a.landmarks)
    shoot = write_shoot(work, actor, takes, a.iterations, a.window)
    print(f"shoot: {len(takes)} takes x {a.frames} frames at {a.size}, actor {actor.name}, {a.landmarks} landmarks, "
          f"{a.iterations} fit iterations, window {a.window}; 1 thread per take", flush=True)
    results = {}
    for workers in (1, 2):
        out = work / f"runs_{workers}"
        shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        report = run_batch(BatchConfig(shoot=shoot, out=out, workers=workers, threads=1, progress=False))
        wall = time.perf_counter() - t0
        frames = report["totals"]["frames_fitted"]
        assert report["totals"]["done"] == len(takes), report["totals"]
        per_take = [r["seconds"] for r in report["takes"]]
        cpu = sum(r["cpu_seconds"] for r in report["takes"])
        results[workers] = frames / wall
        print(f"workers {workers}: {frames} frames in {wall:.1f} s wall -> {frames / wall:.3f} frames/s "
              f"(per take {', '.join(f'{s:.1f}' for s in per_take)} s; the tasks used {cpu:.0f} CPU s: "
              f"{cpu / sum(per_take):.2f} cores per task while running, {cpu / wall:.2f} cores over the wall time)",
              flush=True)
    print(f"speed-up 2 workers / 1 worker: {results[2] / results[1]:.2f}x "
          f"({results[1]:.3f} -> {results[2]:.3f} frames/s)")


if __name__ == "__main__":
    main()
