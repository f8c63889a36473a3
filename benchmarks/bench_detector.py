"""Detector throughput on this machine: frames per second with and without batching.

A synthetic ONNX landmark network of realistic cost (four stages of a stride-2 and a stride-1 3x3
convolution, 32->64->128->256 channels, on a 256x256 RGB crop, global pooling, a linear layer to 68
landmarks; ~1.7 GFLOP per frame, like a small real landmark network) runs on
real GRID clips (360x288, Haar face finder on the first frame of each segment, then tracking).

    python benchmarks/bench_detector.py [--clips 2] [--threads 2] [--batches 1,4,8]

Prints, per batch size, the best of ``--repeats`` runs: the model alone (session.run on prepared
inputs) and the whole video path (decode, Haar, crop, preprocess, model, map back; no cache).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from capture.detector import Detector, TrackOptions, detect_video  # noqa: E402
from capture.detector import synthetic as S  # noqa: E402
from benchmarks.assets import GRID_CLIPS  # noqa: E402

GRID = GRID_CLIPS     # benchmarks.assets: $CAPTURE_SHARED_ASSETS or ../shared/assets


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--clips", type=int, default=2, help="GRID clips to run (75 frames each)")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads")
    ap.add_argument("--batches", default="1,4,8", help="batch sizes (segments side by side)")
    ap.add_argument("--segment", type=int, default=32, help="frames per tracking segment")
    ap.add_argument("--repeats", type=int, default=3, help="runs per setting; the best is printed")
    args = ap.parse_args()
    batches = [int(b) for b in args.batches.split(",")]
    clips = sorted(GRID.glob("*.mpg"))[: args.clips]
    if not clips:
        raise SystemExit(f"no clips in {GRID}")

    with tempfile.TemporaryDirectory() as d:
        spec = S.detector_spec(name="bench68", count=68, size=(256, 256), first_frame="haar", margin=0.2)
        model = S.conv_model(size=(256, 256), count=68, widths=(32, 64, 128, 256), repeats=1)
        path = S.save_detector(model, spec, d, "bench68")
        det = Detector.load(path, threads=args.threads, options=TrackOptions(segment=args.segment))

        print(f"synthetic 68-landmark conv net, 256x256 input, {args.threads} onnxruntime threads, "
              f"{len(clips)} GRID clip(s) x 75 frames, segments of {args.segment} frames")
        print(f"{'batch':>5} | {'model only fps':>14} | {'video path fps':>14} | model calls")
        rng = np.random.default_rng(0)
        for b in batches:
            x = rng.random((b, 3, 256, 256), dtype=np.float32)
            det.session.run(None, {"image": x})  # warm up
            model_fps = video_fps = 0.0
            for _ in range(args.repeats):  # best of: the machine is shared
                n, t0 = 0, time.perf_counter()
                while time.perf_counter() - t0 < 1.0:
                    det.session.run(None, {"image": x})
                    n += b
                model_fps = max(model_fps, n / (time.perf_counter() - t0))

                det.model_calls = 0
                frames, t0 = 0, time.perf_counter()
                for clip in clips:
                    tr = detect_video(clip, det, None, progress=False, batch=b)
                    frames += len(tr)
                video_fps = max(video_fps, frames / (time.perf_counter() - t0))
            print(f"{b:>5} | {model_fps:>14.1f} | {video_fps:>14.1f} | {det.model_calls}")


if __name__ == "__main__":
    main()
