"""``report.html``: a take at a glance, one self-contained file (no network; figures are embedded PNG).

Written by ``capture run`` and ``capture fit3d`` next to ``report.json`` (every run, whatever
``--formats``), from the run's own data: the stored frame fits, the detections and ``report.json``.

Contents (top to bottom):

* a summary table: take, actor, camera (flagged when it is the default guess), frames fitted / bridged
  / without a face, error mean / median / max and the worst frame, the run's settings and time;
* **reprojection error** per frame (px, RMS over landmarks with confidence >= 0.5; fit3d: the 3D vertex
  error in mm) with bridged frames and frames without a face shaded;
* **head pose**: yaw, pitch, roll (degrees, relative to a frontal view; see
  :func:`capture.export.rig.head_angles_deg`) and translation (mm, camera frame);
* **jaw**: opening (negative pitch, degrees), yaw, roll and translation length (mm);
* **expression weights** over time (the per-frame base, one line per shape; a heat map beyond 12);
* **jitter**: per frame the RMS over vertices of the mesh's second difference in time
  ``|v[t+1] - 2 v[t] + v[t-1]|`` in the head frame (mm): the head's motion removed, what is left is
  expression acceleration (a fast jaw moves it too) and shake; a spike on a still face is a pop;
* **detector confidence**: median and 10th percentile of the landmarks' confidence per frame, and the
  share of confident landmarks (>= 0.5);
* **worst frames**: thumbnails of the frames with the largest error, drawn like ``overlay.mp4`` and
  cropped to the face (video runs only).

The figures are made with matplotlib (no display needed) and embedded as base64 SVG, the thumbnails as
base64 PNG; the page has inline CSS and no scripts.
"""

from __future__ import annotations

import base64
import heapq
import html
import io
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Sequence

import numpy as np

REPORT_HTML = "report.html"
WORST_FRAMES = 6
THUMB_HEIGHT = 240
CONFIDENT = 0.5


@dataclass
class TakeSeries:
    """Per-frame series of a take (T frames, E expressions)."""

    frame: np.ndarray            # (T,) video frame index
    time_s: np.ndarray           # (T,)
    status: list[str]            # fitted / bridged / skipped
    error: np.ndarray            # (T,) px (video) or mm (fit3d); NaN when none
    error_unit: str
    head_deg: np.ndarray         # (T, 3) yaw, pitch, roll
    head_t: np.ndarray           # (T, 3) mm
    jaw_deg: np.ndarray          # (T, 3) yaw, pitch, roll
    jaw_t: np.ndarray            # (T, 3) mm
    weights: np.ndarray          # (T, E) base coefficients
    names: tuple[str, ...]
    jitter_mm: np.ndarray        # (T,) NaN at the ends
    face_found: np.ndarray       # (T,) bool
    conf_median: np.ndarray      # (T,) NaN without confidences
    conf_p10: np.ndarray         # (T,)
    conf_share: np.ndarray       # (T,) share of landmarks with confidence >= 0.5


class SeriesCollector:
    """Builds a :class:`TakeSeries` from frame fits given one at a time (``add``), then ``series(...)``:
    per frame a few numbers, and two meshes held for the jitter. ``capture run``'s stream feeds it the fits
    as they are exported, so the report need not read the fit back (:func:`take_series` is the same on an
    iterable). Given with each fit (``add(f, detection)``), a frame's detection is summarised at once (face
    found, :func:`confidence_stats` of its row: the same numbers as from all rows at the end), and
    ``series`` then needs no ``detections``: the stream draws the figures before the take's track exists."""

    def __init__(self, n_expressions: int):
        self.E = int(n_expressions)
        self.rows: dict[str, list] = {k: [] for k in ("frame", "status", "head_R", "head_t", "jaw_R", "jaw_t", "w",
                                                      "acc")}
        self.prev: list[np.ndarray | None] = [None, None]
        self.seen: dict[int, tuple] = {}     # frame -> (face found, confidence median, p10, share)

    def add(self, f, detection=None) -> None:
        from capture.export.base import to_head_frame
        from capture.export.rig import frame_base_weights

        rows = self.rows
        rows["frame"].append(int(f.frame))
        rows["status"].append(str(getattr(f, "status", "fitted")))
        for k in ("head_R", "head_t", "jaw_R", "jaw_t"):
            v = getattr(f, k, None)
            rows[k].append(np.full((3, 3) if k.endswith("R") else 3, np.nan) if v is None else np.asarray(v, float))
        rows["w"].append(frame_base_weights(f, self.E))
        v = getattr(f, "vertices", None)
        cur = None if v is None else to_head_frame(v, f.head_R, f.head_t, exact=False)
        a, b = self.prev
        if a is None or b is None or cur is None:
            rows["acc"].append(None)
        else:       # RMS over the vertices of the second difference (float32 points, float64 sum: ~1e-5 mm)
            d = cur - 2 * b + a
            rows["acc"].append(float(np.sqrt(np.einsum("ij,ij->", d, d, dtype=np.float64) / len(d))))
        self.prev = [b, cur]
        if detection is not None:
            c = getattr(detection, "confidence", None)
            stats = (np.nan,) * 3
            if c is not None and detection.face_found:
                stats = tuple(float(v[0]) for v in confidence_stats(np.asarray(c, np.float64).reshape(1, -1)))
            self.seen[int(f.frame)] = (bool(detection.face_found),) + stats

    def series(self, fps: float, names: Sequence[str], errors: dict[int, float | None], error_unit: str,
               detections: dict[int, Any] | None = None) -> TakeSeries:
        from capture.export.rig import head_angles_deg, jaw_angles_deg

        E, rows = len(names), self.rows
        if E != self.E:
            raise ValueError(f"{E} expression names for series of {self.E} expressions")
        T = len(rows["frame"])
        frame = np.asarray(rows["frame"], np.int64)
        jitter = np.full(T, np.nan)
        for j in range(2, T):   # acc of frame j is centred at j - 1
            if rows["acc"][j] is not None:
                jitter[j - 1] = rows["acc"][j]
        face = np.ones(T, bool)
        med, p10, share = (np.full(T, np.nan) for _ in range(3))
        rows_of: dict[int, list] = {}          # the frames' confidences, by landmark count
        for j, i in enumerate(frame):
            if detections is None and int(i) in self.seen:     # summarised as it came (add)
                face[j], med[j], p10[j], share[j] = self.seen[int(i)]
                continue
            d = None if detections is None else detections.get(int(i))
            if d is None:
                continue
            face[j] = bool(d.face_found)
            c = getattr(d, "confidence", None)
            if c is not None and d.face_found:
                c = np.asarray(c, np.float64).reshape(-1)
                rows_of.setdefault(c.size, []).append((j, c))
        for rows_c in rows_of.values():
            idx = np.array([j for j, _ in rows_c])
            med[idx], p10[idx], share[idx] = confidence_stats(np.stack([c for _, c in rows_c]))
        err = np.array([np.nan if errors.get(int(i)) is None else float(errors[int(i)]) for i in frame])
        stack = (lambda k, shape: np.stack(rows[k]) if T else np.zeros((0,) + shape))
        return TakeSeries(frame=frame, time_s=frame / float(fps), status=list(rows["status"]), error=err,
                          error_unit=error_unit, head_deg=head_angles_deg(stack("head_R", (3, 3))),
                          head_t=stack("head_t", (3,)), jaw_deg=jaw_angles_deg(stack("jaw_R", (3, 3))),
                          jaw_t=stack("jaw_t", (3,)), weights=stack("w", (E,)) if E else np.zeros((T, 0)),
                          names=tuple(names), jitter_mm=jitter, face_found=face, conf_median=med, conf_p10=p10,
                          conf_share=share)


def confidence_stats(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per row of ``c (n, L)`` over its finite entries: the median, the 10th percentile (numpy's default
    linear interpolation) and the share >= :data:`CONFIDENT`; NaN for a row with none. One sort for all
    rows: a take of 36,000 frames took 4 s frame by frame with ``np.median`` and ``np.percentile``, and
    ``np.nanpercentile(c, q, axis=1)`` loops over the rows too (12x this function's time on 3,000 rows)."""
    c = np.where(np.isfinite(c), c, np.nan)
    k = np.isfinite(c).sum(1)
    srt = np.sort(c, axis=1)                 # NaN last
    rows = np.arange(len(c))

    def quantile(q: float) -> np.ndarray:
        pos = (k - 1).clip(0) * q
        lo = np.floor(pos).astype(np.int64)
        hi = np.minimum(lo + 1, (k - 1).clip(0))
        a, b = srt[rows, lo], srt[rows, hi]
        return a + (b - a) * (pos - lo)

    with np.errstate(invalid="ignore", divide="ignore"):
        share = (c >= CONFIDENT).sum(1) / k
    none = k == 0
    out = [quantile(0.5), quantile(0.1), share]
    for v in out:
        v[none] = np.nan
    return out[0], out[1], out[2]


def take_series(fits: Iterable[Any], fps: float, names: Sequence[str], errors: dict[int, float | None],
                error_unit: str, detections: dict[int, Any] | None = None) -> TakeSeries:
    """Collect the series from frame fits (streamed once; two meshes held for the jitter)."""
    collector = SeriesCollector(len(names))
    for f in fits:
        collector.add(f)
    return collector.series(fps, names, errors, error_unit, detections)


def worst_frames(s: TakeSeries, k: int = WORST_FRAMES) -> list[int]:
    """Video frame indices of the ``k`` largest errors, worst first."""
    ok = np.flatnonzero(np.isfinite(s.error))
    order = ok[np.argsort(-s.error[ok], kind="stable")][:k]
    return [int(s.frame[j]) for j in order]


def face_box(points, width: int, height: int) -> tuple[int, int, int, int] | None:
    """The thumbnail's crop ``(x0, y0, x1, y1)`` (px, end exclusive, inside a ``width x height`` frame): the
    box of the finite ``points`` ``(N, 2)`` px, squared and widened by 25 % + 8 px; None when there are no
    points or the box is 8 px or less on a side."""
    pts = np.asarray(points, np.float64).reshape(-1, 2)
    pts = pts[np.isfinite(pts).all(1)]
    if not len(pts):
        return None
    lo, hi = pts.min(0), pts.max(0)
    c, half = 0.5 * (lo + hi), 0.5 * (hi - lo).max() * 1.25 + 8
    x0, y0 = int(max(0, c[0] - half)), int(max(0, c[1] - half))
    x1, y1 = int(min(width, c[0] + half)), int(min(height, c[1] + half))
    return (x0, y0, x1, y1) if x1 - x0 > 8 and y1 - y0 > 8 else None


@dataclass(frozen=True)
class FaceCrop:
    """What a thumbnail needs of a frame, kept small while the take goes by: the face's box of a
    ``frame_size`` ``(W, H)`` frame (:func:`face_box` of its detected landmarks), scaled to the thumbnail's
    height (never up) and stored as JPEG (quality 95: 5-25 KB, where the frame is 2.7 MB at 720p; about
    1 ms a frame).

    :meth:`frame` puts it back into a frame-sized image (black elsewhere) for the overlay's renderer; the
    thumbnail cut from it differs from one cut from the video frame only by the JPEG and the resampling
    (``tests/test_report_html.py`` bounds it)."""

    box: tuple[int, int, int, int]
    frame_size: tuple[int, int]
    jpeg: bytes

    @classmethod
    def of(cls, image: np.ndarray, points, height: int = THUMB_HEIGHT) -> "FaceCrop | None":
        """The crop of ``image`` (BGR uint8 (H, W, 3)) around ``points`` (N, 2) px; None without a box."""
        import cv2

        h, w = image.shape[:2]
        box = face_box(points, w, h)
        if box is None:
            return None
        x0, y0, x1, y1 = box
        crop = image[y0:y1, x0:x1]
        # halved by area averaging while twice the height is left (OpenCV's fast path: 0.3 ms for a 720 px
        # face, against 2.7 for one area resize by 3), then bilinear by less than 2 (48 dB from area all the way)
        while crop.shape[0] >= 2 * height and crop.shape[1] >= 2:
            crop = cv2.resize(crop[:crop.shape[0] // 2 * 2, :crop.shape[1] // 2 * 2],
                              (crop.shape[1] // 2, crop.shape[0] // 2), interpolation=cv2.INTER_AREA)
        if crop.shape[0] > height:
            crop = cv2.resize(crop, (max(1, round(crop.shape[1] * height / crop.shape[0])), height),
                              interpolation=cv2.INTER_LINEAR)
        ok, jpeg = cv2.imencode(".jpg", crop, [cv2.IMWRITE_JPEG_QUALITY, 95])
        return cls(box, (w, h), jpeg.tobytes()) if ok else None

    def frame(self) -> np.ndarray:
        """A ``(H, W, 3)`` uint8 frame: the crop, scaled back, in its box; black elsewhere."""
        import cv2

        w, h = self.frame_size
        x0, y0, x1, y1 = self.box
        out = np.zeros((h, w, 3), np.uint8)
        crop = cv2.imdecode(np.frombuffer(self.jpeg, np.uint8), cv2.IMREAD_COLOR)
        out[y0:y1, x0:x1] = cv2.resize(crop, (x1 - x0, y1 - y0), interpolation=cv2.INTER_CUBIC)
        return out


class WorstFrameImages:
    """The images of a take's ``k`` worst frames, gathered while the take goes by: frames are offered in
    order with their error (:meth:`wants`, then :meth:`keep` with the image), and at most ``k`` images are
    held. At the end :attr:`images` has those of :func:`worst_frames` (the ``k`` worst frames of a take
    are among the ``k`` worst of every prefix that contains them; ties go to the earlier frame, as there).
    ``capture run`` fills it as it exports, with the frames the overlay's export decoded or else the
    :class:`FaceCrop` that detection cut from the frames it had, so the report need not decode the video
    again (:func:`thumbnails`' ``images``); and, in another, those frames' fits, so that it need not read
    them back."""

    def __init__(self, k: int = WORST_FRAMES):
        self.k = int(k)
        self._heap: list[tuple[float, int]] = []     # (error, -frame): the least bad kept frame first
        self.images: dict[int, np.ndarray | FaceCrop] = {}

    def wants(self, frame: int, error: float | None) -> bool:
        """Would the frame be among the ``k`` worst of those offered so far?"""
        if self.k <= 0 or error is None or not math.isfinite(error):
            return False
        return len(self._heap) < self.k or (float(error), -int(frame)) > self._heap[0]

    def keep(self, frame: int, error: float, image: np.ndarray | FaceCrop) -> None:
        """Hold ``image`` for ``frame`` (after :meth:`wants` said yes); lets go of the one it displaces."""
        key = (float(error), -int(frame))
        if len(self._heap) < self.k:
            heapq.heappush(self._heap, key)
        else:
            _, gone = heapq.heapreplace(self._heap, key)
            self.images.pop(-gone, None)
        self.images[int(frame)] = image


# ------------------------------------------------------------------------------------------- figures
def _svg(fig) -> str:
    """The figure as base64 SVG: vector, with text left as text (``svg.fonttype`` none), so it is half
    the drawing time of a PNG and scales in the browser."""
    import matplotlib
    import matplotlib.pyplot as plt

    buf = io.BytesIO()
    with matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": "capture"}):   # same take, same bytes
        fig.savefig(buf, format="svg", metadata={"Date": None})       # no time stamp: same take, same bytes
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _subplots(plt, figsize: tuple[float, float], ncols: int = 1, left_in: float = 0.75, top_in: float = 0.3):
    """``plt.subplots`` with margins fixed in inches, which fit these plots' labels: a constrained layout
    would measure every text first (half of the report's drawing time)."""
    fig, axes = plt.subplots(1, ncols, figsize=figsize)
    w, h = figsize
    fig.subplots_adjust(left=left_in / w, right=1 - 0.3 / w, bottom=0.5 / h, top=1 - top_in / h,
                        wspace=0.9 / (w / ncols))
    return fig, axes


def flag_spans(s: TakeSeries) -> list[tuple[float, float, str]]:
    """``[(x0, x1, colour)]``: the stretches of consecutive video frames that were bridged (orange) or had
    no face otherwise (red), each frame ``[i - 0.5, i + 0.5]``; one span per stretch, so a long take with
    thousands of lost frames draws a few dozen patches, not one per frame."""
    spans: list[tuple[float, float, str]] = []
    for j, st in enumerate(s.status):
        if st == "fitted" and s.face_found[j]:
            continue
        colour = "#f4a261" if st == "bridged" else "#e76f51"
        x0, x1 = float(s.frame[j]) - 0.5, float(s.frame[j]) + 0.5
        if spans and spans[-1][2] == colour and spans[-1][1] == x0:
            spans[-1] = (spans[-1][0], x1, colour)
        else:
            spans.append((x0, x1, colour))
    return spans


def _shade_flags(ax, s: TakeSeries) -> None:
    for x0, x1, colour in flag_spans(s):
        ax.axvspan(x0, x1, color=colour, alpha=0.25, lw=0)


def figures(s: TakeSeries) -> list[tuple[str, str]]:
    """``[(title, base64 SVG)]`` of the take's plots (x axis: video frame)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    out = []
    x = s.frame
    wide = (9.5, 2.6)

    fig, ax = _subplots(plt, wide)
    ax.plot(x, s.error, color="#1d3557", lw=1.2)
    _shade_flags(ax, s)
    if np.isfinite(s.error).any():
        ax.axhline(np.nanmedian(s.error), color="#457b9d", ls="--", lw=0.8, label="median")
        ax.legend(loc="upper right", fontsize=8)
    ax.set_ylabel(s.error_unit)
    ax.set_xlabel("frame  (orange: bridged, red: no face)")
    ax.grid(alpha=0.3)
    out.append(("Reprojection error" if s.error_unit == "px" else "3D error", _svg(fig)))

    fig, (a1, a2) = _subplots(plt, wide, 2)
    for k, (lab, c) in enumerate((("yaw", "#e63946"), ("pitch", "#2a9d8f"), ("roll", "#264653"))):
        a1.plot(x, s.head_deg[:, k], color=c, lw=1.1, label=lab)
    a1.set_ylabel("degrees")
    a1.legend(fontsize=8, ncol=3)
    for k, (lab, c) in enumerate((("x", "#e63946"), ("y", "#2a9d8f"), ("z - mean", "#264653"))):
        v = s.head_t[:, k] - (np.nanmean(s.head_t[:, k]) if k == 2 and np.isfinite(s.head_t[:, k]).any() else 0)
        a2.plot(x, v, color=c, lw=1.1, label=lab)
    a2.set_ylabel("mm (camera frame)")
    a2.legend(fontsize=8, ncol=3)
    for a in (a1, a2):
        a.grid(alpha=0.3)
        a.set_xlabel("frame")
    out.append(("Head pose: rotation and translation", _svg(fig)))

    fig, (a1, a2) = _subplots(plt, wide, 2)
    a1.plot(x, -s.jaw_deg[:, 1], color="#e76f51", lw=1.3, label="opening (-pitch)")
    a1.plot(x, s.jaw_deg[:, 0], color="#2a9d8f", lw=1.0, label="yaw")
    a1.plot(x, s.jaw_deg[:, 2], color="#264653", lw=1.0, label="roll")
    a1.set_ylabel("degrees")
    a1.legend(fontsize=8, ncol=3)
    a2.plot(x, np.linalg.norm(s.jaw_t, axis=1), color="#6d597a", lw=1.1)
    a2.set_ylabel("jaw translation, mm")
    for a in (a1, a2):
        a.grid(alpha=0.3)
        a.set_xlabel("frame")
    out.append(("Jaw", _svg(fig)))

    if s.weights.shape[1]:
        E = s.weights.shape[1]
        if E <= 12:
            fig, ax = _subplots(plt, (9.5, 3.0))
            cmap = plt.get_cmap("tab20")
            for e in range(E):
                ax.plot(x, s.weights[:, e], lw=1.0, color=cmap(e % 20), label=s.names[e])
            ax.legend(fontsize=7, ncol=4, loc="upper right")
            ax.set_ylabel("weight")
            ax.set_xlabel("frame")
            ax.grid(alpha=0.3)
        else:
            # names at 7 pt on the y axis: about 0.05 in per character
            fig, ax = _subplots(plt, (9.5, 0.9 + 0.17 * E), left_in=0.25 + 0.05 * max(map(len, s.names)), top_in=0.15)
            lim = max(1e-6, float(np.nanmax(np.abs(s.weights))) if np.isfinite(s.weights).any() else 1.0)
            im = ax.imshow(s.weights.T, aspect="auto", cmap="RdBu_r", vmin=-lim, vmax=lim, interpolation="nearest",
                           extent=(x[0] - 0.5, x[-1] + 0.5, E - 0.5, -0.5) if len(x) else None)
            ax.set_yticks(range(E))
            ax.set_yticklabels(s.names, fontsize=7)
            ax.set_xlabel("frame")
            fig.colorbar(im, ax=ax, label="weight", pad=0.01)
        out.append(("Expression weights (per-frame base)", _svg(fig)))

    fig, (a1, a2) = _subplots(plt, wide, 2)
    a1.plot(x, s.jitter_mm, color="#9d0208", lw=1.0)
    a1.set_ylabel("mm per frame²")
    a1.set_xlabel("frame")
    a1.set_title("jitter: RMS second difference of the mesh (head frame)", fontsize=8)
    if np.isfinite(s.conf_median).any():
        a2.plot(x, s.conf_median, color="#2a9d8f", lw=1.1, label="median")
        a2.plot(x, s.conf_p10, color="#e9c46a", lw=1.0, label="10th percentile")
        a2.plot(x, s.conf_share, color="#264653", lw=1.0, ls="--", label="share >= 0.5")
        a2.set_ylim(-0.02, 1.02)
        a2.legend(fontsize=8, ncol=3, loc="lower right")
    else:
        a2.text(0.5, 0.5, "the detector gives no confidence", ha="center", va="center", transform=a2.transAxes)
    _shade_flags(a2, s)
    a2.set_xlabel("frame")
    a2.set_title("detector confidence", fontsize=8)
    for a in (a1, a2):
        a.grid(alpha=0.3)
    out.append(("Jitter and detector confidence", _svg(fig)))
    return out


# ---------------------------------------------------------------------------------------- thumbnails
def thumbnails(video: Path, frames: list[int], fits: dict[int, Any], detections: dict[int, Any], renderer,
               height: int = THUMB_HEIGHT, images: dict[int, Any] | None = None) -> list[tuple[int, str]]:
    """``[(frame, base64 PNG)]``: the frames drawn by ``renderer`` (an overlay ``FrameRenderer``), cropped
    to the face (:func:`face_box` of the detected landmarks, else of the fitted ones).

    ``images``: frames already decoded, or their :class:`FaceCrop` (e.g. kept by :class:`WorstFrameImages`);
    the others, and crops whose box is not the thumbnail's, are read from ``video``."""
    from concurrent.futures import ThreadPoolExecutor

    import cv2

    from capture.export.overlay import DRAW_THREADS
    from capture.io.machine import usable_cores
    from capture.io.video import VideoReader

    def points(i: int):
        d = detections.get(int(i))
        f = fits.get(int(i))
        return d.points if d is not None and d.face_found else getattr(f, "landmarks_fit", np.zeros((0, 2)))

    def usable(i: int, img) -> bool:
        if not isinstance(img, FaceCrop):
            return True
        return img.box == face_box(points(i), *img.frame_size)

    def frames_read():
        have = {int(i): img for i, img in (images or {}).items() if usable(int(i), img)}
        missing = sorted(i for i in frames if int(i) not in have)
        for i in sorted(frames):
            if int(i) in have:
                img = have[int(i)]
                yield int(i), img.frame() if isinstance(img, FaceCrop) else img
        if missing:
            with VideoReader(video) as reader:
                yield from reader.frames(missing)

    def thumbnail(i: int, img: np.ndarray) -> str | None:
        f = fits.get(int(i))
        if f is None:
            return None
        d = detections.get(int(i))
        drawn = renderer.render(img, f, d, getattr(f, "vertices", None))
        h, w = drawn.shape[:2]
        box = face_box(points(i), w, h)
        crop = drawn if box is None else drawn[box[1]:box[3], box[0]:box[2]]
        scale = height / crop.shape[0]
        crop = cv2.resize(crop, (max(1, int(round(crop.shape[1] * scale))), height), interpolation=cv2.INTER_AREA)
        ok, png = cv2.imencode(".png", crop)
        return base64.b64encode(png.tobytes()).decode("ascii") if ok else None

    # drawn on the overlay's threads (numpy and OpenCV release the GIL; the renderer keeps no state per frame):
    # the report comes after the take, on the run's critical path
    out = {}
    with ThreadPoolExecutor(max_workers=min(DRAW_THREADS, usable_cores()), thread_name_prefix="capture-thumbs") as pool:
        for i, job in [(i, pool.submit(thumbnail, i, img)) for i, img in frames_read()]:
            png = job.result()
            if png is not None:
                out[int(i)] = png
    return [(i, out[i]) for i in frames if i in out]


# ------------------------------------------------------------------------------------------- the page
_CSS = """body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:24px;color:#1d1d1f;max-width:1000px}
h1{font-size:20px;margin:0 0 4px}h2{font-size:15px;margin:22px 0 6px;border-bottom:1px solid #ddd;padding-bottom:3px}
table{border-collapse:collapse;font-size:13px}td,th{padding:3px 10px 3px 0;text-align:left;vertical-align:top}
th{color:#555;font-weight:600}.flag{background:#e76f51;color:#fff;border-radius:3px;padding:1px 5px;font-size:12px}
.ok{color:#2a9d8f}img{max-width:100%}.thumbs{display:flex;flex-wrap:wrap;gap:10px}
.thumbs figure{margin:0}.thumbs figcaption{font-size:12px;color:#444}.muted{color:#777;font-size:12px}"""


def _fmt(v, unit: str = "", digits: int = 2) -> str:
    if v is None:
        return "-"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return html.escape(str(v))
    return f"{f:.{digits}f}{(' ' + unit) if unit else ''}" if np.isfinite(f) else "-"


def render_html(report: dict, s: TakeSeries, figs: list[tuple[str, str]], thumbs: list[tuple[int, str]]) -> str:
    """The page (a string) from ``report.json``'s dict, the series, the figures and the thumbnails."""
    e = report.get("error", {})
    unit = e.get("unit", s.error_unit)
    cam = report.get("camera") or {}
    n_bridged = sum(st == "bridged" for st in s.status)
    n_noface = int((~s.face_found).sum())
    title = report.get("video", {}).get("path") or report.get("meshes", {}).get("folder") or report.get("out_dir", "")
    rows = [("take", html.escape(Path(str(title)).name) + f" <span class=muted>{html.escape(str(title))}</span>"),
            ("command", html.escape(str(report.get("command", "")))),
            ("actor", html.escape(str(report.get("actor", {}).get("name", "-"))))]
    if cam:
        flag = " <span class=flag>DEFAULT CAMERA (60 deg guess)</span>" if cam.get("is_default") else ""
        rows.append(("camera", html.escape(str(cam.get("source", cam.get("provenance", "")))) + flag))
    fr = report.get("frames", {})
    rows.append(("frames", f"{fr.get('fitted', len(s.frame))} fitted of {fr.get('requested', len(s.frame))}; "
                           f"{n_bridged} bridged; {n_noface} without a face; {fr.get('skipped', 0)} skipped"))
    rows.append(("error", f"mean {_fmt(e.get('mean'), unit)}, median {_fmt(e.get('median'), unit)}, "
                          f"max {_fmt(e.get('max'), unit)} (worst frame {e.get('worst_frame', '-')})"
                          + (f"; over {html.escape(str(e.get('landmarks')))}" if e.get("landmarks") else "")))
    if np.isfinite(s.jitter_mm).any():
        rows.append(("jitter", f"median {np.nanmedian(s.jitter_mm):.3f} mm, max {np.nanmax(s.jitter_mm):.3f} mm "
                               f"(frame {int(s.frame[np.nanargmax(s.jitter_mm)])})"))
    rows.append(("time", f"{_fmt(report.get('seconds_total'), 's', 1)}"))
    notes = report.get("notes") or []
    parts = [f"<!doctype html><html lang=en><head><meta charset=utf-8><title>capture report: "
             f"{html.escape(Path(str(title)).name)}</title><style>{_CSS}</style></head><body>",
             f"<h1>{html.escape(Path(str(title)).name)}</h1>",
             "<table>" + "".join(f"<tr><th>{k}</th><td>{v}</td></tr>" for k, v in rows) + "</table>"]
    if notes:
        parts.append("<ul>" + "".join(f"<li>{html.escape(str(n))}</li>" for n in notes) + "</ul>")
    for t, svg in figs:
        parts.append(f"<h2>{html.escape(t)}</h2><img alt='{html.escape(t)}' src='data:image/svg+xml;base64,{svg}'>")
    if thumbs:
        parts.append("<h2>Worst frames</h2><div class=thumbs>")
        err = dict(zip(s.frame.tolist(), s.error.tolist()))
        for i, png in thumbs:
            parts.append(f"<figure><img alt='frame {i}' src='data:image/png;base64,{png}'><figcaption>frame {i}: "
                         f"{_fmt(err.get(i), unit)}</figcaption></figure>")
        parts.append("</div>")
    parts.append(f"<p class=muted>capture {html.escape(str(report.get('versions', {}).get('capture', '')))}; "
                 f"report.json has every number of this page.</p></body></html>")
    return "\n".join(parts)


def write_report_html(out_dir: Path, report: dict, series: TakeSeries, thumbs: list[tuple[int, str]],
                      figs: list[tuple[str, str]] | None = None) -> Path:
    """Write ``out_dir/report.html`` atomically (``figs``: :func:`figures` of ``series``, drawn here when
    None); returns its path."""
    from capture.io.atomic import write_text

    figs = figures(series) if figs is None else figs
    return write_text(Path(out_dir) / REPORT_HTML, render_html(report, series, figs, thumbs))


# -------------------------------------------------------------------------------------- a whole shoot
def shoot_html(report: dict, out_dir: Path) -> str:
    """The shoot-level page of ``capture batch`` (``batch_report.html``): the totals and one row per take,
    linking each take's ``report.html`` (relative links, so the folder can be moved or served as it is)."""
    out_dir = Path(out_dir)
    tot = report.get("totals", {})
    head = ("take", "status", "frames", "error mean px", "median", "max", "time", "")
    rows = []
    for r in report.get("takes", []):
        take_dir = Path(str(r.get("out", "")))
        page = take_dir / REPORT_HTML
        try:
            rel = page.resolve().relative_to(out_dir.resolve()).as_posix()
        except ValueError:
            rel = page.resolve().as_uri()
        link = f"<a href='{html.escape(rel)}'>report</a>" if page.is_file() else "<span class=muted>no report</span>"
        frames = "-" if r.get("frames_requested") is None else f"{r.get('frames_fitted')}/{r.get('frames_requested')}"
        status = html.escape(str(r.get("status", "")))
        if r.get("status") == "failed":
            status = f"<span class=flag>failed</span> {html.escape(str(r.get('error') or ''))}"
        secs = r.get("seconds")
        rows.append([html.escape(str(r.get("take", ""))), status, frames, _fmt(r.get("reprojection_mean_px")),
                     _fmt(r.get("reprojection_median_px")), _fmt(r.get("reprojection_max_px")),
                     "-" if secs is None else f"{float(secs):.0f} s", link])
    name = html.escape(str(report.get("name", "shoot")))
    summary = (f"{tot.get('takes', len(rows))} takes: {tot.get('done', 0)} done, {tot.get('already_done', 0)} already "
               f"done, {tot.get('failed', 0)} failed; {tot.get('frames_fitted', 0)} frames fitted")
    return "\n".join([
        f"<!doctype html><html lang=en><head><meta charset=utf-8><title>capture batch: {name}</title>"
        f"<style>{_CSS}</style></head><body><h1>capture batch: {name}</h1>",
        f"<p>{html.escape(summary)}. <span class=muted>Shoot file {html.escape(str(report.get('shoot', '')))}; "
        f"batch_report.json and batch_summary.csv hold the same rows.</span></p>",
        "<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>"
        + "".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in rows) + "</table>",
        "</body></html>"])
