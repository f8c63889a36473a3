"""Overlay speed: milliseconds per frame to draw and to encode ``overlay.mp4`` at 720p and 1080p (and 4K).

The bundled demo actor (9,409 vertices, 18,460 triangles) is posed frame by frame (head turning, jaw and
expressions moving), seen by a 60-degree camera with the face filling 70 % of the frame height, over a
textured background, with 468 detected landmarks (a MediaPipe-sized set) 0.7 px off the fit. Timed per
frame, one thread:

* ``draw``: :class:`capture.export.overlay_draw.FrameRenderer` with the default layers (shaded mesh by
  the project's rasteriser, contours, landmarks, header), and with ``wireframe,contours,header``;
* ``draw, 2 threads``: the default layers drawn by two threads, as ``OverlayWriter`` does (frames per
  second of both, as ms per frame);
* ``baseline``: the overlay shipped before issue 18 (every triangle edge of the front-facing mesh
  blended orange, each landmark a green disk), a plain reference in the same run;
* ``encode``: PyAV libx264 ``veryfast`` yuv420p, as the writer does.

Run (prints a table and writes ``benchmarks/out/overlay.json``)::

    /work/venv/bin/python benchmarks/bench_overlay.py [--frames 20] [--sizes 1280x720,1920x1080] [--quick]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEMO = Path(__file__).resolve().parents[1] / "capture" / "data" / "demo_actor"


class _Fit:
    def __init__(self, frame, vertices, landmarks_fit):
        self.frame, self.vertices, self.landmarks_fit = frame, vertices, landmarks_fit
        self.status, self.reprojection_rms_px = "fitted", 0.7


class _Det:
    def __init__(self, points, confidence):
        self.points, self.confidence, self.face_found = points, confidence, True


def take(size: tuple[int, int], frames: int, rig, n_landmarks: int = 468, seed: int = 0):
    """Frames (BGR), fits and detections of a posed demo actor at ``size``."""
    import cv2
    from scipy.spatial.transform import Rotation

    from calib.camera import Camera
    from capture.export.overlay_draw import project
    from capture.export.rig import R_FRONT, base_vertices

    w, h = size
    f = 0.5 * w / np.tan(np.deg2rad(30.0))
    cam = Camera(K=[[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1]], dist=[], image_size=(w, h))
    height = np.ptp(rig.neutral[:, 1])
    dist = f * height / (0.7 * h)
    centre = 0.5 * (rig.neutral.min(0) + rig.neutral.max(0))
    rng = np.random.default_rng(seed)
    lm_ids = rng.choice(rig.n_vertices, n_landmarks, replace=False)
    noise = cv2.resize(rng.integers(30, 160, (h // 16 + 1, w // 16 + 1, 3)).astype(np.uint8), (w, h),
                       interpolation=cv2.INTER_CUBIC)
    names = list(rig.names)
    out = []
    for j in range(frames):
        R = R_FRONT @ Rotation.from_euler("ZYX", [3 * np.sin(j / 7), 20 * np.sin(j / 11), -5], degrees=True).as_matrix()
        t = np.array([0.0, 0.0, dist]) - R @ centre
        wts = np.zeros(len(names))
        if "jawOpen" in names:
            wts[names.index("jawOpen")] = 0.5 + 0.5 * np.sin(j / 3)
        jaw = Rotation.from_euler("x", -8 * (0.5 + 0.5 * np.sin(j / 3)), degrees=True).as_matrix()
        v = base_vertices(rig, R, t, jaw, np.zeros(3), wts).astype(np.float32)
        lm_fit = project(v[lm_ids], cam)
        det = lm_fit + rng.normal(0, 0.5, lm_fit.shape)
        out.append((noise, _Fit(j, v, lm_fit), _Det(det, rng.uniform(0.3, 1.0, n_landmarks))))
    return cam, out


def baseline_draw(img, fit, det, faces, edges, face_edges, cam):
    """The overlay before issue 18: orange wireframe of front-facing triangles at 50 %, green landmark disks."""
    import cv2

    from capture.export.overlay_draw import project

    out = img.copy()
    layer = out.copy()
    v = fit.vertices
    px = project(v, cam)
    tri = v[faces].astype(np.float64)
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    front = np.einsum("ij,ij->i", normal, tri.mean(1)) < 0
    eids = np.unique(face_edges[front])
    segs = np.round(px[edges[eids]] * 16).astype(np.int32)
    cv2.polylines(layer, list(segs), False, (0, 140, 255), 1, cv2.LINE_AA, 4)
    cv2.addWeighted(layer, 0.5, out, 0.5, 0, dst=out)
    for (x, y), c in zip(det.points, det.confidence):
        cv2.circle(out, (int(round(x * 16)), int(round(y * 16))), int(round((1 + 3 * c) * 16)), (80, 220, 60), -1,
                   cv2.LINE_AA, 4)
    return out


def bench_size(size, frames, rig, faces, features) -> dict:
    import av

    from capture.export.overlay_draw import FrameRenderer, Topology

    cam, data = take(size, frames, rig)
    topo = Topology.of(faces, features)
    res = {"size": f"{size[0]}x{size[1]}", "frames": frames}
    for name, layers in (("draw_default_ms", ("mesh", "contours", "landmarks", "header")),
                         ("draw_wireframe_ms", ("wireframe", "contours", "header"))):
        ren = FrameRenderer(topo, cam, size, 25.0, layers)
        ren.render(*[data[0][i] for i in (0, 1, 2)], data[0][1].vertices)   # warm-up
        t = time.perf_counter()
        for img, fit, det in data:
            last = ren.render(img, fit, det, fit.vertices)
        res[name] = 1000 * (time.perf_counter() - t) / frames
        if name == "draw_default_ms":
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(2) as pool:
                t = time.perf_counter()
                list(pool.map(lambda d: ren.render(d[0], d[1], d[2], d[1].vertices), data))
                res["draw_default_2_threads_ms"] = 1000 * (time.perf_counter() - t) / frames
    t = time.perf_counter()
    for img, fit, det in data:
        baseline_draw(img, fit, det, topo.faces, topo.edges, topo.face_edges, cam)
    res["baseline_draw_ms"] = 1000 * (time.perf_counter() - t) / frames
    import io

    buf = io.BytesIO()
    with av.open(buf, mode="w", format="mp4") as c:
        s = c.add_stream("libx264", rate=25)
        s.width, s.height, s.pix_fmt = size[0], size[1], "yuv420p"
        s.options = {"crf": "23", "preset": "veryfast", "threads": "1"}
        t = time.perf_counter()
        for img, fit, det in data:
            for p in s.encode(av.VideoFrame.from_ndarray(last, format="bgr24")):
                c.mux(p)
        for p in s.encode():
            c.mux(p)
        res["encode_ms"] = 1000 * (time.perf_counter() - t) / frames
    return res


def main(argv=None) -> dict:
    import os

    import torch

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--sizes", default="1280x720,1920x1080")
    ap.add_argument("--quick", action="store_true", help="3 frames at 640x360 (a smoke run)")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "out"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    import cv2

    cv2.setNumThreads(1)
    from capture.actor.package import load_actor
    from capture.export.features import face_features
    from capture.export.rig import FaceRig

    actor = load_actor(str(DEMO))
    rig = FaceRig.from_actor(actor)
    faces = np.asarray(actor.template.faces)
    features = face_features(faces, np.asarray(actor.template.vertices), rig.expressions, rig.names)
    sizes = ["640x360"] if args.quick else args.sizes.split(",")
    frames = 3 if args.quick else args.frames
    rows = [bench_size(tuple(int(x) for x in s.split("x")), frames, rig, faces, features) for s in sizes]
    load = os.getloadavg()
    print(f"overlay, ms per frame (one thread; load average {load[0]:.1f} on {os.cpu_count()} cores)")
    print(f"{'size':>10} {'draw default':>13} {'2 threads':>10} {'draw wireframe':>15} {'baseline draw':>14} "
          f"{'encode':>8}")
    for r in rows:
        print(f"{r['size']:>10} {r['draw_default_ms']:13.1f} {r['draw_default_2_threads_ms']:10.1f} "
              f"{r['draw_wireframe_ms']:15.1f} {r['baseline_draw_ms']:14.1f} {r['encode_ms']:8.1f}")
    result = {"rows": rows, "load_average": load[0], "cpus": os.cpu_count()}
    if not args.quick:
        from capture.io.atomic import write_text

        Path(args.out).mkdir(parents=True, exist_ok=True)
        write_text(Path(args.out) / "overlay.json", json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
