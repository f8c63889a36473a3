"""Cost of the 2D take fit as work grows: take length (100 / 1,000 / 10,000 frames) and landmark
count (100 / 1,000 / 10,000).

One synthetic take (``capture synth``, bundled demo actor, preset ``talk``, 640x360, 100 frames,
10,000 landmarks) is rendered once; the 100- and 1,000-landmark sets are farthest-point subsets of the
10,000 (on the template), and longer takes repeat the 100 frames back and forth (ping-pong, so the
motion stays continuous). True landmarks + 0.5 px noise. Every configuration runs in a fresh child
process, which streams :func:`capture.fit.take.fit_take` (no frame is kept) and reports ms per
frame, mean 3D error (mm) and its peak resident memory (``ru_maxrss``, MB).

* landmark series: 100 frames, 100 / 1,000 / 10,000 landmarks;
* length series: ``--length-landmarks`` (100) landmarks, 100 / 1,000 / 10,000 frames.

Both run the default preset CAPPED to ``--cap-iterations`` (first window) / ``--cap-warm`` (later
windows) iterations, labelled so, so that 10,000 frames and 10,000 landmarks finish in minutes: what
the series show is how time per frame and memory grow with the work, not the accuracy of a full
fit. ``--full`` runs the uncapped default preset (hours for the largest configurations on 2 shared
cores).

Usage:
    python benchmarks/bench_scale.py [--threads 1] [--full] [--quick]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the repo's packages
from benchmarks.takes import DEFAULT_ACTOR, REPO, load_take, peak_rss_mb, save_png, synth


def pingpong(n: int, period: int) -> np.ndarray:
    """Frame indices 0..period-1, period-2..1, 0.. repeated to length ``n``."""
    if period == 1:
        return np.zeros(n, np.int64)
    cyc = np.concatenate([np.arange(period), np.arange(period - 2, 0, -1)])
    return cyc[np.arange(n) % len(cyc)]


def child(cfg: dict) -> dict:
    """One configuration (run in its own process): fit, stream, measure."""
    import torch

    from capture.actor.package import load_actor
    from capture.fit.take import TakeLandmarks, WindowedFit, farthest_point_sample, fit_take
    from models.fit import FIT_PRESETS

    torch.set_num_threads(cfg["threads"])
    rss0 = peak_rss_mb()
    actor = load_actor(cfg["actor"])
    inp = load_take(Path(cfg["take"]), actor.template, 0.5, seed=0)
    lm = farthest_point_sample(inp.template_points, cfg["landmarks"]) if cfg["landmarks"] < len(
        inp.template_points) else np.arange(len(inp.template_points))
    idx = pingpong(cfg["frames"], len(inp.points2d))
    pts, w = inp.points2d[:, lm][idx], inp.weights[:, lm][idx]
    settings = FIT_PRESETS["default"]
    if cfg.get("cap"):
        settings = replace(settings, iterations=cfg["cap"][0], warm_iterations=cfg["cap"][1])
    rss_loaded = peak_rss_mb()
    tm: dict = {}
    t0 = time.perf_counter()
    err_sum, n = 0.0, 0
    for f in fit_take(actor, TakeLandmarks(pts, w, None, inp.template_points[lm]), inp.camera,
                      WindowedFit(settings, threads=cfg["threads"]), timings=tm):
        err_sum += float(np.linalg.norm(f.vertices - inp.truth[idx[f.frame]], axis=1).mean())
        n += 1
    total = time.perf_counter() - t0
    return {**cfg, "ms_per_frame": 1000 * total / n, "solve_ms_per_frame": 1000 * tm["solve_s"] / n,
            "vertices_ms_per_frame": 1000 * tm["outputs_s"] / n, "query_s": tm["query_s"], "pnp_s": tm["pnp_s"],
            "iterations": tm["iterations"], "windows": tm["windows_solved"], "mean_mm": err_sum / n,
            "peak_rss_mb": peak_rss_mb(), "rss_before_load_mb": rss0, "rss_inputs_loaded_mb": rss_loaded,
            "input_arrays_mb": (pts.nbytes + w.nbytes) / 2 ** 20, "load_average": os.getloadavg()[0]}


def run_child(cfg: dict) -> dict:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    r = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(cfg)], env=env,
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"child {cfg} failed: {r.stderr.strip()[-2000:]}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def plot(out: Path, rows: list[dict]) -> Path:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for ax, series, key in ((axes[0], "length", "frames"), (axes[1], "landmarks", "landmarks")):
        rs = [r for r in rows if r["series"] == series]
        x = [r[key] for r in rs]
        ax.plot(x, [r["ms_per_frame"] for r in rs], "o-", label="ms per frame")
        ax2 = ax.twinx()
        ax2.plot(x, [r["peak_rss_mb"] for r in rs], "s--", color="C1", label="peak RSS (MB)")
        ax.set_xscale("log")
        ax.set_xlabel(key)
        ax.set_ylabel("ms per frame")
        ax2.set_ylabel("peak RSS (MB)", color="C1")
        ax2.set_ylim(0, 1.1 * max([r["peak_rss_mb"] for r in rs], default=1))   # from 0: flat looks flat
        ax.set_ylim(0, 1.1 * max([r["ms_per_frame"] for r in rs], default=1))
        cap = rs[0].get("cap") if rs else None
        ax.set_title(f"{series} series" + (f" (capped: {cap[0]} / {cap[1]} iterations)" if cap else ""), fontsize=9)
    fig.tight_layout()
    p = save_png(fig, out / "scale.png")
    plt.close(fig)
    return p


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--actor", default=str(DEFAULT_ACTOR))
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--lengths", default="100,1000,10000")
    ap.add_argument("--landmarks", default="100,1000,10000")
    ap.add_argument("--cap-iterations", type=int, default=40)
    ap.add_argument("--cap-warm", type=int, default=2)
    ap.add_argument("--length-landmarks", type=int, default=100, help="landmarks of the length series")
    ap.add_argument("--full", action="store_true", help="both series with the uncapped default preset (slow)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results"))
    ap.add_argument("--quick", action="store_true", help="check that it runs: 6 / 12 frames, 50 landmarks")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(json.loads(args.child))))
        return {}
    from capture.io.atomic import write_text

    lengths = [int(v) for v in args.lengths.split(",")]
    counts = [int(v) for v in args.landmarks.split(",")]
    take_frames, size = 100, "640x360"
    cap = None if args.full else [args.cap_iterations, args.cap_warm]
    if args.quick:
        lengths, counts, take_frames, size, cap = [6, 12], [50], 6, "320x240", [5, 2]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        actor_copy = Path(tmp) / "actor"
        shutil.copytree(args.actor, actor_copy, ignore=shutil.ignore_patterns("training"))
        t0 = time.perf_counter()
        take = synth(actor_copy, Path(tmp) / "take", take_frames, size, "talk", 0, max(counts))
        print(f"take: {take_frames} frames {size}, {max(counts)} landmarks, rendered in "
              f"{time.perf_counter() - t0:.0f} s", flush=True)
        base = {"actor": str(actor_copy), "take": str(take), "threads": args.threads}
        configs = [{**base, "series": "landmarks", "frames": take_frames, "landmarks": n, "cap": cap}
                   for n in counts]
        configs += [{**base, "series": "length", "frames": n, "landmarks": min(args.length_landmarks, max(counts)),
                     "cap": cap}
                    for n in lengths]
        for cfg in configs:
            r = run_child(cfg)
            rows.append(r)
            lab = f"capped {r['cap'][0]}/{r['cap'][1]} iterations" if r["cap"] else "default preset"
            print(f"[{r['series']}] {r['frames']:6d} frames {r['landmarks']:6d} landmarks ({lab}): "
                  f"{r['ms_per_frame']:7.1f} ms/frame (solve {r['solve_ms_per_frame']:.1f}, vertices "
                  f"{r['vertices_ms_per_frame']:.1f}; query {r['query_s']:.1f} s, pnp {r['pnp_s']:.1f} s), "
                  f"mean {r['mean_mm']:.3f} mm, peak RSS {r['peak_rss_mb']:.0f} MB (inputs "
                  f"{r['input_arrays_mb']:.0f} MB, before fit {r['rss_inputs_loaded_mb']:.0f} MB); "
                  f"load {r['load_average']:.1f}", flush=True)
            res = {"rows": rows, "take_frames": take_frames, "size": size}
            p = out / ("scale_quick.json" if args.quick else "scale.json")
            write_text(p, json.dumps(res, indent=1))   # after every row: an interrupted run keeps what it measured
    fig = plot(out, rows)
    res["figure"] = str(fig)
    write_text(p, json.dumps(res, indent=1))
    print(f"figure: {fig}; numbers: {p}")
    return res


if __name__ == "__main__":
    main()
