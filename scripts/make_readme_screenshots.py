"""The README's screenshots of the overlay and of report.html (docs/images/*.png), made from a real run.

Steps (about two minutes on 2 CPU cores; everything in a work folder, default /tmp/capture_screenshots):

1. the bundled demo actor renders a synthetic take (``capture synth --look``, 640x360, preset ``talk``);
2. ``capture run`` fits it (``--formats npz,overlay,curves``), which writes ``overlay.mp4`` and ``report.html``;
3. ``docs/images/overlay_360p.png``: one frame drawn by the overlay (default layers) over the take's
   *look* video (the same frames Lambert-shaded for people; ``overlay.mp4`` itself is drawn over the
   colour-coded frames the synthetic detector reads, which tell a reader nothing);
4. ``docs/images/overlay_4k_detail.png``: the same frame drawn at 3840x2160 (frame upscaled, camera
   and landmarks scaled by 6), a 900x600 crop around the left eye at full resolution: line widths,
   dots and the header scale with the frame, so 4K reads like 720p;
5. ``docs/images/overlay_wireframe.png``: ``--overlay wireframe,contours,header``;
6. ``docs/images/report.png``: the top of ``report.html`` (its embedded figures, taken out of the page
   and stacked under a title line; no browser is needed).

Run:  /work/venv/bin/python scripts/make_readme_screenshots.py [--work DIR] [--frame 37]
"""

from __future__ import annotations

import argparse
import base64
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def sh(*args: str) -> None:
    print("+ capture", " ".join(args))
    subprocess.run([sys.executable, "-m", "capture.cli", *args], check=True, cwd=ROOT)


def main() -> None:
    import cv2

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--work", default="/tmp/capture_screenshots")
    ap.add_argument("--frame", type=int, default=37)
    ap.add_argument("--out", default=str(ROOT / "docs" / "images"))
    args = ap.parse_args()
    work, out = Path(args.work), Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    actor = work / "actor"
    if not actor.is_dir():
        shutil.copytree(ROOT / "capture" / "data" / "demo_actor", actor)
    take = work / "take"
    if not (take / "take_look.mp4").is_file():
        sh("synth", "--actor", str(actor), "--out", str(take), "--frames", "60", "--size", "640x360", "--preset",
           "talk", "--landmarks", "300", "--look", "--overwrite", "--no-progress")
    run = work / "run"
    sh("run", str(take / "take.mp4"), "--actor", str(actor), "--camera", str(take / "camera.json"), "--out", str(run),
       "--formats", "npz,overlay,curves", "--no-progress")

    from calib.camera import Camera
    from calib.camera_io import read_camera
    from capture.actor.package import load_actor
    from capture.detector import LandmarkTrack
    from capture.export.features import face_features
    from capture.export.overlay_draw import FrameRenderer, Topology
    from capture.export.rig import FaceRig
    from capture.io.video import VideoReader
    from capture.run.stages import iter_fits
    from capture.run.take import Detection

    a = load_actor(str(actor))
    rig = FaceRig.from_actor(a)
    faces = np.asarray(a.template.faces)
    topo = Topology.of(faces, face_features(faces, np.asarray(a.template.vertices), rig.expressions, rig.names))
    cam = read_camera(take / "camera.json")
    track = LandmarkTrack.load_npz(run / "detections" / "track.npz")
    fit_dir = next(p for p in (run / "fit").iterdir() if p.is_dir())
    fit = next(f for f in iter_fits(fit_dir) if int(f.frame) == args.frame)
    j = list(track.frame_index).index(args.frame)
    det = Detection(track.points[j], None if track.confidence is None else track.confidence[j],
                    bool(track.face_found[j]))
    with VideoReader(take / "take_look.mp4") as reader:
        img = dict(reader.frames([args.frame]))[args.frame]
    default = ("mesh", "contours", "landmarks", "header")
    frame360 = FrameRenderer(topo, cam, cam.image_size, 25.0, default).render(img, fit, det, fit.vertices)
    cv2.imwrite(str(out / "overlay_360p.png"), frame360, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    wire = FrameRenderer(topo, cam, cam.image_size, 25.0, ("wireframe", "contours", "header"))
    cv2.imwrite(str(out / "overlay_wireframe.png"), wire.render(img, fit, det, fit.vertices),
                [cv2.IMWRITE_PNG_COMPRESSION, 9])

    s = 6                                                   # 640x360 -> 3840x2160
    K = np.array(cam.K, float)
    K4 = K.copy()
    K4[:2, :2] *= s
    K4[:2, 2] = (K[:2, 2] + 0.5) * s - 0.5                  # pixel centres at integers
    cam4 = Camera(K=K4, dist=cam.dist, image_size=(640 * s, 360 * s))
    img4 = cv2.resize(img, (640 * s, 360 * s), interpolation=cv2.INTER_CUBIC)

    class Scaled:
        def __init__(self, f):
            self.__dict__.update(f.__dict__)
            self.landmarks_fit = (np.asarray(f.landmarks_fit) + 0.5) * s - 0.5

    det4 = Detection((det.points + 0.5) * s - 0.5, det.confidence, det.face_found)
    frame4k = FrameRenderer(topo, cam4, cam4.image_size, 25.0, default).render(img4, Scaled(fit), det4, fit.vertices)
    eye = fit.vertices[topo.features.openings[1]] if len(topo.features.openings) > 1 else fit.vertices
    from capture.export.overlay_draw import project

    cx, cy = project(eye, cam4).mean(0).astype(int)
    x0, y0 = int(np.clip(cx - 450, 0, 3840 - 900)), int(np.clip(cy - 300, 0, 2160 - 600))
    cv2.imwrite(str(out / "overlay_4k_detail.png"), frame4k[y0:y0 + 600, x0:x0 + 900], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    header = frame4k[:110, :1800]
    cv2.imwrite(str(out / "overlay_4k_header.png"), cv2.resize(header, (900, 55), interpolation=cv2.INTER_AREA),
                [cv2.IMWRITE_PNG_COMPRESSION, 9])

    page = (run / "report.html").read_text()
    pngs = [cv2.imdecode(np.frombuffer(base64.b64decode(b), np.uint8), cv2.IMREAD_COLOR)
            for b in re.findall(r"src='data:image/png;base64,([^']+)'", page)]
    titles = re.findall(r"<h2>([^<]+)</h2>", page)
    width = max(p.shape[1] for p in pngs[:5])
    parts = []
    for t, p in list(zip(titles, pngs))[:5]:
        band = np.full((30, width, 3), 255, np.uint8)
        cv2.putText(band, t, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (40, 40, 40), 1, cv2.LINE_AA)
        pad = np.full((p.shape[0], width - p.shape[1], 3), 255, np.uint8)
        parts += [band, np.hstack([p, pad])]
    thumbs = [p for p in pngs[5:9]]
    if thumbs:
        h = min(t.shape[0] for t in thumbs)
        row = np.hstack([cv2.resize(t, (int(t.shape[1] * h / t.shape[0]), h)) for t in thumbs])
        row = row[:, :width] if row.shape[1] > width else np.hstack(
            [row, np.full((h, width - row.shape[1], 3), 255, np.uint8)])
        band = np.full((30, width, 3), 255, np.uint8)
        cv2.putText(band, "Worst frames", (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (40, 40, 40), 1, cv2.LINE_AA)
        parts += [band, row]
    sheet = np.vstack(parts)
    sheet = cv2.resize(sheet, (760, int(sheet.shape[0] * 760 / sheet.shape[1])), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(out / "report.png"), sheet, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    from PIL import Image

    # a 256-colour palette keeps the report's picture small (the overlays keep full colour: a palette
    # loses the few red pixels of the colour key)
    Image.open(out / "report.png").convert("RGB").quantize(colors=256, method=Image.Quantize.FASTOCTREE,
                                                           dither=Image.Dither.NONE).save(out / "report.png",
                                                                                          optimize=True)
    for p in sorted(out.glob("*.png")):
        print(f"{p.relative_to(ROOT)}: {p.stat().st_size // 1024} KB")


if __name__ == "__main__":
    main()
