"""Decoding of model outputs described by a version-2 spec (pure numpy math, no file or model I/O).

* :func:`per_crop`: an output of any shape with the batch on axis 0 and any singleton dims -> (n, values).
* :func:`coordinates`: (n, L * C) values -> positions (n, L, 2) and the optional depth (n, L), for the
  ``interleaved`` (x0 y0 [z0] x1 ...) and ``planar`` (x0 x1 ... y0 y1 ... [z0 z1 ...]) orders.
* :func:`heatmap_peaks`: heatmaps (n, L, H, W) -> sub-pixel peaks in heatmap pixels and the peak value.
  ``gaussian``: the argmax cell refined by a parabola through the logarithm of it and its two
  neighbours on each axis, which is exact for a Gaussian blob (its log is a quadratic), the usual
  "Taylor / DARK" decoding. ``parabola``: the same on the raw values. ``none``: the argmax cell.
* :func:`heatmap_to_input_px`: the heatmap covers the network input edge to edge, so heatmap pixel
  ``u`` (centre convention, like OpenCV) is input pixel ``(u + 0.5) * W / Wh - 0.5``.
* :func:`make_anchors`, :func:`decode_boxes`, :func:`nms`: SSD / BlazeFace face-detector outputs.

Anchors are generated like MediaPipe's ``SsdAnchorsCalculator`` with a fixed anchor size and like
RetinaFace's prior boxes: consecutive layers with the same stride share one feature map (their anchors
per cell add up); for each such map of ``ceil(H / stride) x ceil(W / stride)`` cells, row by row, cell
by cell, anchor by anchor, the centre is ``((j + offset) * stride / W, (i + offset) * stride / H)`` in
``crop_unit`` coordinates (0..1 edge to edge of the input) and the size is 1 x 1 (fixed size, BlazeFace)
or ``size / W x size / H`` (``sizes`` given, SSD).
"""

from __future__ import annotations

import math

import numpy as np


def sigmoid(x: np.ndarray) -> np.ndarray:
    """Logistic function, clipped at +-100 like MediaPipe's score clipping (no overflow warnings)."""
    return 1.0 / (1.0 + np.exp(-np.clip(np.asarray(x, np.float64), -100.0, 100.0)))


def per_crop(arr: np.ndarray, n: int) -> np.ndarray:
    """An output (B, ...) with B >= n crops on axis 0 -> (n, values) float64, row-major per crop."""
    a = np.asarray(arr, dtype=np.float64)
    if a.ndim == 0:
        a = a.reshape(1)
    return a[:n].reshape(n, -1)


def coordinates(flat: np.ndarray, count: int, components: int, order: str) -> tuple[np.ndarray, np.ndarray | None]:
    """(n, L * C) -> (positions (n, L, 2), depth (n, L) or None when C = 2)."""
    n = flat.shape[0]
    if order == "interleaved":
        v = flat.reshape(n, count, components)
    elif order == "planar":
        v = flat.reshape(n, components, count).transpose(0, 2, 1)
    else:
        raise ValueError(f"unknown landmark order {order!r}")
    return np.ascontiguousarray(v[..., :2]), (np.ascontiguousarray(v[..., 2]) if components == 3 else None)


def _refine_axis(lo: np.ndarray, c: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Offset in [-0.5, 0.5] of the vertex of the parabola through (-1, lo), (0, c), (1, hi)."""
    den = lo - 2.0 * c + hi
    ok = den < 0  # a proper maximum
    off = np.where(ok, 0.5 * (lo - hi) / np.where(ok, den, -1.0), 0.0)
    return np.clip(off, -0.5, 0.5)


def heatmap_peaks(hm: np.ndarray, refine: str = "gaussian") -> tuple[np.ndarray, np.ndarray]:
    """Heatmaps (n, L, H, W) of non-negative scores -> (peaks (n, L, 2) as heatmap px x, y; peak values (n, L)).

    A peak on the border is not refined along the axis that has no neighbour.
    """
    hm = np.asarray(hm, dtype=np.float64)
    n, count, h, w = hm.shape
    flat = hm.reshape(n, count, h * w)
    idx = flat.argmax(axis=2)
    iy, ix = np.divmod(idx, w)
    peak = np.take_along_axis(flat, idx[..., None], axis=2)[..., 0]
    x, y = ix.astype(np.float64), iy.astype(np.float64)
    if refine != "none" and (w > 1 or h > 1):
        def val(dy, dx):
            yy, xx = np.clip(iy + dy, 0, h - 1), np.clip(ix + dx, 0, w - 1)
            v = np.take_along_axis(flat, (yy * w + xx)[..., None], axis=2)[..., 0]
            return np.log(np.maximum(v, 1e-30)) if refine == "gaussian" else v

        c = val(0, 0)
        inner_x = (ix > 0) & (ix < w - 1)
        inner_y = (iy > 0) & (iy < h - 1)
        x = x + np.where(inner_x, _refine_axis(val(0, -1), c, val(0, 1)), 0.0)
        y = y + np.where(inner_y, _refine_axis(val(-1, 0), c, val(1, 0)), 0.0)
    return np.stack([x, y], axis=-1), peak


def heatmap_to_input_px(uv: np.ndarray, heatmap_size: tuple[int, int], input_size: tuple[int, int]) -> np.ndarray:
    """Heatmap px (*, 2) -> input px (*, 2); heatmap and input both span the input edge to edge."""
    sx = input_size[0] / heatmap_size[0]
    sy = input_size[1] / heatmap_size[1]
    uv = np.asarray(uv, dtype=np.float64)
    return np.stack([(uv[..., 0] + 0.5) * sx - 0.5, (uv[..., 1] + 0.5) * sy - 0.5], axis=-1)


# ----------------------------------------------------------------------------------------------
# anchors


def anchor_layers(strides, per_cell, sizes=None) -> list[tuple[int, int, list[float] | None]]:
    """Merge consecutive layers of equal stride: [(stride, anchors per cell, sizes or None)]."""
    out: list[tuple[int, int, list[float] | None]] = []
    for k, s in enumerate(strides):
        sz = None if sizes is None else list(sizes[k])
        if out and out[-1][0] == s:
            st, pc, prev = out[-1]
            out[-1] = (st, pc + per_cell[k], None if sz is None else prev + sz)
        else:
            out.append((s, per_cell[k], sz))
    return out


def anchor_counts(input_size: tuple[int, int], spec) -> list[int]:
    """Anchors of each layer of :func:`anchor_layers`, in :func:`make_anchors`' order (they add up to its K)."""
    w_in, h_in = input_size
    return [math.ceil(w_in / stride) * math.ceil(h_in / stride) * per
            for stride, per, _ in anchor_layers(spec.strides, spec.per_cell, spec.sizes)]


def make_anchors(input_size: tuple[int, int], spec) -> np.ndarray:
    """Anchors (K, 4) as cx, cy, w, h in crop_unit coordinates for an :class:`~.spec.AnchorSpec`."""
    w_in, h_in = input_size
    rows = []
    for stride, per, sizes in anchor_layers(spec.strides, spec.per_cell, spec.sizes):
        fw, fh = math.ceil(w_in / stride), math.ceil(h_in / stride)
        jj, ii = np.meshgrid(np.arange(fw), np.arange(fh))  # (fh, fw): row i, column j
        cx = (jj.reshape(-1) + spec.offset) * stride / w_in
        cy = (ii.reshape(-1) + spec.offset) * stride / h_in
        if sizes is None:
            aw = ah = np.ones(per)
        else:
            aw = np.asarray(sizes, np.float64) / w_in
            ah = np.asarray(sizes, np.float64) / h_in
        a = np.empty((cx.size, per, 4))
        a[..., 0], a[..., 1] = cx[:, None], cy[:, None]
        a[..., 2], a[..., 3] = aw[None, :], ah[None, :]
        rows.append(a.reshape(-1, 4))
    return np.concatenate(rows)


def decode_boxes(raw: np.ndarray, anchors: np.ndarray, encoding: str, scale=(1.0, 1.0, 1.0, 1.0),
                 variances=(0.1, 0.2)) -> np.ndarray:
    """Regressors (K, >=4) (first four columns: x, y, w, h) -> boxes (K, 4) cx, cy, w, h in crop_unit.

    ``anchor_linear`` (MediaPipe BlazeFace): ``cx = a_cx + r_x / scale_x * a_w``, ``w = r_w / scale_w * a_w``.
    ``anchor_ssd`` (SSD, RetinaFace): ``cx = a_cx + r_x * v0 * a_w``, ``w = a_w * exp(r_w * v1)``.
    ``anchor_distance`` (SCRFD, FCOS): the four columns are the distances from the anchor centre to the
    left, top, right and bottom edges in anchor sides: ``x0 = a_cx - r_0 a_w``, ``x1 = a_cx + r_2 a_w``.
    """
    r = np.asarray(raw, dtype=np.float64)[:, :4]
    a = anchors
    if encoding == "anchor_linear":
        sx, sy, sw, sh = scale
        return np.stack([a[:, 0] + r[:, 0] / sx * a[:, 2], a[:, 1] + r[:, 1] / sy * a[:, 3],
                         r[:, 2] / sw * a[:, 2], r[:, 3] / sh * a[:, 3]], axis=1)
    if encoding == "anchor_ssd":
        v0, v1 = variances
        return np.stack([a[:, 0] + r[:, 0] * v0 * a[:, 2], a[:, 1] + r[:, 1] * v0 * a[:, 3],
                         a[:, 2] * np.exp(np.clip(r[:, 2] * v1, -50, 50)),
                         a[:, 3] * np.exp(np.clip(r[:, 3] * v1, -50, 50))], axis=1)
    if encoding == "anchor_distance":
        x0, y0 = a[:, 0] - r[:, 0] * a[:, 2], a[:, 1] - r[:, 1] * a[:, 3]
        x1, y1 = a[:, 0] + r[:, 2] * a[:, 2], a[:, 1] + r[:, 3] * a[:, 3]
        return np.stack([(x0 + x1) / 2, (y0 + y1) / 2, x1 - x0, y1 - y0], axis=1)
    raise ValueError(f"unknown box encoding {encoding!r}")


def to_xyxy(boxes: np.ndarray, fmt: str) -> np.ndarray:
    """(K, 4) boxes in ``xyxy``, ``xywh`` or ``cxcywh`` -> (K, 4) x0, y0, x1, y1."""
    b = np.asarray(boxes, dtype=np.float64)
    if fmt == "xyxy":
        return b.copy()
    if fmt == "xywh":
        return np.stack([b[:, 0], b[:, 1], b[:, 0] + b[:, 2], b[:, 1] + b[:, 3]], axis=1)
    if fmt == "cxcywh":
        return np.stack([b[:, 0] - b[:, 2] / 2, b[:, 1] - b[:, 3] / 2, b[:, 0] + b[:, 2] / 2,
                         b[:, 1] + b[:, 3] / 2], axis=1)
    raise ValueError(f"unknown box format {fmt!r}")


def _iou(box: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    x0 = np.maximum(box[0], boxes[:, 0])
    y0 = np.maximum(box[1], boxes[:, 1])
    x1 = np.minimum(box[2], boxes[:, 2])
    y1 = np.minimum(box[3], boxes[:, 3])
    inter = np.clip(x1 - x0, 0, None) * np.clip(y1 - y0, 0, None)
    area = lambda b: np.clip(b[..., 2] - b[..., 0], 0, None) * np.clip(b[..., 3] - b[..., 1], 0, None)
    union = area(box) + area(boxes) - inter
    return np.where(union > 0, inter / np.where(union > 0, union, 1.0), 0.0)


def nms(boxes_xyxy: np.ndarray, scores: np.ndarray, iou: float, mode: str = "hard") -> tuple[np.ndarray, np.ndarray]:
    """Non-maximum suppression of (K, 4) xyxy boxes; returns (boxes, scores), best first.

    ``hard``: OpenCV's ``cv2.dnn.NMSBoxes``. ``weighted`` (MediaPipe's face detector): each kept box is
    the score-weighted mean of the boxes overlapping it by more than ``iou``.
    """
    b = np.asarray(boxes_xyxy, dtype=np.float64)
    s = np.asarray(scores, dtype=np.float64)
    if len(b) == 0:
        return b.reshape(0, 4), s.reshape(0)
    if mode == "hard":
        import cv2

        # NMSBoxes takes (x, y, w, h); scale unit boxes up so its float32 / integer-free maths is not coarse
        k = 1000.0
        xywh = np.stack([b[:, 0], b[:, 1], b[:, 2] - b[:, 0], b[:, 3] - b[:, 1]], axis=1) * k
        ranks = (s - s.min() + 1.0).tolist()   # NMSBoxes wants scores >= its threshold >= 0; only order matters
        keep = cv2.dnn.NMSBoxes(xywh.tolist(), ranks, 0.0, float(iou))
        keep = np.asarray(keep, dtype=np.int64).reshape(-1)
        keep = keep[np.argsort(-s[keep], kind="stable")]
        return b[keep], s[keep]
    order = np.argsort(-s, kind="stable")
    left = order
    out_b, out_s = [], []
    while left.size:
        best = left[0]
        ov = _iou(b[best], b[left])
        grp = left[ov > iou] if (ov > iou).any() else left[:1]
        if best not in grp:
            grp = np.concatenate([[best], grp])
        w = s[grp]
        out_b.append((b[grp] * w[:, None]).sum(axis=0) / w.sum())
        out_s.append(s[best])
        left = left[~np.isin(left, grp)]
    return np.array(out_b), np.array(out_s)
