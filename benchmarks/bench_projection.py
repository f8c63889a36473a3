"""Throughput of calib.projection.project_points, forward and forward+backward, on the CPU.

The fit projects a window of frames x landmarks every iteration; this prints how long one such
call takes and the points per second, for a few sizes and dtypes. Run:

    /work/venv/bin/python benchmarks/bench_projection.py [--frames 30] [--points 1000] [--threads 2]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from calib.projection import project_points  # noqa: E402


def bench(frames: int, points: int, dtype: torch.dtype, n_dist: int, per_frame_K: bool, repeats: int = 200):
    g = torch.Generator().manual_seed(0)
    pts = torch.randn(frames, points, 3, generator=g, dtype=dtype) * 80
    pts[..., 2] = pts[..., 2].abs() + 600
    K = torch.tensor([[1500.0, 0, 959.5], [0, 1500.0, 539.5], [0, 0, 1]], dtype=dtype)
    if per_frame_K:
        K = K.expand(frames, 3, 3).clone()
    dist = torch.tensor([-0.1, 0.05, 1e-3, -1e-3, 0.01, 0.0, 0.0, 0.0][:n_dist], dtype=dtype) if n_dist else None
    pts.requires_grad_(True)

    def forward():
        with torch.no_grad():
            project_points(pts, K, dist)

    def forward_backward():
        uv = project_points(pts, K, dist)
        uv.square().sum().backward()
        pts.grad = None

    out = {}
    for name, fn in (("forward", forward), ("fwd+bwd", forward_backward)):
        for _ in range(10):
            fn()
        best = float("inf")  # best of 5 batches: robust to other processes on a shared machine
        for _ in range(5):
            t0 = time.perf_counter()
            for _ in range(repeats // 5):
                fn()
            best = min(best, (time.perf_counter() - t0) / (repeats // 5))
        out[name] = best
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--points", type=int, default=1000)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    n = args.frames * args.points
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, {args.frames} frames x {args.points} points")
    print(f"{'dtype':8} {'dist':>4} {'K':>9} {'forward ms':>11} {'fwd+bwd ms':>11} {'Mpts/s fwd+bwd':>15}")
    for dtype in (torch.float32, torch.float64):
        for n_dist, per_frame in ((0, False), (5, False), (5, True), (8, False)):
            r = bench(args.frames, args.points, dtype, n_dist, per_frame)
            print(f"{str(dtype).split('.')[-1]:8} {n_dist:>4} {'per-frame' if per_frame else 'shared':>9} "
                  f"{r['forward'] * 1e3:11.3f} {r['fwd+bwd'] * 1e3:11.3f} {n / r['fwd+bwd'] / 1e6:15.2f}")


if __name__ == "__main__":
    main()
