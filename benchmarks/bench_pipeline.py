"""Whole ``capture run`` against the detector-only pass, 1 core against 2, start-up, and ``capture live``.

The take: ``capture synth`` of the bundled demo actor (1280x720, re-encoded as H.264 4:2:0 as a camera
records it, ``--source``; 468 landmarks embedded on the
actor). The detector: a MobileNet-sized network with random weights (192x192 RGB input, depthwise
separable convolutions, ~2.5 MB of float32 weights, 468 landmarks; :func:`mobilenet_detector`) whose
landmarks are a fixed face layout in the crop plus a small term of its random features, so that
tracking keeps a crop on the face and the fit sees a plausible face; its cost is that of a real one.

Measured in one run, interleaved (repeat r runs every configuration once before repeat r + 1), each in
a fresh child process on a fresh output folder so nothing is cached, without the shell's thread variables
(``OMP_NUM_THREADS``, ``OPENBLAS_NUM_THREADS``, ``MKL_NUM_THREADS``: until the twentieth round they were set to 1
here, which hid a spinning BLAS thread that a user's ``capture run`` had):

* ``detector only``: decode + detect of the whole take (``capture.detector.detect_video``, no cache), 2 cores,
  the native pools set as ``capture detect`` sets them;
* ``run 2 cores``: ``capture run --formats npz,usd`` (the default exports of the issue), both cores;
* ``run 1 core``: the same pinned to one core (``os.sched_setaffinity``);
* ``live N``: ``capture live`` on the take played at N frames/s (``--live-fps``, default its own 25 and a
  faster 30 and 40): frames fitted per second of the source (``fps_sustained``: N when nothing is dropped),
  frames dropped and why, lag, latency;
* start-up: ``capture --help``, and ``capture run`` from launch until ``run.json`` is written
  (inputs checked, the stages about to start).

Figures are frames per second over the child's whole wall time (start-up included); the median of the
repeats is printed with the machine's load (``uptime``), since the machine is shared.

A run costs a fixed ~1.7 s more than the detector-only pass (the fit process imports torch and kornia and builds
its networks; the report; the exit) on top of about 1 ms a frame, so the ratio of the two depends on the take's
length: 2.0x at 300 frames, 1.43x at 1,200 (BENCHMARKS.md). The default is a 40 s take of 1,200 frames; pass
``--frames 300`` to see a short take's.

    python benchmarks/bench_pipeline.py [--frames 1200] [--repeats 3] [--work DIR] [--quick]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

DEMO_ACTOR = REPO / "capture" / "data" / "demo_actor"
DET_NAME = "mobilenet468"
SIZE = 192
COUNT = 468


def mobilenet_detector(out_dir: Path, template_points: np.ndarray, margin: float = 0.25,
                       crop_px: float = 300.0, seed: int = 0) -> Path:
    """Write ``out_dir/mobilenet468.onnx`` + ``.json``: a MobileNet-v1-like net (width 0.5) with random weights.

    Output landmarks (crop px) = a frontal layout of ``template_points`` (L, 3) mm + 1e-3 x (random
    features -> linear). Tracking maps a crop of size ``s`` to one of ``slope * s + k`` (``k = 1 + 2
    margin``); the layout's span sets ``slope`` so that the fixed point is ``crop_px``. Convergence is
    slow, so in practice each 32-frame segment starts at the full frame and the crop shrinks a little
    over the segment: the fit sees a large, slowly receding face.
    """
    import torch
    from torch import nn

    from capture.detector.synthetic import detector_spec

    torch.manual_seed(seed)

    def dw(c_in, c_out, stride):
        return nn.Sequential(nn.Conv2d(c_in, c_in, 3, stride, 1, groups=c_in, bias=False), nn.BatchNorm2d(c_in),
                             nn.ReLU6(), nn.Conv2d(c_in, c_out, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU6())

    k = 1 + 2 * margin
    slope = 1 - k / crop_px                       # crop size s -> slope * s + k, fixed point crop_px
    p = np.asarray(template_points, np.float64)[:, :2] * [1, -1]        # frontal, y down
    p = (p - (p.min(0) + p.max(0)) / 2) / np.ptp(p, axis=0).max()       # unit box span, centred
    span = slope * SIZE / k - 1.0                 # landmark span in crop px for that slope (half-pixel boxes)
    layout = (SIZE - 1) / 2 + p * span

    class Net(nn.Module):
        def __init__(self):
            super().__init__()
            cfg = [(16, 32, 1), (32, 64, 2), (64, 64, 1), (64, 128, 2), (128, 128, 1), (128, 256, 2)] + \
                  [(256, 256, 1)] * 5
            self.stem = nn.Sequential(nn.Conv2d(3, 16, 3, 2, 1, bias=False), nn.BatchNorm2d(16), nn.ReLU6())
            self.body = nn.Sequential(*[dw(a, b, s) for a, b, s in cfg], nn.AvgPool2d(2))
            self.fc = nn.Linear(256, COUNT * 2)
            self.register_buffer("layout", torch.as_tensor(layout, dtype=torch.float32).reshape(-1))

        def forward(self, x):
            f = self.body(self.stem(x)).mean((2, 3))
            return (self.layout + 1e-3 * self.fc(f)).reshape(-1, COUNT, 2)

    net = Net().eval()
    for m in net.modules():          # random BN statistics, like a trained net's (not identity)
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1)
            m.running_var.uniform_(0.5, 1.5)
    out_dir.mkdir(parents=True, exist_ok=True)
    onnx_path = out_dir / f"{DET_NAME}.onnx"
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(net, (torch.zeros(1, 3, SIZE, SIZE),), str(onnx_path), dynamo=False, opset_version=17,
                          input_names=["image"], output_names=["landmarks"],
                          dynamic_axes={"image": {0: "N"}, "landmarks": {0: "N"}})
    spec = detector_spec(name=DET_NAME, count=COUNT, size=(SIZE, SIZE), first_frame="full_frame", margin=margin)
    (out_dir / f"{DET_NAME}.json").write_text(json.dumps(spec, indent=2))
    return onnx_path


def setup(work: Path, frames: int, size: str, source: str = "yuv420p") -> dict:
    """Actor (the demo actor + a 468-landmark embedding), take and detector in ``work`` (reused if there).

    ``source``: ``yuv420p`` (default) re-encodes the synthetic take as a camera records it (H.264 4:2:0, crf
    18, :func:`upscaled` at the take's own size); ``synth`` keeps ``capture synth``'s H.264 4:4:4, whose
    conversion to BGR costs OpenCV 3-4 ms a frame at 1280x720 where 4:2:0's costs 0.5-0.7 ms."""
    from capture.detector.embedding import embedded_points, parse_embedding, write_embedding

    actor, take, det = work / "actor", work / f"take_{frames}_{size}", work / "detector"
    if not actor.is_dir():
        shutil.copytree(DEMO_ACTOR, actor)
    if not (take / "take.mp4").is_file():
        cmd = [sys.executable, "-m", "capture.cli", "synth", "--actor", str(actor), "--out", str(take), "--frames",
               str(frames), "--size", size, "--landmarks", str(COUNT), "--codec", "h264", "--crf", "18",
               "--no-progress", "--overwrite"]
        r = subprocess.run(cmd, cwd=REPO, env=_env(), capture_output=True, text=True)
        if r.returncode:
            raise RuntimeError(f"capture synth failed: {r.stderr.strip()[-2000:]}")
    if not (det / f"{DET_NAME}.onnx").is_file():
        import trimesh

        template = trimesh.load(actor / "template.ply", process=False)
        src = json.loads((actor / "landmarks" / f"synthetic_dense_{COUNT}.json").read_text())
        src["detector"] = DET_NAME
        emb = parse_embedding(src)
        write_embedding(actor, emb, template)
        mobilenet_detector(det, embedded_points(emb, template))
    video = take / "take.mp4"
    if source == "yuv420p":
        video = upscaled(video, take / "take_yuv420p.mp4", tuple(int(x) for x in size.split("x")), 1)
    elif source != "synth":
        raise ValueError(f"--source must be yuv420p or synth, got {source!r}")
    return {"actor": actor, "video": video, "camera": take / "camera.json", "detector": det / f"{DET_NAME}.onnx"}


#: thread variables a shell may carry; the children run without them, as in a user's fresh shell, so that the
#: figures are those of the product's own thread settings (:mod:`capture.io.threads`)
THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _env() -> dict:
    env = {k: v for k, v in os.environ.items() if k not in THREAD_VARIABLES}
    env["PYTHONPATH"] = str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")
    return env


def tree_pss_mb(pid: int) -> float | None:
    """Proportional set size (MB) of process ``pid`` and all its descendants, from Linux' ``smaps_rollup``;
    None where /proc does not have it. Unlike the peak RSS of ``wait4``, which is that of the largest single
    process, this is what the run and its fit process hold together, pages they share (the fork's
    copy-on-write pages, libraries) counted once."""
    total, stack, seen = 0, [pid], False
    while stack:
        p = stack.pop()
        try:
            with open(f"/proc/{p}/smaps_rollup") as f:
                total += next(int(line.split()[1]) for line in f if line.startswith("Pss:"))
            seen = True
            for task in os.listdir(f"/proc/{p}/task"):
                with open(f"/proc/{p}/task/{task}/children") as f:
                    stack.extend(int(c) for c in f.read().split())
        except (OSError, StopIteration, ValueError):   # gone meanwhile, or no such file on this system
            continue
    return total / 1024 if seen else None


def _child(cmd: list[str], cores: set[int] | None, watch: Path | None = None, pss_every_s: float = 0.0) -> dict:
    """Run ``cmd``; wall seconds, and the seconds until ``watch`` exists (polled every 5 ms). With
    ``pss_every_s`` > 0 also ``peak_pss_mb``: the largest :func:`tree_pss_mb` sampled that often."""
    pre = (lambda: os.sched_setaffinity(0, cores)) if cores else None
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=REPO, env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=pre)
    seen, peak_pss, next_pss = None, None, 0.0
    import threading

    pipes = {}
    readers = [threading.Thread(target=lambda k=k, f=f: pipes.__setitem__(k, f.read()), daemon=True)
               for k, f in (("out", proc.stdout), ("err", proc.stderr))]
    for t in readers:                                # drain the pipes while we wait (wait4 reaps the child)
        t.start()
    while True:
        if watch is not None and seen is None and watch.exists():
            seen = time.perf_counter() - t0
        if pss_every_s > 0 and time.perf_counter() >= next_pss:
            pss = tree_pss_mb(proc.pid)
            if pss is not None:
                peak_pss = pss if peak_pss is None else max(peak_pss, pss)
            next_pss = time.perf_counter() + pss_every_s
        pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
        if pid:
            break
        time.sleep(0.005)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    for t in readers:
        t.join()
    out, err = pipes.get("out", ""), pipes.get("err", "")
    if proc.returncode:
        raise RuntimeError(f"{' '.join(cmd[:4])} failed ({proc.returncode}): {err.strip()[-2000:]}")
    return {"wall_s": wall, "watch_s": seen, "stdout": out, "stderr": err, "peak_rss_mb": usage.ru_maxrss / 1024,
            "peak_pss_mb": peak_pss}


def upscaled(video: Path, out: Path, size: tuple[int, int], repeat: int) -> Path:
    """``video`` resized to ``size`` and played ``repeat`` times in a row (H.264 via PyAV): a longer 1080p take.

    Frame by frame: this process must stay small, since a child forked from it inherits its resident size
    until it executes ``capture`` (Linux's ``ru_maxrss`` of the child keeps that mark: holding the take's
    1080p frames here once made ``--memory`` report 2.25 GB for a run that peaked at 0.7 GB)."""
    if out.is_file():
        return out
    import av
    import cv2

    from capture.io.video import VideoReader

    with VideoReader(video) as r:
        fps = r.info.fps
    tmp = out.with_suffix(".part.mp4")
    with av.open(str(tmp), "w") as c:
        st = c.add_stream("libx264", rate=int(round(fps)))
        st.width, st.height, st.pix_fmt = size[0], size[1], "yuv420p"
        st.options = {"crf": "18"}
        for _ in range(repeat):
            with VideoReader(video) as r:
                for _, f in r.frames():
                    f = cv2.resize(f, size, interpolation=cv2.INTER_LINEAR)
                    for pkt in st.encode(av.VideoFrame.from_ndarray(f, format="bgr24")):
                        c.mux(pkt)
        for pkt in st.encode():
            c.mux(pkt)
    tmp.rename(out)
    return out


DETECT_ONLY = """
import sys, time, json
from capture.detector import Detector, detect_video
from capture.io.threads import limit_native_pools
limit_native_pools(int(sys.argv[3]))    # the pools as capture detect and capture run set them
det = Detector.load(sys.argv[2], threads=int(sys.argv[3]))
t0 = time.perf_counter()
tr = detect_video(sys.argv[1], det, None, progress=False)
print(json.dumps({"frames": len(tr), "detect_s": time.perf_counter() - t0}))
"""


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1200,
                    help="take length (default 1200: 40 s); a run's fixed start and end costs weigh more on short "
                         "takes (BENCHMARKS.md)")
    ap.add_argument("--size", default="1280x720")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--lag", type=int, default=5, help="capture live --lag")
    ap.add_argument("--work", help="folder kept between runs (take, actor, detector); default: a temporary one")
    ap.add_argument("--out", default=str(REPO / "benchmarks" / "results"))
    ap.add_argument("--no-live", action="store_true")
    ap.add_argument("--live-fps", default="25,30,40", help="paces of capture live's file source (frames/s)")
    ap.add_argument("--memory", action="store_true", help="only: peak memory of capture run at 1920x1080 (by "
                    "default all exports but the overlay) on the take and on it played 4 times")
    ap.add_argument("--formats", help="capture run --formats (default npz,usd; with --memory obj,usd,npz); "
                    "capture run's own default is obj,usd,npz,overlay")
    ap.add_argument("--quick", action="store_true", help="check that it runs: 24 frames at 320x240, 1 repeat")
    ap.add_argument("--source", default="yuv420p", choices=("yuv420p", "synth"),
                    help="the video: the synthetic take re-encoded in 4:2:0 as cameras record (default), or "
                         "capture synth's own 4:4:4 H.264")
    args = ap.parse_args(argv)
    if args.quick:
        args.frames, args.size, args.repeats, args.live_fps = 24, "320x240", 1, "25"
    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory()
        work = Path(tmp.name)
    else:
        work = Path(args.work)
        work.mkdir(parents=True, exist_ok=True)
    try:
        return _measure(args, work)
    finally:
        if tmp is not None:
            tmp.cleanup()


def _measure(args, work: Path) -> dict:
    from capture.io.atomic import write_text

    s = setup(work, args.frames, args.size, args.source)
    py = sys.executable
    if args.memory:
        return _memory(s, work, args.formats or "obj,usd,npz")
    both = set(range(min(2, os.cpu_count() or 1)))
    rows: dict[str, list] = {}

    def run_cmd(out: Path) -> list[str]:
        return [py, "-m", "capture.cli", "run", str(s["video"]), "--actor", str(s["actor"]), "--camera",
                str(s["camera"]), "--detector", str(s["detector"]), "--formats", args.formats or "npz,usd",
                "--out", str(out),
                "--no-progress", "--overwrite"]

    loads = [os.getloadavg()]
    for r in range(args.repeats):
        res = _child([py, "-c", DETECT_ONLY, str(s["video"]), str(s["detector"]), "1"], both)
        d = json.loads(res["stdout"].strip().splitlines()[-1])
        rows.setdefault("detector only", []).append({"wall_s": res["wall_s"], "frames": d["frames"],
                                                     "inner_s": d["detect_s"]})
        for name, cores in (("run 2 cores", both), ("run 1 core", {0})):
            out = work / f"run_{r}_{name.replace(' ', '_')}"
            shutil.rmtree(out, ignore_errors=True)
            res = _child(run_cmd(out), cores, watch=out / "run.json")
            rep = json.loads((out / "report.json").read_text())
            detect = next(st for st in rep["stages"] if st["stage"] == "detect")
            rows.setdefault(name, []).append({"wall_s": res["wall_s"], "frames": rep["frames"]["requested"],
                                              "peak_rss_mb": res["peak_rss_mb"], "peak_pss_mb": res["peak_pss_mb"],
                                              "fit_process_peak_rss_mb": _fit_peak(rep),
                                              "inner_s": rep["seconds_total"], "start_s": res["watch_s"],
                                              "stages": {st["stage"]: round(st["seconds"], 2) for st in rep["stages"]},
                                              "frame_buffers": detect.get("frame_buffers"),
                                              # the fit cache's frames (beside them, once: the mesh basis)
                                              "fit_chunks_mb": sum(f.stat().st_size for f in
                                                                   out.glob("fit/*/frames_*.npz")) / 2**20})
            shutil.rmtree(out, ignore_errors=True)
        for pace in ([] if args.no_live else [float(x) for x in args.live_fps.split(",")]):
            out = work / f"live_{r}"
            shutil.rmtree(out, ignore_errors=True)
            res = _child([py, "-m", "capture.cli", "live", str(s["video"]), "--actor", str(s["actor"]), "--camera",
                          str(s["camera"]), "--detector", str(s["detector"]), "--lag", str(args.lag), "--out",
                          str(out), "--json", "none", "--no-progress", "--fps", f"{pace:g}"], both)
            rep = json.loads((out / "live.json").read_text())
            rows.setdefault(f"live {pace:g}", []).append({
                "wall_s": res["wall_s"], "frames": rep["frames"]["received"], "inner_s": rep["seconds"],
                "fps": rep["fps_sustained"], "fps_whole_run": rep["fps_processed"], "dropped": rep["frames"]["dropped"],
                "dropped_why": rep["frames"]["dropped_why"], "max_lag": rep["lag"]["max_frames"],
                "latency_median_s": rep["latency_s"]["median"], "latency_p95_s": rep["latency_s"]["p95"]})
            shutil.rmtree(out, ignore_errors=True)
        t0 = time.perf_counter()
        _child([py, "-m", "capture.cli", "--help"], both)
        rows.setdefault("capture --help", []).append({"wall_s": time.perf_counter() - t0, "frames": 0})
        loads.append(os.getloadavg())

    # memory in a run of its own: reading /proc/PID/smaps_rollup every 0.5 s walks the run's page tables under its
    # mmap lock, which slowed the timed runs by 0-2 s (of 10.5-13 s) on a machine where page faults were costly
    out = work / "run_memory"
    shutil.rmtree(out, ignore_errors=True)
    res = _child(run_cmd(out), both, pss_every_s=0.5)
    rows["run 2 cores, memory sampled"] = [{"wall_s": res["wall_s"], "peak_rss_mb": res["peak_rss_mb"],
                                            "peak_pss_mb": res["peak_pss_mb"],
                                            "fit_process_peak_rss_mb": _fit_peak(json.loads((out / "report.json").read_text()))}]
    shutil.rmtree(out, ignore_errors=True)

    def med(name, key="wall_s"):
        v = [x[key] for x in rows[name] if x.get(key) is not None]
        return float(np.median(v)) if v else float("nan")

    n = rows["run 2 cores"][0]["frames"]
    summary = {
        "frames": n, "size": args.size, "source": args.source, "repeats": args.repeats, "loadavg": loads,
        "detector_only_fps": n / med("detector only"),
        "run_2_cores_fps": n / med("run 2 cores"), "run_1_core_fps": n / med("run 1 core"),
        "run_over_detector_only": med("run 2 cores") / med("detector only"),
        "two_over_one_core": med("run 1 core") / med("run 2 cores"),
        "run_start_s": med("run 2 cores", "start_s"), "help_s": med("capture --help"),
        "run_peak_rss_mb": max(x["peak_rss_mb"] for x in rows["run 2 cores"]),
        "fit_process_peak_rss_mb": max((x["fit_process_peak_rss_mb"] or 0.0) for x in rows["run 2 cores"]),
        "run_peak_pss_mb": rows["run 2 cores, memory sampled"][0]["peak_pss_mb"],   # both processes
    }
    for name in [k for k in rows if k.startswith("live ")]:
        key = name.replace(" ", "_")
        summary.update({f"{key}_fps_sustained": med(name, "fps"), f"{key}_dropped": [x["dropped"] for x in rows[name]],
                        f"{key}_max_lag": max(x["max_lag"] for x in rows[name]),
                        f"{key}_latency_p95_s": med(name, "latency_p95_s")})
    print(f"{n} frames {args.size} ({args.source}), {args.repeats} interleaved repeats (medians); load average before/after: "
          f"{loads[0][0]:.2f} / {loads[-1][0]:.2f}")
    for name, v in rows.items():
        print(f"  {name:15s} " + "  ".join(f"{x['wall_s']:.2f}s" for x in v) +
              (f"   stages {v[-1]['stages']}" if "stages" in v[-1] else ""))
    for k, v in summary.items():
        if k != "loadavg":
            print(f"  {k}: {v if isinstance(v, (str, int, list)) else round(v, 3)}")
    out = Path(args.out)
    if not args.quick:
        write_text(out / "pipeline.json", json.dumps({"summary": summary, "rows": rows}, indent=2))
    return {"summary": summary, "rows": rows}


def _fit_peak(report: dict) -> float | None:
    """Peak RSS (MB) of the run's fit process, from its report (None when the fit ran in the run's process)."""
    return next((st.get("peak_rss_mb") for st in report["stages"] if st["stage"] == "fit"), None)


def _memory(s: dict, work: Path, formats: str) -> dict:
    rows = []
    for repeat in (1, 4):
        video = upscaled(s["video"], work / f"take_1080p_x{repeat}.mp4", (1920, 1080), repeat)
        out = work / f"mem_{repeat}"
        shutil.rmtree(out, ignore_errors=True)
        res = _child([sys.executable, "-m", "capture.cli", "run", str(video), "--actor", str(s["actor"]), "--camera",
                      str(s["camera"]), "--detector", str(s["detector"]), "--formats", formats, "--out",
                      str(out), "--no-progress", "--overwrite"], None, pss_every_s=0.5)
        rep = json.loads((out / "report.json").read_text())
        rows.append({"frames": rep["frames"]["requested"], "formats": formats, "peak_rss_mb": res["peak_rss_mb"],
                     "peak_pss_mb": res["peak_pss_mb"], "wall_s": res["wall_s"],
                     "fit_process_peak_rss_mb": _fit_peak(rep)})
        together = "n/a" if res["peak_pss_mb"] is None else f"{res['peak_pss_mb']:.0f} MB"
        print(f"  1920x1080, {rows[-1]['frames']} frames, {formats}: both processes together {together} (peak of "
              f"their PSS, sampled every 0.5 s); peak RSS {res['peak_rss_mb']:.0f} MB (the larger of the run's "
              f"process and its fit process; the fit process alone {_fit_peak(rep) or 0:.0f} MB), "
              f"{res['wall_s']:.1f} s (load average {os.getloadavg()[0]:.1f})")
        shutil.rmtree(out, ignore_errors=True)
    return {"memory": rows}


if __name__ == "__main__":
    main()
