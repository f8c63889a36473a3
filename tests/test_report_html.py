"""report.html and the shoot page: series against hand-computed values, a self-contained page, relative links."""

from __future__ import annotations

import base64
import re
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace

import cv2
import numpy as np
import pytest

from capture.export.report_html import (confidence_stats, figures, flag_spans, render_html, shoot_html, take_series,
                                        worst_frames)
from capture.export.rig import R_FRONT


@dataclass
class Fit:
    frame: int
    head_R: np.ndarray
    head_t: np.ndarray
    jaw_R: np.ndarray
    jaw_t: np.ndarray
    vertices: np.ndarray
    coefficients_base: np.ndarray
    status: str = "fitted"


@dataclass
class Det:
    points: np.ndarray
    confidence: np.ndarray | None
    face_found: bool = True


def rot_y(deg):
    a = np.deg2rad(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def make_take(T=12, accel=0.2, pop_frame=7, pop=1.5):
    rng = np.random.default_rng(0)
    base = rng.normal(0, 30, (50, 3))
    fits, dets = [], {}
    for j in range(T):
        head = v = base + np.array([0.0, 0.5 * accel * j * j, 0.0])   # constant acceleration along y (head frame)
        if j == pop_frame:
            head = v + [0.0, 0.0, pop]
        R, t = R_FRONT @ rot_y(2.0 * j), np.array([3.0 * j, 0.0, 600.0])  # the head turns and moves: removed
        fits.append(Fit(10 + j, R, t, np.eye(3), np.zeros(3), (head @ R.T + t).astype(np.float32),
                        np.array([0.1 * j, 0.5]), "bridged" if j == 3 else "fitted"))
        conf = np.linspace(0.0, 1.0, 11)
        dets[10 + j] = Det(np.zeros((11, 2)), conf, face_found=j != 3)
    return fits, dets


def test_take_series_against_hand_values():
    fits, dets = make_take()
    errors = {10 + j: 0.1 * j for j in range(12)}
    errors[13] = None
    s = take_series(iter(fits), 25.0, ("jawOpen", "smile"), errors, "px", dets)
    np.testing.assert_array_equal(s.frame, np.arange(10, 22))
    np.testing.assert_allclose(s.time_s, s.frame / 25.0)
    np.testing.assert_allclose(s.head_deg[:, 0], 2.0 * np.arange(12), atol=1e-9)        # yaw
    np.testing.assert_allclose(s.head_deg[:, 1:], 0.0, atol=1e-9)
    np.testing.assert_allclose(s.weights[:, 0], 0.1 * np.arange(12))
    # jitter: |a| where the motion is smooth (float32 meshes: 1e-4 mm), the pop stands out around frame 7
    smooth = [j for j in range(1, 11) if abs(j - 7) > 1]
    np.testing.assert_allclose(s.jitter_mm[smooth], 0.2, atol=2e-4)
    assert np.isnan(s.jitter_mm[[0, 11]]).all()
    assert np.nanargmax(s.jitter_mm) == 7 and s.jitter_mm[7] > 2.5
    # confidences 0, 0.1 .. 1.0: median 0.5, share >= 0.5 is 6/11; no face at j = 3
    assert s.conf_median[0] == 0.5 and abs(s.conf_share[0] - 6 / 11) < 1e-12 and np.isnan(s.conf_median[3])
    assert not s.face_found[3] and s.face_found.sum() == 11
    assert np.isnan(s.error[3])
    assert worst_frames(s, 3) == [21, 20, 19]


def test_confidence_stats_equal_numpy_row_by_row():
    """The series' confidence median, 10th percentile and share >= 0.5, all rows at once, against np.median,
    np.percentile and a mean over each row's finite values (rows with NaN, inf, one, two or no finite value)."""
    from capture.export.report_html import CONFIDENT

    rng = np.random.default_rng(1)
    c = rng.random((300, 37))
    c[rng.random(c.shape) < 0.2] = np.nan
    c[3] = np.nan
    c[4, :36] = np.inf
    c[5, :35] = np.nan
    c[6, ::2] = CONFIDENT                      # ties at the threshold count as confident
    med, p10, share = confidence_stats(c)
    for i, row in enumerate(c):
        r = row[np.isfinite(row)]
        if r.size == 0:
            assert np.isnan([med[i], p10[i], share[i]]).all()
            continue
        assert abs(med[i] - np.median(r)) < 1e-12 and abs(p10[i] - np.percentile(r, 10)) < 1e-12
        assert share[i] == (r >= CONFIDENT).mean()


def test_flag_spans_cover_exactly_the_flagged_frames_one_span_per_stretch():
    """The report shades bridged (orange) and faceless (red) frames: the merged spans cover the same x as
    one span per flagged frame (the readable reference), and there is one span per stretch of consecutive
    frames of one colour, not one per frame."""
    rng = np.random.default_rng(3)
    T = 400
    frame = np.cumsum(rng.choice([1, 1, 1, 1, 2], T))            # gaps in the frame numbers split stretches
    status = rng.choice(["fitted", "bridged", "skipped"], T, p=[0.6, 0.3, 0.1]).tolist()
    face = rng.random(T) > 0.05                                  # fitted frames without a face are red too
    s = SimpleNamespace(frame=frame, status=status, face_found=face)
    per_frame = [(f - 0.5, f + 0.5, "#f4a261" if st == "bridged" else "#e76f51")
                 for f, st, ok in zip(frame, status, face) if st != "fitted" or not ok]
    spans = flag_spans(s)
    grid = np.arange(frame[0] - 1, frame[-1] + 1, 0.25) + 0.125  # points between the half-frame borders
    for colour in ("#f4a261", "#e76f51"):
        def covered(sp):
            return np.any([(grid > a) & (grid < b) for a, b, c in sp if c == colour], axis=0)
        np.testing.assert_array_equal(covered(spans), covered(per_frame))
    flagged = [st != "fitted" or not ok for st, ok in zip(status, face)]
    colours = ["#f4a261" if st == "bridged" else "#e76f51" for st in status]
    stretches = sum(flagged[j] and not (j > 0 and flagged[j - 1] and colours[j - 1] == colours[j]
                                        and frame[j] == frame[j - 1] + 1) for j in range(T))
    assert len(spans) == stretches < len(per_frame)
    assert all(b0 > a1 or c0 != c1 for (_, a1, c1), (b0, _, c0) in zip(spans, spans[1:]))


def test_render_html_is_self_contained():
    fits, dets = make_take()
    s = take_series(iter(fits), 25.0, ("jawOpen", "smile"), {10 + j: 0.1 * j for j in range(12)}, "px", dets)
    ok, png = cv2.imencode(".png", np.zeros((8, 8, 3), np.uint8))
    thumbs = [(21, base64.b64encode(png.tobytes()).decode())]
    report = {"command": "capture run", "video": {"path": "/data/take7.mp4"}, "actor": {"name": "A"},
              "camera": {"source": "default guess", "is_default": True},
              "frames": {"requested": 12, "fitted": 12, "skipped": 0},
              "error": {"unit": "px", "mean": 0.55, "median": 0.55, "max": 1.1, "worst_frame": 21}}
    page = render_html(report, s, figures(s), thumbs)
    assert not re.search(r"(src|href)\s*=\s*['\"]?(https?:|//)", page) and "<script" not in page
    imgs = re.findall(r"src='data:image/png;base64,([^']+)'", page)
    assert len(imgs) == 1                                   # the thumbnail
    img = cv2.imdecode(np.frombuffer(base64.b64decode(imgs[0]), np.uint8), cv2.IMREAD_COLOR)
    assert img is not None and img.size > 0
    svgs = re.findall(r"src='data:image/svg\+xml;base64,([^']+)'", page)
    assert len(svgs) == 5                                   # the figures: well-formed SVG with their labels as text
    import xml.etree.ElementTree as ET

    roots = [ET.fromstring(base64.b64decode(b)) for b in svgs]
    assert all(r.tag.endswith("svg") for r in roots)
    assert "jawOpen" in base64.b64decode(svgs[3]).decode()  # the expression names are text, not paths
    assert "take7.mp4" in page and "DEFAULT CAMERA" in page and "worst frame 21" in page
    assert "1 bridged" in page and "1 without a face" in page


def test_shoot_page_links_each_take_report(tmp_path):
    out = tmp_path / "shoot_out"
    (out / "a").mkdir(parents=True)
    (out / "a" / "report.html").write_text("<html></html>")
    report = {"name": "day1", "shoot": "day1.toml", "totals": {"takes": 2, "done": 1, "failed": 1},
              "takes": [{"take": "a", "status": "done", "out": str(out / "a"), "frames_requested": 10,
                         "frames_fitted": 10, "reprojection_mean_px": 0.4, "seconds": 12.0},
                        {"take": "b", "status": "failed", "out": str(out / "b"), "error": "video missing"}]}
    page = shoot_html(report, out)
    assert "href='a/report.html'" in page and (out / "a" / "report.html").is_file()
    assert "failed</span> video missing" in page and page.count("<tr>") == 3
    assert "0.40" in page


def test_batch_report_writes_the_shoot_page(tmp_path):
    from capture.batch.report import write_batch_report

    report = {"name": "s", "out": str(tmp_path), "takes": [], "totals": {"takes": 0}}
    write_batch_report(tmp_path, report)
    assert (tmp_path / "batch_report.html").read_text().startswith("<!doctype html>")
    assert Path(tmp_path / "batch_report.json").is_file()


@pytest.mark.parametrize("method", ["fork", "spawn"])
def test_figures_drawn_in_their_own_process_are_the_same_bytes(method, monkeypatch):
    """FigureProcess draws report_html.figures in its own process (it imports matplotlib while a take
    runs), forked (Linux) or a fresh interpreter (elsewhere): the same SVG bytes as drawn here (no time
    stamp in them), and drawn here when the process is gone."""
    import multiprocessing

    import capture.export.report_figures as rf
    from capture.export.report_figures import FigureProcess

    if method not in multiprocessing.get_all_start_methods():
        pytest.skip(f"no {method} on this platform")
    monkeypatch.setattr(rf, "START_METHOD", method)

    fits, dets = make_take()
    s = take_series(iter(fits), 25.0, ("jawOpen", "smile"), {10 + j: 0.1 * j for j in range(12)}, "px", dets)
    here = figures(s)
    assert figures(s) == here                      # deterministic, or the comparison below means nothing
    with FigureProcess() as fp:
        fp.submit(s)
        assert fp.result() == here
        fp._proc.kill()
        fp._proc.join()
        fp.submit(s)
        assert fp.result() == here                 # the process is gone: drawn here
    with FigureProcess() as fp:
        fp.submit(s)
        assert fp.result() == here
    assert fp._proc.exitcode == 0                  # it left cleanly when told to (report_figures._leave)
    # matplotlib imported when asked (a streamed run asks when detection ends), or at the first series
    for prepare in (True, False):
        with FigureProcess(prepare_later=True) as fp:
            if prepare:
                fp.prepare()
            fp.submit(s)
            assert fp.result() == here
        assert fp._proc.exitcode == 0


def test_worst_frame_images_keeps_exactly_the_worst_frames():
    """Offered frame by frame in order (as a take streams by), the collector ends with the images of
    worst_frames' frames, never holding more than k: ties (the earlier frame is worse), frames without an
    error (None, NaN) and takes shorter than k included."""
    from capture.export.report_html import WorstFrameImages, worst_frames

    rng = np.random.default_rng(0)
    for trial in range(200):
        T = int(rng.integers(0, 40))
        err = np.round(rng.random(T) * 5, 1)            # rounded: many ties
        err[rng.random(T) < 0.15] = np.nan
        frames = np.arange(T) * 2 + 7
        k = int(rng.integers(1, 8))
        c = WorstFrameImages(k)
        for f, e in zip(frames, err):
            e = None if (np.isnan(e) and f % 4 == 1) else float(e)
            if c.wants(int(f), e):
                c.keep(int(f), e, np.full(2, f))
            assert len(c.images) <= k
        ref = worst_frames(SimpleNamespace(error=err, frame=frames), k)
        assert sorted(c.images) == sorted(ref), (trial, k)
        assert all(int(v[0]) == f for f, v in c.images.items())


def test_thumbnails_drawn_on_threads_equal_those_drawn_one_by_one(monkeypatch):
    """report_html.thumbnails draws the worst frames on the overlay's threads: the same PNGs, in the order of
    ``frames``, as one thread gives, whatever order the drawings finish in; frames without a fit are left out."""
    import time

    import capture.export.overlay as overlay
    import capture.io.machine as machine
    from capture.export.report_html import thumbnails

    rng = np.random.default_rng(3)
    frames = [40, 7, 22, 13, 31, 5]
    images = {i: rng.integers(0, 255, (120, 160, 3), np.uint8) for i in frames}
    fits = {i: SimpleNamespace(vertices=None, landmarks_fit=np.array([[30.0 + i, 20.0], [90.0, 70.0 + i]]))
            for i in frames if i != 22}
    delays = dict(zip(frames, [0.05, 0.0, 0.02, 0.04, 0.0, 0.03]))

    class Renderer:
        def render(self, img, fit, det, vertices):
            time.sleep(delays[int(fit.landmarks_fit[0, 0]) - 30])      # finish out of order
            out = img.copy()
            out[::7] = 255 - out[::7]
            return out

    def run(threads):
        monkeypatch.setattr(overlay, "DRAW_THREADS", threads)
        monkeypatch.setattr(machine, "usable_cores", lambda: threads)
        return thumbnails(Path("unused.mp4"), frames, fits, {}, Renderer(), height=48, images=images)

    one, three = run(1), run(3)
    assert [i for i, _ in one] == [i for i in frames if i != 22]
    assert three == one


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255.0 ** 2 / max(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2), 1e-12)))


def _textured(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A frame with detail at every scale (blurred noise at three sizes), as a face's photo has."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w, 3), np.float64)
    for sigma, amp in ((2.0, 30.0), (4.0, 60.0), (16.0, 120.0)):
        img += amp * cv2.GaussianBlur(rng.normal(0, 1, (h, w, 3)), (0, 0), sigma) * sigma ** 0.5
    return np.clip(img + 128, 0, 255).astype(np.uint8)


def test_a_face_crop_gives_back_the_thumbnails_face():
    """report_html.FaceCrop keeps the thumbnail's box of a frame (face_box of the landmarks) at no more than
    the thumbnail's height; put back into a frame it is black outside the box and, seen at the thumbnail's
    size, within 33 dB of the frame inside it (the resampling and JPEG 95 give 35-42 dB on this texture and
    38 dB on a portrait photograph; the same crop put back 4 px off is at least 3 dB worse). A face smaller
    than the thumbnail is kept at its own size."""
    from capture.export.report_html import THUMB_HEIGHT, FaceCrop, face_box

    img = _textured(720, 1280)
    for lo, hi in (((300.0, 120.0), (900.0, 690.0)), ((600.0, 300.0), (680.0, 380.0)), ((-50.0, 500.0), (200.0, 760.0))):
        pts = np.array([lo, hi, [0.5 * (lo[0] + hi[0]), lo[1]], [np.nan, np.nan]])
        c = FaceCrop.of(img, pts)
        assert c.box == face_box(pts, 1280, 720) and c.frame_size == (1280, 720)
        x0, y0, x1, y1 = c.box
        stored = cv2.imdecode(np.frombuffer(c.jpeg, np.uint8), cv2.IMREAD_COLOR)
        assert stored.shape[0] == min(THUMB_HEIGHT, y1 - y0)
        back = c.frame()
        assert back.shape == img.shape and back.dtype == np.uint8
        outside = np.ones(img.shape[:2], bool)
        outside[y0:y1, x0:x1] = False
        assert not back[outside].any()
        size = (round((x1 - x0) * stored.shape[0] / (y1 - y0)), stored.shape[0])
        thumb = lambda im, dx=0: cv2.resize(im[y0:y1, x0 + dx:x1 + dx], size, interpolation=cv2.INTER_AREA)
        assert _psnr(thumb(back), thumb(img)) > 33.0
        if x0 >= 4:
            assert _psnr(thumb(back), thumb(img, -4)) < _psnr(thumb(back), thumb(img)) - 3.0
    assert FaceCrop.of(img, np.full((5, 2), np.nan)) is None
    assert FaceCrop.of(img, np.array([[10.0, 10.0]])) is not None      # one point: its 16 px box
    assert face_box(np.array([[-40.0, -40.0]]), 1280, 720) is None     # off the frame


def test_thumbnails_read_the_video_where_a_face_crop_is_not_the_thumbnails_box(monkeypatch):
    """A kept FaceCrop whose box is not the one the thumbnail cuts (the landmarks the report uses differ from
    those detection cropped around) is not drawn black: that frame is read from the video instead."""
    import capture.io.video as video
    from capture.export.report_html import FaceCrop, thumbnails

    img = _textured(240, 320, seed=1)
    pts = {3: np.array([[100.0, 60.0], [200.0, 170.0]]), 5: np.array([[40.0, 30.0], [150.0, 140.0]])}
    dets = {i: Det(p, None) for i, p in pts.items()}
    fits = {i: SimpleNamespace(vertices=None, landmarks_fit=p) for i, p in pts.items()}
    images = {3: FaceCrop.of(img, pts[3]), 5: FaceCrop.of(img, pts[3])}      # frame 5's crop: frame 3's box
    read = []

    class Reader:
        def __init__(self, path):
            pass

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        def frames(self, indices):
            read.extend(indices)
            return ((i, img) for i in indices)

    class Renderer:
        def render(self, image, fit, det, vertices):
            return image.copy()

    monkeypatch.setattr(video, "VideoReader", Reader)
    got = dict(thumbnails(Path("take.mp4"), [3, 5], fits, dets, Renderer(), height=64, images=images))
    ref = dict(thumbnails(Path("take.mp4"), [3, 5], fits, dets, Renderer(), height=64, images={}))
    assert read == [5, 3, 5]
    for i in (3, 5):
        a, b = (cv2.imdecode(np.frombuffer(base64.b64decode(x[i]), np.uint8), cv2.IMREAD_COLOR) for x in (got, ref))
        assert a.shape == b.shape and _psnr(a, b) > 35.0


KILLED_RUN = """
import sys, time
import capture.export.report_figures as rf
rf.START_METHOD = sys.argv[1]
fp = rf.FigureProcess(prepare_later=True)    # as capture run makes it: waiting, matplotlib not yet imported
print(fp._proc.pid, flush=True)
time.sleep(300)
"""


@pytest.mark.parametrize("method", ["fork", "spawn"])
def test_figures_process_ends_when_the_run_is_killed(method):
    """kill -9 of the run: its figures' process reads the end of its pipe and leaves, instead of living on
    (a forked one that kept the run's end of the pipe never did, and held the run's folder lock with it)."""
    import multiprocessing
    import os
    import signal
    import subprocess
    import sys
    import time

    if method not in multiprocessing.get_all_start_methods():
        pytest.skip(f"no {method} on this platform")
    if not os.path.isdir("/proc"):
        pytest.skip("no /proc to watch the process with")
    run = subprocess.Popen([sys.executable, "-c", KILLED_RUN, method], stdout=subprocess.PIPE, text=True,
                           cwd=Path(__file__).resolve().parents[1])
    try:
        child = int(run.stdout.readline())
    finally:
        run.send_signal(signal.SIGKILL)
        run.wait(timeout=30)

    def alive(pid: int) -> bool:
        try:
            with open(f"/proc/{pid}/stat") as fh:
                return fh.read().rsplit(")", 1)[1].split()[0] != "Z"    # a zombie has ended
        except FileNotFoundError:
            return False

    deadline = time.time() + 60
    while alive(child) and time.time() < deadline:
        time.sleep(0.05)
    ended = not alive(child)
    if not ended:
        os.kill(child, signal.SIGKILL)
    assert ended, "the figures' process outlived the killed run"
