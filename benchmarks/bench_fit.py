"""Speed and accuracy of the take-level fit (``capture.fit.take``): default preset vs the paper's.

A synthetic take of an ICT-based actor (``capture synth``, preset ``talk``) is fitted from its true
landmarks plus 0.5 px Gaussian noise. Printed per preset: seconds per frame of each stage, mean and
95th-percentile 3D vertex error (mm) against the truth meshes, reprojection RMS (px), and jitter
(RMS over vertices and frames of the high-passed trajectory minus the truth's high-passed
trajectory, mm; high pass = signal minus its Gaussian smoothing with sigma 2 frames).

Rows: the default preset; the previous default (Adam only: 500 + 150 iterations with early stop,
no Levenberg-Marquardt base; ``--no-previous`` skips it), run back to back for an A/B speed-up under
the same load; the paper preset. The load average is printed with the figures.

The paper preset (1e4 iterations per window, lr 1e-3, weights 0.75 / 0.05, squared loss) runs on
one short window only; its time per frame is measured there (and, with ``--paper-iterations`` below
1e4, extrapolated linearly to 1e4 iterations and labelled so). Its errors are compared with the
default preset's errors on the same frames.

Usage:
    python benchmarks/bench_fit.py [--actor PATH] [--frames 60] [--quick]
Without ``--actor`` an actor is trained at /tmp/ict (``capture actor train /tmp/ict --sample
--iterations 300 --width 128``, a few minutes) unless it already exists.
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch
from scipy.ndimage import gaussian_filter1d

from calib.camera_io import read_camera
from capture.actor.package import is_actor, load_actor
from capture.cli import main as capture_main
from capture.fit.take import TakeLandmarks, WindowedFit, fit_take, resolved_settings_dict
from models.fit import FIT_PRESETS, FitSettings

# The default preset before the Levenberg-Marquardt base (for the A/B row).
PREVIOUS_DEFAULT = FitSettings(hidden=64, temporal_weight=0.5, early_stop_tol=2e-3)


def ensure_actor(path: str | None) -> str:
    if path:
        return path
    p = Path("/tmp/ict")
    if not is_actor(p):
        print("training an ICT sample actor at /tmp/ict (300 iterations, width 128) ...", flush=True)
        assert capture_main(["actor", "train", str(p), "--sample", "--iterations", "300", "--width", "128",
                             "--no-progress"]) == 0
    return str(p)


def metrics(fits, truth: np.ndarray) -> dict:
    V = np.stack([f.vertices for f in fits]).astype(np.float64)
    err = np.linalg.norm(V - truth, axis=2)
    fitted = np.array([f.status == "fitted" for f in fits])
    out = {"mean_mm": float(err[fitted].mean()), "p95_mm": float(np.percentile(err[fitted], 95)),
           "rms_px": float(np.sqrt(np.nanmean(np.array([f.reprojection_rms_px for f in fits]) ** 2)))}
    if len(V) >= 5:
        hp = lambda x: x - gaussian_filter1d(x, 2.0, axis=0, mode="nearest")
        out["jitter_mm"] = float(np.sqrt((np.linalg.norm(hp(V) - hp(truth.astype(np.float64)), axis=2) ** 2).mean()))
    return out


def run(actor, inputs, settings, window, overlap, threads, frames=None):
    pts, w, tp, cam = inputs
    if frames is not None:
        pts, w = pts[frames], w[frames]
    tm: dict = {}
    t0 = time.perf_counter()
    fits = list(fit_take(actor, TakeLandmarks(pts, w, None, tp), cam,
                         WindowedFit(settings, window, overlap, threads=threads), timings=tm))
    tm["total_s"] = time.perf_counter() - t0
    return fits, tm


def stage_line(tm: dict, n: int, scale: float = 1.0) -> str:
    ms = lambda k: 1000 * tm.get(k, 0.0) / n
    return (f"query {ms('query_s'):.1f} | pnp {ms('pnp_s'):.1f} | solve {scale * ms('solve_s'):.1f} | "
            f"vertices {ms('outputs_s'):.1f} | total {ms('total_s') + (scale - 1) * ms('solve_s'):.1f} ms/frame; "
            f"{tm.get('iterations', 0)} Adam + {tm.get('lm_iterations', 0)} LM iterations in "
            f"{tm.get('windows_solved', 0)} windows")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--actor", help="actor package (default: train /tmp/ict if missing)")
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--size", default="640x480")
    ap.add_argument("--landmarks", type=int, default=468)
    ap.add_argument("--window", type=int, default=30)
    ap.add_argument("--overlap", type=int, default=6)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--paper-frames", type=int, default=8, help="window length of the paper-preset run (0: skip it)")
    ap.add_argument("--paper-iterations", type=int, default=10_000)
    ap.add_argument("--noise-px", type=float, default=0.5)
    ap.add_argument("--no-previous", action="store_true", help="skip the previous default's A/B row")
    ap.add_argument("--quick", action="store_true", help="30 frames, paper preset 1,000 iterations (extrapolated)")
    args = ap.parse_args()
    if args.quick:
        args.frames, args.paper_iterations, args.paper_frames = 30, 1000, 6
    torch.set_num_threads(args.threads)
    actor_path = ensure_actor(args.actor)
    with tempfile.TemporaryDirectory() as tmp:
        # render into a copy of the actor: synth writes the detector embedding into the package
        import shutil
        actor_copy = Path(tmp) / "actor"
        shutil.copytree(actor_path, actor_copy, ignore=shutil.ignore_patterns("training"))
        out = Path(tmp) / "take"
        t0 = time.perf_counter()
        assert capture_main(["synth", "--actor", str(actor_copy), "--out", str(out), "--frames", str(args.frames),
                             "--size", args.size, "--preset", "talk", "--landmarks", str(args.landmarks),
                             "--no-progress"]) == 0
        print(f"synthetic take: {args.frames} frames {args.size}, {args.landmarks} landmarks, "
              f"{time.perf_counter() - t0:.1f} s to render", flush=True)
        actor = load_actor(str(actor_copy))
        cam = read_camera(out / "camera.json")
        lm = np.load(out / "truth_landmarks.npz")
        truth = np.load(out / "truth_meshes.npz")["vertices"]
    tv, tf = np.asarray(actor.template.vertices), np.asarray(actor.template.faces)
    tp = np.einsum("lk,lkc->lc", lm["barycentric"], tv[tf[lm["face_index"]]])
    rng = np.random.default_rng(0)
    pts = lm["points_2d"] + rng.normal(0.0, args.noise_px, lm["points_2d"].shape)
    w = lm["visible"].astype(np.float64)
    inputs = (pts, w, tp, cam)
    print(f"actor {actor_path}: {len(tv)} vertices, {actor.config.n_expressions} expressions; "
          f"noise {args.noise_px} px; threads {args.threads}")

    default = FIT_PRESETS["default"]
    fits, tm = run(actor, inputs, default, args.window, args.overlap, args.threads)
    m = metrics(fits, truth)
    print(f"\n[default] window {args.window}, overlap {args.overlap}, {args.frames} frames")
    print("  " + stage_line(tm, len(fits)))
    print("  error mean {mean_mm:.3f} mm, p95 {p95_mm:.3f} mm, reprojection RMS {rms_px:.3f} px, "
          "jitter {jitter_mm:.3f} mm".format(**m))
    print(f"  load average {os.getloadavg()[0]:.1f}")
    print("  resolved settings:", json.dumps(resolved_settings_dict(default, args.window, args.overlap,
                                                                  threads=args.threads)))
    if not args.no_previous:
        pfits, ptm0 = run(actor, inputs, PREVIOUS_DEFAULT, args.window, args.overlap, args.threads)
        m0 = metrics(pfits, truth)
        print("\n[previous default] (Adam only) same take, run right after")
        print("  " + stage_line(ptm0, len(pfits)))
        print("  error mean {mean_mm:.3f} mm, p95 {p95_mm:.3f} mm, reprojection RMS {rms_px:.3f} px, "
              "jitter {jitter_mm:.3f} mm".format(**m0))
        print(f"  load average {os.getloadavg()[0]:.1f}; default is {ptm0['total_s'] / tm['total_s']:.1f}x faster "
              f"end to end ({ptm0['solve_s'] / max(tm['solve_s'], 1e-9):.1f}x in the solve)")

    J = args.paper_frames
    if J <= 0:  # --paper-frames 0: no paper-preset row
        return
    paper = replace(FIT_PRESETS["paper"], iterations=args.paper_iterations, warm_iterations=None)
    scale = 10_000 / args.paper_iterations
    pf, ptm = run(actor, inputs, paper, J, 0, args.threads, frames=slice(0, J))
    pm = metrics(pf, truth[:J])
    dm = metrics(fits[:J], truth[:J])
    label = "" if scale == 1 else f" (solve measured at {args.paper_iterations} iterations, EXTRAPOLATED x{scale:g} to 1e4)"
    print(f"\n[paper] one window of {J} frames, 1e4 iterations{label}")
    print("  " + stage_line(ptm, J, scale))
    print(f"  error mean {pm['mean_mm']:.3f} mm, p95 {pm['p95_mm']:.3f} mm, reprojection RMS {pm['rms_px']:.3f} px"
          + (" (at the measured iterations)" if scale != 1 else ""))
    print(f"  default preset on the same {J} frames: mean {dm['mean_mm']:.3f} mm, p95 {dm['p95_mm']:.3f} mm, "
          f"RMS {dm['rms_px']:.3f} px")
    paper_ms = 1000 * (ptm["total_s"] + (scale - 1) * ptm["solve_s"]) / J
    print(f"  load average {os.getloadavg()[0]:.1f}; default is {paper_ms / (1000 * tm['total_s'] / len(fits)):.0f}x "
          f"faster per frame than the paper preset (end to end)")


if __name__ == "__main__":
    main()
