"""Render speed of ``capture synth`` and the synthetic dense detector's speed and accuracy.

Per preset (default: frontal, yaw30, turns): render + lossless encode seconds per frame, the ONNX
detector's seconds per frame (onnxruntime, 1 thread) and its error against the projected truth on
the decoded frames: median over visible landmarks; RMS and p99 over confident (> 0.5) visible ones;
the fraction of visible landmarks flagged (confidence <= 0.5) and of occluded ones left confident.

Usage: python benchmarks/bench_synth.py ACTOR [--frames 20] [--landmarks 1000] [--size 1280x720]
       python benchmarks/bench_synth.py ACTOR --quick      (4 frames, 300 landmarks, 640x360)
(e.g. a copy of capture/data/demo_actor: ``capture synth`` writes the detector's embedding into it).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

from capture.synth.detector_onnx import square_crop
from capture.synth.take import SynthConfig, synthesize
from capture.synth.video import read_frames


def measure(actor: str, preset: str, frames: int, landmarks: int, size: tuple[int, int]) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "take"
        synthesize(SynthConfig(actor=actor, out=out, frames=frames, preset=preset, landmarks=landmarks, size=size))
        report = json.loads((out / "truth.json").read_text())
        spec = json.loads((out / report["detector"]["spec"]).read_text())
        so = ort.SessionOptions()
        so.intra_op_num_threads = 1
        sess = ort.InferenceSession(str(out / report["detector"]["onnx"]), so)
        S = spec["input"]["size"][0]
        lms = np.load(out / "truth_landmarks.npz")
        times, errs, conf, vis = [], [], [], []
        for j, frame in enumerate(read_frames(out / "take.mp4")):
            p, v = lms["points_2d"][j], lms["visible"][j]
            crop, M = square_crop(frame, (*p[v].min(0), *p[v].max(0)), spec["crop"]["margin"], S)
            t0 = time.perf_counter()
            pts, c, _ = sess.run(None, {"image": crop.transpose(2, 0, 1)[None].astype(np.float32)})
            times.append(time.perf_counter() - t0)
            errs.append(np.linalg.norm((pts[0] - M[:, 2]) / M[0, 0] - p, axis=1))
            conf.append(c[0])
            vis.append(v)
    e, c, v = np.concatenate(errs), np.concatenate(conf), np.concatenate(vis)
    ok = v & (c > 0.5)
    return {"preset": preset, "render_s": report["timings"]["render_per_frame_s"], "detect_s": float(np.median(times)),
            "median": float(np.median(e[v])), "rms": float(np.sqrt((e[ok] ** 2).mean())),
            "p99": float(np.percentile(e[ok], 99)), "flagged": float(1 - ok.sum() / v.sum()),
            "occluded_confident": float((c[~v] > 0.5).mean()) if (~v).any() else 0.0}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("actor")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--landmarks", type=int, default=1000)
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--presets", default="frontal,yaw30,turns")
    ap.add_argument("--quick", action="store_true", help="4 frames, 300 landmarks, 640x360")
    args = ap.parse_args()
    if args.quick:
        args.frames, args.landmarks, args.size = 4, 300, "640x360"
    size = tuple(int(x) for x in args.size.split("x"))
    torch.set_num_threads(1)
    print(f"{args.size}, {args.frames} frames, {args.landmarks} landmarks, 1 thread; errors in frame px")
    print("| preset | render+encode s/frame | detector s/frame | median | RMS (confident) | p99 (confident) "
          "| visible flagged | occluded confident |")
    print("|---|---|---|---|---|---|---|---|")
    for preset in args.presets.split(","):
        r = measure(args.actor, preset, args.frames, args.landmarks, size)
        print(f"| {preset} | {r['render_s']:.3f} | {r['detect_s']:.3f} | {r['median']:.3f} | {r['rms']:.3f} | "
              f"{r['p99']:.3f} | {100 * r['flagged']:.1f}% | {100 * r['occluded_confident']:.1f}% |", flush=True)


if __name__ == "__main__":
    main()
