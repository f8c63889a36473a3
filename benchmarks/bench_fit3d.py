"""3D fit on held-out expressions: ``capture fit3d`` (AIM) against the global blendshape baseline (GBS).

The performance (:mod:`benchmarks.heldout`): the bundled sample actor's ICT identity animated with
expressions outside its 19 training shapes, at partial weights, mixed with partial jaw shapes and a
rigid head motion; several sequences, registered meshes in the actor's topology (9,409 vertices, mm).

* AIM: the actor (default: the bundled demo actor, trained on the sample) fitted with
  :func:`capture.fit.take.fit_meshes`, the fit behind ``capture fit3d``, with that command's
  defaults (preset ``default``, window 30, overlap 6, 1,000 sampled vertices), one fit per sequence.
* GBS: per frame, rigid pose + least squares on the SAME 19 training shapes (exact ICT deltas of the
  identity; weights bounded to [0, 1], and unbounded), every vertex constrained (:mod:`benchmarks.gbs`).

Printed: mean / p95 vertex error (mm) on the face region (9,409 vertices) and on the narrow face
(ICT vertices 0..6705: no scalp, ears or neck), per sequence, the ratio AIM / GBS (the paper: 0.312 /
0.834 mm = 0.37), per held-out expression the error where it acts, time per frame, peak memory.
Figures (PNG) and a JSON of the numbers go to ``--out`` (default ``benchmarks/results``).

Usage:
    python benchmarks/bench_fit3d.py [--sequences 4] [--frames 90] [--threads 1] [--quick]
    python benchmarks/bench_fit3d.py --identity c --actor C [--rigid-jaw]   # a face no setting was chosen on

``--identity b|c`` plays the performance in another ICT identity's face, for an actor learned from that identity's
shapes (``benchmarks.heldout.write_identity_shapes``); ``--rigid-jaw`` turns the jaw shapes as a jaw does
(``benchmarks.heldout.RigidJaw``) instead of ICT's linear blends, which bend the teeth.
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")   # numpy/scipy BLAS: many threads only fight on a shared 2-core machine

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

import sys  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the repo's packages
from benchmarks.gbs import fit_gbs_sequence
from benchmarks.heldout import (DEFAULT_ICT, IDENTITIES, JAW_RANGES, NARROW_FACE_NV, identity_coeffs,
                               load_ict_identity, make_performance, sample_actor_split)
from benchmarks.takes import front_heatmap, peak_rss_mb, save_png

REPO = Path(__file__).resolve().parents[1]
DEFAULT_ACTOR = REPO / "capture" / "data" / "demo_actor"
SAMPLE_JSON = REPO / "capture" / "data" / "sample_actor" / "sample.json"
PAPER = {"aim_mm": 0.312, "gbs_mm": 0.834}


def vertex_errors(fit: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """(T, V) distances (mm) between fitted and true vertices."""
    return np.linalg.norm(np.asarray(fit, np.float64) - truth, axis=2)


def stats(err: np.ndarray) -> dict:
    return {"mean_mm": float(err.mean()), "p95_mm": float(np.percentile(err, 95)), "max_mm": float(err.max())}


def fit_aim(actor, meshes: np.ndarray, sequence: np.ndarray, settings, window: int, overlap: int, samples: int,
            threads: int) -> tuple[np.ndarray, dict]:
    """``fit_meshes`` once per sequence -> (fitted vertices (T, V, 3), timings)."""
    from capture.fit.take import WindowedFit, fit_meshes

    out = np.empty_like(meshes, dtype=np.float32)
    tm: dict = {}
    t0 = time.perf_counter()
    for s in np.unique(sequence):
        idx = np.flatnonzero(sequence == s)
        for f in fit_meshes(actor, meshes[idx], WindowedFit(settings, window, overlap, threads=threads),
                            n_samples=samples, timings=tm):
            out[idx[f.frame]] = f.vertices
        print(f"  AIM: sequence {s} fitted ({len(idx)} frames, {time.perf_counter() - t0:.0f} s so far)", flush=True)
    tm["total_s"] = time.perf_counter() - t0
    return out, tm


def per_expression(perf, ident, err_aim: np.ndarray, err_gbs: np.ndarray, held_out: list[str]) -> list[dict]:
    """Per held-out expression: mean error over the vertices it moves > 1 mm, on frames where its weight > 0.2."""
    rows = []
    for k, n in enumerate(perf.names):
        if n not in held_out:
            continue
        frames = perf.weights[:, k] > 0.2
        verts = np.linalg.norm(ident.deltas[n], axis=1) > 1.0
        if frames.sum() == 0 or verts.sum() == 0:
            continue
        rows.append({"expression": n, "frames": int(frames.sum()), "vertices": int(verts.sum()),
                     "aim_mm": float(err_aim[np.ix_(frames, verts)].mean()),
                     "gbs_mm": float(err_gbs[np.ix_(frames, verts)].mean())})
    return sorted(rows, key=lambda r: -r["aim_mm"])


def save_figures(out: Path, faces: np.ndarray, neutral: np.ndarray, err: dict[str, np.ndarray],
                 sequence: np.ndarray) -> list[Path]:
    """Error per frame (all methods) and front-view heat maps of the mean error per vertex."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    fig, ax = plt.subplots(figsize=(10, 3.5))
    for name, e in err.items():
        ax.plot(e.mean(1), lw=1, label=f"{name} (mean {e.mean():.3f} mm)")
    for b in np.flatnonzero(np.diff(sequence)) + 0.5:
        ax.axvline(b, color="0.7", lw=0.8, ls="--")
    ax.set_xlabel("frame (dashed: sequence boundaries)")
    ax.set_ylabel("mean vertex error (mm)")
    ax.set_title("3D fit to held-out expressions: error per frame (face region, 9,409 vertices)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(save_png(fig, out / "fit3d_error_per_frame.png"))
    plt.close(fig)

    vmax = max(float(np.percentile(e.mean(0), 99)) for e in err.values())
    fig, axes = plt.subplots(1, len(err), figsize=(4.2 * len(err), 5))
    for ax, (name, e) in zip(np.atleast_1d(axes), err.items()):
        pc = front_heatmap(ax, neutral, faces, e.mean(0), vmax, f"{name}: mean {e.mean():.3f} mm")
    fig.colorbar(pc, ax=axes, shrink=0.8, label="mean error over frames (mm)")
    paths.append(save_png(fig, out / "fit3d_error_heatmap.png"))
    plt.close(fig)
    return paths


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--actor", default=str(DEFAULT_ACTOR), help="actor trained on the identity's shapes (default: "
                    "the demo actor, trained on the sample)")
    ap.add_argument("--identity", default="sample", choices=IDENTITIES, help="the performer's ICT identity (the "
                    "actor must be learned from its shapes)")
    ap.add_argument("--rigid-jaw", action="store_true", help="turn the jaw shapes rigidly, as a jaw does, instead of "
                    "ICT's linear blends")
    ap.add_argument("--ict", default=str(DEFAULT_ICT), help="ict_facekit_light.npz")
    ap.add_argument("--sequences", type=int, default=4)
    ap.add_argument("--frames", type=int, default=90, help="frames per sequence (30 fps)")
    ap.add_argument("--per-sequence", type=int, default=5, help="held-out expressions per sequence")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--peak", default="0.3,0.8", help="range of the held-out expressions' peak weights")
    ap.add_argument("--control-frames", type=int, default=90, help="frames of a control sequence made of TRAINING "
                    "shapes only (in the span of GBS: separates the fit and actor floor from generalisation; 0: none)")
    ap.add_argument("--preset", default="default", help="fit preset of capture fit3d: default, networks or paper")
    ap.add_argument("--iterations", type=int, help="override the preset's first-window iterations")
    ap.add_argument("--samples", type=int, help="fitted vertices (default: capture fit3d's for the preset)")
    ap.add_argument("--window", type=int, default=30)
    ap.add_argument("--overlap", type=int, default=6)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results"), help="folder of figures and JSON")
    ap.add_argument("--quick", action="store_true", help="check that it runs: 1 sequence of 8 frames, 10 iterations")
    args = ap.parse_args(argv)
    import torch

    from capture.actor.package import load_actor
    from capture.io.atomic import write_text
    from models.fit import FIT3D_PRESETS

    torch.set_num_threads(args.threads)
    settings = FIT3D_PRESETS[args.preset]
    if args.iterations:
        settings = replace(settings, iterations=args.iterations)
    if args.quick:
        args.sequences, args.frames, args.window, args.overlap, args.samples = 1, 8, 4, 1, 200
        args.control_frames = 0
        settings = replace(settings, iterations=10, warm_iterations=5)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    training, held_out = sample_actor_split(SAMPLE_JSON)
    ident = load_ict_identity(Path(args.ict), identity_coeffs(args.identity, Path(args.ict)))
    perf = make_performance(ident, held_out, args.sequences, args.frames, per_sequence=args.per_sequence,
                            seed=args.seed, peak=tuple(float(v) for v in args.peak.split(",")),
                            rigid_jaw=args.rigid_jaw)
    truth = perf.vertices
    print(f"held-out performance: {json.dumps(perf.describe())}")
    print("  jaw: jawOpen / jawLeft / jawRight are TRAINING shapes, used at partial weights only; every other "
          "active shape is held out")

    actor = load_actor(args.actor)
    tv = np.asarray(actor.template.vertices, np.float64)
    if tv.shape != ident.neutral.shape or np.abs(tv - ident.neutral).max() > 1e-3:
        raise SystemExit(f"actor {args.actor} does not have identity {args.identity}'s template; train it on that "
                         f"identity's shapes (the sample's: the bundled sample actor)")
    t0 = time.perf_counter()
    fitted, tm = fit_aim(actor, truth, perf.sequence, settings, args.window, args.overlap, args.samples,
                         args.threads)
    aim_s = time.perf_counter() - t0
    rss_aim = peak_rss_mb()

    D = np.stack([ident.deltas[n] for n in training])
    gbs, gbs_s = {}, {}
    for bounded in (True, False):
        t0 = time.perf_counter()
        fits = fit_gbs_sequence(truth, ident.neutral, D, bounded=bounded)
        gbs["GBS [0,1]" if bounded else "GBS unbounded"] = np.stack([f.vertices for f in fits])
        gbs_s["GBS [0,1]" if bounded else "GBS unbounded"] = time.perf_counter() - t0

    err = {"AIM (fit3d)": vertex_errors(fitted, truth)}
    err.update({k: vertex_errors(v, truth) for k, v in gbs.items()})
    T = len(truth)
    res = {"performance": perf.describe(), "identity": args.identity, "rigid_jaw": args.rigid_jaw,
           "actor": str(args.actor), "preset": args.preset,
           "fit_settings": settings.to_dict(), "window": args.window, "overlap": args.overlap,
           "samples": args.samples, "threads": args.threads, "load_average": os.getloadavg(), "methods": {}}
    print(f"\n{T} frames; load average {os.getloadavg()[0]:.1f} (2 cores shared: times are inflated)")
    print(f"{'method':16s} {'face mean':>9s} {'p95':>6s} {'narrow mean':>11s} {'p95':>6s}  per sequence (face mean)")
    for name, e in err.items():
        m = {"face": stats(e), "narrow_face": stats(e[:, :NARROW_FACE_NV]),
             "outer": stats(e[:, NARROW_FACE_NV:]),
             "per_sequence_mm": [float(e[perf.sequence == s].mean()) for s in np.unique(perf.sequence)]}
        res["methods"][name] = m
        print(f"{name:16s} {m['face']['mean_mm']:9.3f} {m['face']['p95_mm']:6.3f} {m['narrow_face']['mean_mm']:11.3f} "
              f"{m['narrow_face']['p95_mm']:6.3f}  " + " ".join(f"{v:.3f}" for v in m["per_sequence_mm"]))
    aim = res["methods"]["AIM (fit3d)"]
    for g in gbs:
        for region in ("face", "narrow_face"):
            r = aim[region]["mean_mm"] / res["methods"][g][region]["mean_mm"]
            res.setdefault("ratio", {})[f"{g} {region}"] = r
        print(f"ratio AIM / {g}: face {res['ratio'][f'{g} face']:.3f}, narrow face "
              f"{res['ratio'][f'{g} narrow_face']:.3f}   (paper {PAPER['aim_mm']} / {PAPER['gbs_mm']} = "
              f"{PAPER['aim_mm'] / PAPER['gbs_mm']:.2f}; target <= 0.37)")
    res["time"] = {"aim_s_per_frame": aim_s / T, "aim_solve_s_per_frame": tm.get("solve_s", 0) / T,
                   "aim_vertices_s_per_frame": tm.get("outputs_s", 0) / T, "aim_iterations": tm.get("iterations"),
                   "aim_windows": tm.get("windows_solved"),
                   **{f"{k}_s_per_frame": v / T for k, v in gbs_s.items()}}
    res["peak_rss_mb_after_aim"] = rss_aim
    res["peak_rss_mb"] = peak_rss_mb()
    print(f"time per frame: AIM {1000 * aim_s / T:.0f} ms (solve {1000 * tm.get('solve_s', 0) / T:.0f}, vertices "
          f"{1000 * tm.get('outputs_s', 0) / T:.0f}; {tm.get('iterations')} iterations in {tm.get('windows_solved')} "
          f"windows), " + ", ".join(f"{k} {1000 * v / T:.0f} ms" for k, v in gbs_s.items()))
    print(f"peak memory (process RSS): {rss_aim:.0f} MB after the AIM fit, {res['peak_rss_mb']:.0f} MB at the end")

    if args.control_frames > 0:
        ctrl = make_performance(ident, [n for n in training if n not in JAW_RANGES], 1, args.control_frames,
                                per_sequence=args.per_sequence, seed=args.seed + 1000, rigid_jaw=args.rigid_jaw)
        cf, _ = fit_aim(actor, ctrl.vertices, ctrl.sequence, settings, args.window, args.overlap, args.samples,
                        args.threads)
        cg = np.stack([f.vertices for f in fit_gbs_sequence(ctrl.vertices, ident.neutral, D, bounded=True)])
        ea, eg = vertex_errors(cf, ctrl.vertices), vertex_errors(cg, ctrl.vertices)
        res["control_training_shapes"] = {"performance": ctrl.describe(), "aim": stats(ea), "gbs": stats(eg),
                                          "aim_narrow_face": stats(ea[:, :NARROW_FACE_NV])}
        print(f"control (training shapes only, {args.control_frames} frames): AIM mean {ea.mean():.3f} mm (narrow "
              f"face {ea[:, :NARROW_FACE_NV].mean():.3f}), GBS [0,1] {eg.mean():.3f} mm (in its span)")

    rows = per_expression(perf, ident, err["AIM (fit3d)"], err["GBS [0,1]"], held_out)
    res["per_expression"] = rows
    print("\nwhere the held-out expressions act (vertices moved > 1 mm, frames with weight > 0.2):")
    for r in rows:
        print(f"  {r['expression']:18s} {r['frames']:4d} frames {r['vertices']:5d} vertices: "
              f"AIM {r['aim_mm']:.3f} mm, GBS {r['gbs_mm']:.3f} mm")
    figs = save_figures(out, np.asarray(actor.template.faces), ident.neutral, err, perf.sequence)
    res["figures"] = [str(p) for p in figs]
    p = out / "fit3d.json"
    write_text(p, json.dumps(res, indent=1))
    print(f"\nfigures: {', '.join(str(p) for p in figs)}; numbers: {p}")
    return res


if __name__ == "__main__":
    main()
