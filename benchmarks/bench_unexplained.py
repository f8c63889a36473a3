"""Does the run's report find the frames the actor does not explain? (``capture.fit.unexplained``)

The out-of-span benchmark's performances (:mod:`benchmarks.bench_outofspan`: held-out ICT expressions, or with
``--in-span`` the actor's own training expressions, in an ICT identity's face, with head and jaw motion) are fitted
from their landmarks by the 2D default (``capture run``'s fit), and each fitted frame's residuals go through the same
:class:`capture.fit.unexplained.ResidualTally` and rule as ``capture run``'s report. Against the truth, per
configuration (landmarks:noise):

* the frames flagged (in any region) and the mean 3D error on flagged and on unflagged frames;
* of the frames whose 3D error is over ``--bad-mm`` (default 0.5 mm), the share flagged (what the report finds);
* of the flagged frames, the share with error over ``--bad-mm`` (how often a note points at a frame that is fine).

With ``--in-span`` every flagged frame is a false alarm of "beyond the training shapes" (the fit's own lags remain).

Usage:
    python benchmarks/bench_unexplained.py --identity c --actor C --seeds 1,2,3,4,5 [--in-span] [--noise detector]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import argparse
import json
from pathlib import Path

import numpy as np

import sys  # noqa: E402
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run as a script: the repo's packages
from benchmarks.heldout import DEFAULT_ICT, IDENTITIES, identity_coeffs, load_ict_identity, make_performance, \
    sample_actor_split
from benchmarks.outofspan import NOISE_MODELS, landmark_take

REPO = Path(__file__).resolve().parents[1]
DEFAULT_ACTOR = REPO / "capture" / "data" / "demo_actor"
SAMPLE_JSON = REPO / "capture" / "data" / "sample_actor" / "sample.json"


def fit_and_tally(actor, take, idx: np.ndarray):
    """The 2D default fit (``capture run``'s, windows 30 / overlap 6, 1 thread) of frames ``idx`` of a landmark
    take, each fitted frame's residuals tallied as ``capture run`` tallies them
    (:func:`capture.export.overlay_draw.confident_residuals`, every seen landmark confident; frames numbered 0..),
    and the frames' mean 3D errors against the truth (mm). Returns ``(tally, errors (T,))``."""
    from capture.export.overlay_draw import confident_residuals
    from capture.fit.take import TakeLandmarks, WindowedFit, fit_take
    from capture.fit.unexplained import ResidualTally
    from capture.run.take import Detection
    from models.fit import FIT_PRESETS

    fits = list(fit_take(actor, TakeLandmarks(take.points2d[idx], take.weights[idx], None, take.template_points),
                         take.camera, WindowedFit(FIT_PRESETS["default"], 30, 6, threads=1)))
    tally = ResidualTally.on_template(actor.template, take.template_points)
    for t, (f, j) in enumerate(zip(fits, idx)):
        lengths, used = confident_residuals(f, Detection(take.points2d[j], None, True))
        tally.add(t, lengths, used & (take.weights[j] > 0))
    err = np.array([np.linalg.norm(f.vertices - take.truth[j], axis=1).mean() for f, j in zip(fits, idx)])
    return tally, err


def flag_frames(tally, frames: np.ndarray) -> tuple[np.ndarray, list]:
    """Which of ``frames`` lie in a run of the report's rule (:func:`capture.run.report.unexplained_section`)."""
    from capture.run.report import unexplained_section

    section, _ = unexplained_section(tally, 30.0)
    flagged = np.zeros(len(frames), bool)
    for sp in section["spans"]:
        flagged |= (frames >= sp["first"]) & (frames <= sp["last"])
    return flagged, section["spans"]


def run_seed(args, seed: int, actor, ident, pool, configs) -> list[dict]:
    perf = make_performance(ident, pool, args.sequences, args.frames, seed=seed, rigid_jaw=args.rigid_jaw)
    rows = []
    for n_lm, noise in configs:
        take = landmark_take(perf.vertices, actor.template, n_lm, noise, seed, noise=args.noise)
        for s in range(args.sequences):
            idx = np.flatnonzero(perf.sequence == s)
            tally, err = fit_and_tally(actor, take, idx)
            frames = np.arange(len(idx))
            flagged, spans = flag_frames(tally, frames)
            rows.append({"seed": seed, "landmarks": n_lm, "noise_px": noise, "sequence": s,
                         "noise_read_px": tally.sigma, "error_mm": err.tolist(), "flagged": flagged.tolist(),
                         "spans": spans})
            runs = ", ".join(f"{sp['region']} {sp['first']}-{sp['last']} x{sp['mean_ratio']:.1f}" for sp in spans)
            print(f"seed {seed} [{n_lm}:{noise}] sequence {s}: mean {err.mean():.3f} mm, {flagged.sum()} frames "
                  f"flagged ({runs or 'none'}), noise read {tally.sigma:.3f} px", flush=True)
    return rows


def summarise(rows: list[dict], bad_mm: float) -> list[dict]:
    """Per configuration: frames, flagged, the mean error on flagged and unflagged frames, the share of bad frames
    flagged and the share of flagged frames that are bad."""
    out = []
    for key in sorted({(r["landmarks"], r["noise_px"]) for r in rows}, key=lambda k: (-k[0], k[1])):
        rs = [r for r in rows if (r["landmarks"], r["noise_px"]) == key]
        err = np.concatenate([r["error_mm"] for r in rs])
        fl = np.concatenate([r["flagged"] for r in rs]).astype(bool)
        bad = err > bad_mm
        seq_flagged = sum(bool(np.any(r["flagged"])) for r in rs)
        seq_bad = [float(np.mean(r["error_mm"])) > bad_mm for r in rs]
        out.append({"landmarks": key[0], "noise_px": key[1], "frames": int(len(err)), "flagged": int(fl.sum()),
                    "error_flagged_mm": float(err[fl].mean()) if fl.any() else None,
                    "error_unflagged_mm": float(err[~fl].mean()) if (~fl).any() else None,
                    "bad_frames": int(bad.sum()), "bad_flagged": int((bad & fl).sum()),
                    "sequences": len(rs), "sequences_flagged": seq_flagged,
                    "sequences_over_bad_mm": int(sum(seq_bad)),
                    "sequences_over_bad_mm_flagged": int(sum(b and bool(np.any(r["flagged"]))
                                                             for b, r in zip(seq_bad, rs)))})
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--actor", default=str(DEFAULT_ACTOR))
    ap.add_argument("--ict", default=str(DEFAULT_ICT))
    ap.add_argument("--identity", default="sample", choices=IDENTITIES)
    ap.add_argument("--seeds", default="1,2,3,4,5")
    ap.add_argument("--sequences", type=int, default=4)
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--configs", default="1000:0.5,300:1.5", help="landmarks:noise_px, ...")
    ap.add_argument("--noise", default="iid", choices=NOISE_MODELS)
    ap.add_argument("--in-span", action="store_true", help="the actor's own training expressions (a control)")
    ap.add_argument("--rigid-jaw", action="store_true")
    ap.add_argument("--bad-mm", type=float, default=0.5, help="a frame's mean 3D error counted as bad")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results" / "unexplained.json"))
    ap.add_argument("--quick", action="store_true", help="check that it runs: 1 seed, 1 sequence of 12 frames")
    args = ap.parse_args(argv)
    import torch

    from capture.actor.package import load_actor
    from capture.io.atomic import write_text

    torch.set_num_threads(1)
    seeds = [int(s) for s in args.seeds.split(",")]
    configs = [(int(a), float(b)) for a, b in (c.split(":") for c in args.configs.split(","))]
    if args.quick:
        seeds, args.sequences, args.frames, configs = seeds[:1], 1, 12, configs[:1]
    training, held_out = sample_actor_split(SAMPLE_JSON)
    pool = [n for n in training if not n.startswith("jaw")] if args.in_span else held_out
    ident = load_ict_identity(Path(args.ict), identity_coeffs(args.identity, Path(args.ict)))
    actor = load_actor(args.actor)
    rows = [r for seed in seeds for r in run_seed(args, seed, actor, ident, pool, configs)]
    summary = summarise(rows, args.bad_mm)
    print(f"\n{'config':>10s} {'frames':>6s} {'flagged':>7s} {'mm flagged':>10s} {'unflagged':>9s} "
          f"{'bad found':>10s} {'flagged bad':>11s}  sequences over {args.bad_mm} mm flagged")
    for s in summary:
        print(f"{s['landmarks']:>5d}:{s['noise_px']:<4g} {s['frames']:6d} {s['flagged']:7d} "
              f"{s['error_flagged_mm'] or float('nan'):10.3f} {s['error_unflagged_mm'] or float('nan'):9.3f} "
              f"{s['bad_flagged']:4d}/{s['bad_frames']:<5d} {s['bad_flagged']:5d}/{s['flagged']:<5d}  "
              f"{s['sequences_over_bad_mm_flagged']}/{s['sequences_over_bad_mm']} (any flag: "
              f"{s['sequences_flagged']}/{s['sequences']})")
    res = {"identity": args.identity, "actor": str(args.actor), "seeds": seeds, "in_span": args.in_span,
           "rigid_jaw": args.rigid_jaw, "noise_model": args.noise, "bad_mm": args.bad_mm, "summary": summary,
           "sequences": [{k: v for k, v in r.items() if k not in ("error_mm", "flagged")} |
                         {"mean_mm": float(np.mean(r["error_mm"])), "frames_flagged": int(np.sum(r["flagged"]))}
                         for r in rows]}
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    write_text(Path(args.out), json.dumps(res, indent=1))
    print(f"numbers: {args.out}")
    return res


if __name__ == "__main__":
    main()
