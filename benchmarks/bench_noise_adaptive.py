"""Noise-adaptive smoothing (models/fit_noise.py) against the fixed prior, on in-span synthetic takes.

Takes of the bundled demo actor (``capture synth``: talk, turns and calm motion with blinks and syllables at
~4 Hz; 150 frames at 30 fps) at three image sizes (360x288, 1280x720, 1920x1080) and with 300 to 1,000
landmarks. Each take's true landmarks get one of three kinds of error (:func:`benchmarks.outofspan.landmark_noise`
and ``slow``): Gaussian per frame (``iid``), the part of a detector's error that changes slowly (``slow``:
AR(1), correlation 0.8 between frames), and both with a bias per landmark (``detector``). The same landmarks
are fitted by the default preset (noise-adaptive) and by the same preset with the temporal prior fixed
(``adaptive_ref_px`` 0). Printed per take and error: mean 3D vertex error (mm), jitter above the truth's (mm),
the noise the fit read, the scales it used; JSON to ``--out``. The held-out ICT performances (out of span)
are in ``bench_outofspan.py --fixed-prior [--noise detector]``.

    python benchmarks/bench_noise_adaptive.py [--noise 0.5:iid,1.5:iid,1.5:slow] [--quick]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse
import json
import shutil
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the repo's packages
from benchmarks.outofspan import DETECTOR_NOISE_CORRELATION, ar1, landmark_noise
from benchmarks.takes import DEFAULT_ACTOR, REPO, accuracy, synth

# size, motion, seed, landmarks (seeds not used by the other benchmarks' takes)
TAKES = [("1280x720", "talk", 20, 1000), ("1280x720", "talk", 21, 300), ("1280x720", "turns", 22, 1000),
         ("1280x720", "calm", 23, 300), ("360x288", "talk", 30, 300), ("360x288", "talk", 31, 1000),
         ("360x288", "calm", 32, 300), ("1920x1080", "talk", 40, 1000), ("1920x1080", "talk", 41, 300),
         ("1920x1080", "turns", 42, 468)]


def errors(rng: np.random.Generator, T: int, L: int, px: float, model: str) -> np.ndarray:
    """``(T, L, 2)`` px: ``iid`` / ``detector`` as in bench_outofspan; ``slow``: the detector's AR(1) part alone."""
    if model != "slow":
        return landmark_noise(rng, T, L, px, model)
    rho = DETECTOR_NOISE_CORRELATION
    first = rng.normal(0.0, px, (L, 2))
    return ar1(first, rng.normal(0.0, px * np.sqrt(1 - rho * rho), (T, L, 2)), rho)


def main(argv: list[str] | None = None) -> dict:
    import torch

    from benchmarks.bench_takes import fit
    from benchmarks.takes import load_take
    from capture.actor.package import load_actor
    from capture.io.atomic import write_text
    from models.fit import FIT_PRESETS

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--actor", default=str(DEFAULT_ACTOR))
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--noise", default="0.5:iid,1.5:iid,1.5:slow", help="px:model,... (model iid, slow, detector)")
    ap.add_argument("--takes", default="", help="indices into TAKES, comma-separated (default: all)")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "noise_adaptive.json"))
    ap.add_argument("--quick", action="store_true", help="check that it runs: one 360x288 take of 40 frames")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    takes = [TAKES[int(i)] for i in args.takes.split(",")] if args.takes else TAKES
    if args.quick:
        takes, args.frames = [("360x288", "calm", 32, 300)], 40
    noises = [(float(a), b) for a, b in (n.split(":") for n in args.noise.split(","))]
    adaptive = FIT_PRESETS["default"]
    methods = {"adaptive (default)": adaptive, "fixed prior": replace(adaptive, adaptive_ref_px=0.0)}
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        actor_copy = Path(tmp) / "actor"   # synth writes the detector embedding into the package
        shutil.copytree(args.actor, actor_copy, ignore=shutil.ignore_patterns("training"))
        actor = load_actor(str(actor_copy))
        for size, motion, seed, n_lm in takes:
            name = f"{motion}_s{seed}_{n_lm}lm_{size}"
            take = synth(actor_copy, Path(tmp) / name, args.frames, size, motion, seed, n_lm)
            clean = load_take(take, actor.template, 0.0, seed)
            for px, model in noises:
                err = errors(np.random.default_rng(seed), *clean.points2d.shape[:2], px, model)
                inp = replace(clean, points2d=clean.points2d + err)
                row = {"take": name, "size": size, "motion": motion, "landmarks": n_lm, "noise_px": px,
                       "noise_model": model, "methods": {}}
                for label, settings in methods.items():
                    V, rms, tm = fit(actor, inp, settings, 30, 6, 1)
                    a = accuracy(V, inp.truth, rms)
                    row["methods"][label] = {"mean_mm": a["mean_mm"], "p95_mm": a["p95_mm"],
                                             "jitter_excess_mm": a.get("jitter_excess_mm"),
                                             **{k: tm[k] for k in ("landmark_noise_px", "landmarks_per_frame",
                                                                   "face_px_per_mm", "temporal_prior_scale_min",
                                                                   "temporal_prior_scale_max") if k in tm}}
                m, f = row["methods"]["adaptive (default)"], row["methods"]["fixed prior"]
                print(f"{name:28s} {px:.1f} px {model:8s} adaptive {m['mean_mm']:.3f} mm (jitter+ "
                      f"{m['jitter_excess_mm']:+.3f}; read {m.get('landmark_noise_px', float('nan')):.2f} px, "
                      f"{m.get('face_px_per_mm', float('nan')):.2f} px/mm, scale "
                      f"{m.get('temporal_prior_scale_min', 1):.1f}-{m.get('temporal_prior_scale_max', 1):.1f})   "
                      f"fixed {f['mean_mm']:.3f} mm (jitter+ {f['jitter_excess_mm']:+.3f})", flush=True)
                rows.append(row)
    print("\nmean over the takes (mm), adaptive / fixed:")
    summary = {}
    for px, model in noises:
        sel = [r for r in rows if r["noise_px"] == px and r["noise_model"] == model]
        a = [r["methods"]["adaptive (default)"]["mean_mm"] for r in sel]
        f = [r["methods"]["fixed prior"]["mean_mm"] for r in sel]
        d = np.subtract(a, f)
        summary[f"{px}:{model}"] = {"adaptive_mm": float(np.mean(a)), "fixed_mm": float(np.mean(f)),
                                    "worst_mm": float(d.max()), "best_mm": float(d.min())}
        print(f"  {px:.1f} px {model:8s} {np.mean(a):.3f} / {np.mean(f):.3f}; per take from {d.min():+.3f} to "
              f"{d.max():+.3f}")
    res = {"actor": args.actor, "frames": args.frames, "rows": rows, "summary": summary}
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text(out, json.dumps(res, indent=1))
    print(f"numbers: {out}")
    return res


if __name__ == "__main__":
    main()
