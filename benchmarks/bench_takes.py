"""2D take fit on several synthetic takes, and the paper's preset side by side with the default.

Takes (``capture synth`` with the bundled demo actor, 1280x720, 100 frames each by default) differ in
seed, motion preset, landmark density (100 / 300 / 1,000) and landmark noise (0.5 / 1.5 px Gaussian
on the true landmarks); one is rendered with lens distortion. Each is fitted with
:func:`capture.fit.take.fit_take` (the fit behind ``capture run``):

* default preset on the whole take: mean / p95 3D vertex error (mm), reprojection RMS (px), jitter
  (RMS of the high-passed vertex trajectories, fit and truth, and their difference), ms per frame
  of each stage (query, pnp, solve, vertices), peak memory;
* paper preset on the first ``--paper-frames`` frames of the same take (one window; with
  ``--paper-iterations`` below 1e4 its solve time is extrapolated linearly to 1e4 and labelled so),
  against the default preset's figures on the same frames: time ratio and error ratio.

Figures (PNG) and a JSON go to ``--out`` (default ``benchmarks/results``).

Usage:
    python benchmarks/bench_takes.py [--frames 100] [--paper-iterations 2000] [--threads 1] [--quick]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse
import json
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import sys  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the repo's packages
from benchmarks.takes import (DEFAULT_ACTOR, REPO, accuracy, front_heatmap, load_take, peak_rss_mb, save_png,
                              stage_ms, synth)

# name, motion preset, seed, landmarks, noise px, distortion (k1,k2,p1,p2,k3)
TAKES = [
    ("talk_s0_1000lm_0.5px", "talk", 0, 1000, 0.5, None),
    ("turns_s1_300lm_0.5px", "turns", 1, 300, 0.5, None),
    ("talk_s2_1000lm_1.5px", "talk", 2, 1000, 1.5, None),
    ("calm_s3_100lm_1.5px", "calm", 3, 100, 1.5, None),
    ("talk_s4_1000lm_0.5px_distorted", "talk", 4, 1000, 0.5, "-0.25,0.08,0.001,-0.0015,0.0"),
]


def fit(actor, inp, settings, window, overlap, threads, frames: slice | None = None):
    """Fit (a slice of) a take; returns (vertices (T, V, 3), rms px (T,), stage timings)."""
    from capture.fit.take import TakeLandmarks, WindowedFit, fit_take

    pts, w = inp.points2d, inp.weights
    if frames is not None:
        pts, w = pts[frames], w[frames]
    tm: dict = {}
    t0 = time.perf_counter()
    V, rms = [], []
    for f in fit_take(actor, TakeLandmarks(pts, w, None, inp.template_points), inp.camera,
                      WindowedFit(settings, window, overlap, threads=threads), timings=tm):
        V.append(f.vertices)
        rms.append(f.reprojection_rms_px)
    tm["total_s"] = time.perf_counter() - t0
    return np.stack(V), np.array(rms), tm


def plots(out: Path, results: list[dict], faces, template) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    fig, ax = plt.subplots(figsize=(10, 3.8))
    for r in results:
        ax.plot(r["default"]["per_frame_mm"], lw=1, label=f"{r['name']} ({r['default']['mean_mm']:.2f} mm)")
    ax.set_xlabel("frame")
    ax.set_ylabel("mean vertex error (mm)")
    ax.set_title("2D take fit, default preset: 3D error per frame")
    ax.legend(fontsize=7)
    fig.tight_layout()
    paths.append(save_png(fig, out / "takes_error_per_frame.png"))
    plt.close(fig)

    stages = ["query", "pnp", "solve", "outputs"]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    bottom = np.zeros(len(results))
    for s in stages:
        v = np.array([r["default"]["ms_per_frame"][s] for r in results])
        ax.barh([r["name"] for r in results], v, left=bottom, label=s if s != "outputs" else "vertices")
        bottom += v
    ax.set_xlabel("ms per frame")
    ax.set_title("2D take fit, default preset: time per stage")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(save_png(fig, out / "takes_time_per_stage.png"))
    plt.close(fig)

    tv = np.asarray(template.vertices)
    vmax = max(float(np.percentile(r["_per_vertex"], 99)) for r in results)
    fig, axes = plt.subplots(1, len(results), figsize=(3.2 * len(results), 4.2))
    for ax, r in zip(np.atleast_1d(axes), results):
        pc = front_heatmap(ax, tv, faces, r["_per_vertex"], vmax, f"{r['name']}\nmean {r['default']['mean_mm']:.2f} mm")
    fig.colorbar(pc, ax=axes, shrink=0.7, label="mean error over frames (mm)")
    paths.append(save_png(fig, out / "takes_error_heatmap.png"))
    plt.close(fig)
    return paths


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--actor", default=str(DEFAULT_ACTOR))
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--window", type=int, default=30)
    ap.add_argument("--overlap", type=int, default=6)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--paper-frames", type=int, default=8, help="frames of the paper preset's one window (>= 2)")
    ap.add_argument("--paper-iterations", type=int, default=2000, help="measured iterations of the paper preset "
                    "(its 1e4 are extrapolated linearly from these)")
    ap.add_argument("--takes", help="comma-separated take names (default: all)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results"))
    ap.add_argument("--quick", action="store_true", help="check that it runs: 1 take of 6 frames at 320x240")
    args = ap.parse_args(argv)
    if args.paper_frames < 2:
        ap.error(f"--paper-frames must be at least 2 (the paper preset is fitted side by side on that many frames), "
                 f"got {args.paper_frames}")
    import torch

    from capture.actor.package import load_actor
    from capture.io.atomic import write_text
    from models.fit import FIT_PRESETS

    torch.set_num_threads(args.threads)
    takes = TAKES if not args.takes else [t for t in TAKES if t[0] in args.takes.split(",")]
    default = FIT_PRESETS["default"]
    if args.quick:
        takes = [TAKES[4][:3] + (100,) + TAKES[4][4:]]   # the distorted take, 100 landmarks
        args.frames, args.size, args.window, args.overlap = 6, "320x240", 4, 1
        args.paper_frames, args.paper_iterations = 2, 10
        default = replace(default, iterations=10, warm_iterations=5)
    paper = replace(FIT_PRESETS["paper"], iterations=args.paper_iterations, warm_iterations=None)
    scale = FIT_PRESETS["paper"].iterations / args.paper_iterations
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        actor_copy = Path(tmp) / "actor"   # synth writes the detector embedding into the package
        shutil.copytree(args.actor, actor_copy, ignore=shutil.ignore_patterns("training"))
        actor = load_actor(str(actor_copy))
        faces = np.asarray(actor.template.faces)
        for name, motion, seed, n_lm, noise, dist in takes:
            print(f"rendering and fitting {name} ...", flush=True)
            t0 = time.perf_counter()
            take = synth(actor_copy, Path(tmp) / name, args.frames, args.size, motion, seed, n_lm, dist)
            render_s = time.perf_counter() - t0
            inp = load_take(take, actor.template, noise, seed)
            V, rms, tm = fit(actor, inp, default, args.window, args.overlap, args.threads)
            d = accuracy(V, inp.truth, rms)
            d["ms_per_frame"] = stage_ms(tm, len(V))
            d["iterations"], d["windows"] = tm.get("iterations"), tm.get("windows_solved")
            J = min(args.paper_frames, len(V))
            pV, prms, ptm = fit(actor, inp, paper, J, 0, args.threads, frames=slice(0, J))
            p = accuracy(pV, inp.truth[:J], prms)
            pms = stage_ms(ptm, J)
            pms["total"] += (scale - 1) * pms["solve"]
            pms["solve"] *= scale
            same = accuracy(V[:J], inp.truth[:J], rms[:J])
            r = {"name": name, "motion": motion, "seed": seed, "landmarks": n_lm, "noise_px": noise,
                 "distortion": dist, "frames": len(V), "render_s": render_s, "default": d,
                 "paper": {**{k: v for k, v in p.items() if k != "per_vertex_mm"}, "ms_per_frame": pms,
                           "frames": J, "iterations_measured": args.paper_iterations,
                           "solve_extrapolated_x": scale},
                 "default_same_frames": {k: v for k, v in same.items() if k != "per_vertex_mm"},
                 "peak_rss_mb": peak_rss_mb(), "load_average": os.getloadavg()[0]}
            r["time_ratio_paper_over_default"] = pms["total"] / same_ms(d)
            r["error_ratio_default_over_paper"] = same["mean_mm"] / p["mean_mm"]
            r["_per_vertex"] = d.pop("per_vertex_mm")
            results.append(r)
            report_take(r)
        figs = plots(out, results, faces, actor.template)
    summary = {"actor": args.actor, "size": args.size, "threads": args.threads, "window": args.window,
               "overlap": args.overlap, "default_settings": default.to_dict(), "paper_settings": paper.to_dict(),
               "takes": [{k: v for k, v in r.items() if not k.startswith("_")} for r in results],
               "figures": [str(p) for p in figs]}
    p = out / ("takes_quick.json" if args.quick else "takes.json")
    write_text(p, json.dumps(summary, indent=1))
    print(f"\nfigures: {', '.join(map(str, figs))}; numbers: {p}")
    return summary


def same_ms(d: dict) -> float:
    """The default preset's total ms per frame (whole take: the per-frame cost a user pays)."""
    return d["ms_per_frame"]["total"]


def report_take(r: dict) -> None:
    d, p, s = r["default"], r["paper"], r["default_same_frames"]
    ms = d["ms_per_frame"]
    print(f"\n[{r['name']}] {r['frames']} frames, {r['landmarks']} landmarks, noise {r['noise_px']} px"
          f"{', distortion ' + r['distortion'] if r['distortion'] else ''}; render {r['render_s']:.0f} s; "
          f"load average {r['load_average']:.1f}")
    print(f"  default: mean {d['mean_mm']:.3f} mm, p95 {d['p95_mm']:.3f} mm, reprojection {d['rms_px']:.3f} px, "
          f"jitter {d.get('jitter_mm', float('nan')):.3f} mm (truth {d.get('truth_jitter_mm', float('nan')):.3f}, "
          f"excess {d.get('jitter_excess_mm', float('nan')):+.3f}; error hp {d.get('jitter_error_mm', float('nan')):.3f})")
    print(f"           ms/frame: query {ms['query']:.1f} | pnp {ms['pnp']:.1f} | solve {ms['solve']:.1f} | vertices "
          f"{ms['outputs']:.1f} | total {ms['total']:.1f}; {d['iterations']} iterations in {d['windows']} windows; "
          f"peak RSS {r['peak_rss_mb']:.0f} MB")
    x = p["solve_extrapolated_x"]
    lab = "" if x == 1 else f" (solve EXTRAPOLATED x{x:g} from {p['iterations_measured']} iterations; errors at those)"
    print(f"  paper, first {p['frames']} frames: mean {p['mean_mm']:.3f} mm, p95 {p['p95_mm']:.3f} mm, "
          f"{p['rms_px']:.3f} px, {p['ms_per_frame']['total']:.0f} ms/frame{lab}")
    print(f"  default on the same frames: mean {s['mean_mm']:.3f} mm, p95 {s['p95_mm']:.3f} mm; time ratio paper/default "
          f"{r['time_ratio_paper_over_default']:.0f}x, error ratio default/paper {r['error_ratio_default_over_paper']:.2f}")


if __name__ == "__main__":
    main()
