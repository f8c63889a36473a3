"""Render and detector speed of ``capture synth`` at 1280x720 (prints seconds per frame).

Usage: python benchmarks/bench_synth.py ACTOR [--frames 20] [--landmarks 1000]
(e.g. an actor from ``capture actor train sample --sample --iterations 300 --width 128``).
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


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("actor")
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--landmarks", type=int, default=1000)
    args = ap.parse_args()
    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "take"
        synthesize(SynthConfig(actor=args.actor, out=out, frames=args.frames, preset="turns", landmarks=args.landmarks))
        report = json.loads((out / "truth.json").read_text())
        print(f"render+encode 1280x720: {report['timings']['render_per_frame_s']:.3f} s/frame "
              f"({report['settings']['codec']}), total {report['timings']['total_s']:.1f} s for {args.frames} frames")
        so = ort.SessionOptions()
        so.intra_op_num_threads = 1
        sess = ort.InferenceSession(str(out / report["detector"]["onnx"]), so)
        S = json.loads((out / report["detector"]["spec"]).read_text())["input"]["size"][0]
        lms = np.load(out / "truth_landmarks.npz")
        times, errs = [], []
        for j, frame in enumerate(read_frames(out / "take.mp4")):
            p, v = lms["points_2d"][j], lms["visible"][j]
            crop, M = square_crop(frame, (*p[v].min(0), *p[v].max(0)), 0.25, S)
            t0 = time.perf_counter()
            pts, conf, _ = sess.run(None, {"image": crop.transpose(2, 0, 1)[None].astype(np.float32)})
            times.append(time.perf_counter() - t0)
            e = np.linalg.norm((pts[0] - M[:, 2]) / M[0, 0] - p, axis=1)
            errs.append(e[v & (conf[0] > 0.5)])
        e = np.concatenate(errs)
        print(f"detector ({args.landmarks} landmarks, {S}x{S}, 1 thread): {np.median(times):.3f} s/frame; "
              f"confident visible error median {np.median(e):.3f} px, RMS {np.sqrt((e ** 2).mean()):.3f} px")


if __name__ == "__main__":
    main()
