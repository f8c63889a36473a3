"""Benchmark: the streamed fit's initial head poses as the take grows (``capture run``'s fit process).

Each window of :func:`capture.fit.stream.fit_take_stream` needs its frames' initial poses: the per-frame
PnP poses interpolated over frames without one and smoothed over time. They are computed from the raw
poses around the window (``StreamLandmarkSource._pose_span``); before, from the whole take received so
far, so a window cost grew with the take and a take's cost with its square. This measures both ways on
the same synthetic pose track (head turns, 20 % of frames without a pose, a long gap), 30-frame windows
with an overlap of 6 as ``capture run``'s, and checks that they give the same poses bit for bit.

    python benchmarks/bench_stream_poses.py                      # 1,200 / 10,000 / 36,000 frames
    python benchmarks/bench_stream_poses.py --frames 1200 --quick

At lengths above ``--whole-max`` the whole-take way is timed on ``--sample`` windows spread over the take
and its total extrapolated (labelled so); the span way always runs every window.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]


def pose_track(T: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(R (T,3,3), t (T,3), ok (T,))``: a head turning about a slowly changing axis, moving, with gaps."""
    from models.quaternion import matrix_from_quat

    rng = np.random.default_rng(seed)
    angle = np.cumsum(rng.normal(0.0, 0.02, T))
    axis = np.stack([np.sin(0.01 * np.arange(T)), np.ones(T), 0.3 * np.cos(0.02 * np.arange(T))], 1)
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    R = matrix_from_quat(np.concatenate([axis * np.sin(angle / 2)[:, None], np.cos(angle / 2)[:, None]], 1))
    t = np.cumsum(rng.normal(0, 0.5, (T, 3)), 0) + [0, 0, 600]
    ok = rng.uniform(size=T) > 0.2
    ok[T // 3:T // 3 + 40] = False
    return R, t, ok


def run(T: int, window: int, overlap: int, whole_max: int, sample: int) -> dict:
    from capture.fit.init import PnPSettings, interpolate_poses, smooth_poses
    from capture.fit.stream import StreamLandmarkSource

    R, t, ok = pose_track(T)
    rows = [(np.zeros((3, 2)), np.ones(3), bool(k), (R[j], t[j]) if k else None) for j, k in enumerate(ok)]
    pnp = PnPSettings()
    src = StreamLandmarkSource(iter(rows), np.zeros((3, 3)), np.eye(3), np.zeros(5), pnp, None, None, None, "cpu",
                               n_landmarks=3)
    starts = list(range(0, T - overlap, window - overlap))
    timed_whole = set(starts) if T <= whole_max else set(starts[::max(1, len(starts) // sample)])
    span_s, whole_s, spans = 0.0, 0.0, []
    for s in starts:
        e = min(s + window, T)
        while not src._ready(e) and src._pull():
            pass
        t0 = time.perf_counter()
        got = src._poses(s, e)
        span_s += time.perf_counter() - t0
        lo, hi = src._pose_span(s, e)
        spans.append(hi - lo)
        if s in timed_whole:     # the way before: the whole take received so far
            t0 = time.perf_counter()
            Rw, tw = interpolate_poses(np.stack(src.R), np.stack(src.t), np.asarray(src.ok))
            Rw, tw = smooth_poses(Rw, tw, pnp.smooth_sigma_frames)
            whole_s += time.perf_counter() - t0
            if not (np.array_equal(got[0], Rw[s:e]) and np.array_equal(got[1], tw[s:e])):
                raise SystemExit(f"{T} frames, window {s}: the span's poses differ from the whole take's")
    whole_total = whole_s * len(starts) / len(timed_whole)
    return {"frames": T, "windows": len(starts), "span_ms_per_window": 1e3 * span_s / len(starts),
            "span_total_s": span_s, "span_frames_median": float(np.median(spans)), "span_frames_max": max(spans),
            "whole_ms_per_window": 1e3 * whole_s / len(timed_whole), "whole_total_s": whole_total,
            "whole_windows_timed": len(timed_whole), "whole_extrapolated": len(timed_whole) < len(starts)}


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", default="1200,10000,36000")
    ap.add_argument("--window", type=int, default=30)
    ap.add_argument("--overlap", type=int, default=6)
    ap.add_argument("--whole-max", type=int, default=10000, help="longer takes: the whole-take way is sampled")
    ap.add_argument("--sample", type=int, default=40, help="windows timed the whole-take way when sampled")
    ap.add_argument("--out", type=Path, default=None, help="JSON of the figures")
    ap.add_argument("--quick", action="store_true", help="check that it runs: 300 frames")
    args = ap.parse_args(argv)
    lengths = [300] if args.quick else [int(x) for x in args.frames.split(",")]
    rows = []
    print(f"{'frames':>7} {'windows':>7} | {'span: ms/window':>15} {'total s':>8} {'frames read':>11} | "
          f"{'whole take: ms/window':>21} {'total s':>8}")
    for T in lengths:
        r = run(T, args.window, args.overlap, args.whole_max, args.sample)
        rows.append(r)
        mark = " (extrapolated)" if r["whole_extrapolated"] else ""
        print(f"{T:>7} {r['windows']:>7} | {r['span_ms_per_window']:>15.2f} {r['span_total_s']:>8.2f} "
              f"{r['span_frames_median']:>6.0f} ({r['span_frames_max']}) | {r['whole_ms_per_window']:>21.2f} "
              f"{r['whole_total_s']:>8.1f}{mark}", flush=True)
    if args.out:
        from capture.io.atomic import write_text

        write_text(args.out, json.dumps(rows, indent=1))
    return rows


if __name__ == "__main__":
    main()
