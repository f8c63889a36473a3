"""The synthetic dense detector: finds each landmark's position colour in the pixels of a crop.

Every landmark is a template point (triangle, barycentric) with a known colour (its position code,
:mod:`capture.synth.texture`). The model reads only the image (N, 3, S, S), RGB levels 0..255:

1. **Coarse**: the image is average-pooled by ``coarse`` (8) and, per landmark, the cell whose
   colour is nearest to the landmark's colour is taken (arg-min of the squared colour distance,
   computed as one matrix product).
2. **Centroid**: in a ``window`` x ``window`` pixel window around that cell, pixels are weighted by
   a Gaussian of their colour distance to the target (sigma ``sigma1`` levels); the weighted mean
   pixel is the first estimate.
3. **Local linear fit**: in a second window around the first estimate, with sharper weights
   (``sigma2``), the colour field is fitted as ``c(x) = c_mean + A (x - x_mean)`` by weighted least
   squares and inverted: ``x* = x_mean + (A^T A)^-1 A^T (target - c_mean)``. Exact for a locally
   linear colour field, whatever the window's asymmetry; sub-pixel.
4. **Confidence**: the colour at ``x*`` (bilinear) is compared with the target:
   ``exp(-d^2 / (2 tau^2))``. An occluded landmark's colour is not in the image, so its best
   position shows another surface's colour and the confidence is low. The presence score is the
   mean confidence.

The module is plain torch (a readable reference) and is exported to ONNX with torch's TorchScript
exporter (no extra packages). Landmarks come out in crop pixels (pixel centres at integers).
"""

from __future__ import annotations

import io
import warnings
from dataclasses import dataclass

import numpy as np
import torch
import trimesh
from torch import nn

from capture.synth.texture import PositionCode

INPUT_NAME = "image"
OUTPUTS = ("landmarks", "confidence", "face_score")


class ColourCodeDetector(nn.Module):
    """Dense landmark detector by colour matching (see the module docstring).

    Args:
        targets: ``(L, 3)`` landmark colours (RGB levels).
        size: input side S (square crops); must be divisible by ``coarse``.
        coarse: pooling factor of the coarse search.
        window: side of the centroid window (pixels, even).
        sigma1: colour width (levels) of the centroid weights.
        fit_window, fit_sigma: side (even) and Gaussian width (pixels) of the quadratic fit.
        channel_weights: weights of R, G, B in the position solve. Blue codes depth (template z),
            which kinks at every mesh edge in the image; red and green (x, y) map almost linearly to
            pixels, so blue is down-weighted for precision (it still counts for the search and the
            confidence).
        tau: colour tolerance (levels) of the confidence.
        background: a pixel whose channels are all below this level is background.
    """

    def __init__(self, targets: np.ndarray, size: int = 768, coarse: int = 8, window: int = 24, sigma1: float = 8.0,
                 fit_window: int = 14, fit_sigma: float = 4.0, tau: float = 4.0, background: float = 16.0,
                 channel_weights: tuple[float, float, float] = (1.0, 1.0, 0.1)):
        super().__init__()
        if size % coarse:
            raise ValueError(f"size {size} must be divisible by coarse {coarse}")
        if window % 2 or fit_window % 2:
            raise ValueError(f"window sides must be even, got {window}, {fit_window}")
        self.size, self.coarse, self.sigma1, self.tau, self.background = size, coarse, sigma1, tau, background
        self.fit_window = fit_window
        t = torch.as_tensor(np.asarray(targets), dtype=torch.float32)
        self.register_buffer("targets", t)                          # (L, 3)
        self.register_buffer("targets_sq", (t * t).sum(1))          # (L,)
        self.register_buffer("offsets1", self._offsets(window))     # (K1, 2) x, y
        o = self._offsets(fit_window).double()
        self.register_buffer("offsets2", o.float())
        # Weighted least squares of a quadratic in the window offsets: a constant (6, K2) projection.
        X = torch.stack([torch.ones_like(o[:, 0]), o[:, 0], o[:, 1], o[:, 0] ** 2, o[:, 0] * o[:, 1], o[:, 1] ** 2], 1)
        W = torch.exp(-(o ** 2).sum(1) / (2 * fit_sigma ** 2))
        P = torch.linalg.solve(X.T @ (W[:, None] * X), X.T * W[None])
        self.register_buffer("fit", P.float())
        self.register_buffer("channel_sqrt_w", torch.tensor(channel_weights, dtype=torch.float32).sqrt())

    @staticmethod
    def _offsets(w: int) -> torch.Tensor:
        r = torch.arange(w, dtype=torch.float32) - (w - 1) / 2.0     # half-integers, symmetric about 0
        yy, xx = torch.meshgrid(r, r, indexing="ij")
        return torch.stack([xx.reshape(-1), yy.reshape(-1)], 1)

    def _gather(self, flat: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
        """Pixels at integer positions ``xy (N, M, 2)`` (clamped) of ``flat (N, S*S, 3)`` -> (N, M, 3)."""
        S = self.size
        xi = xy[..., 0].clamp(0, S - 1)
        yi = xy[..., 1].clamp(0, S - 1)
        idx = (yi * S + xi).long()
        return torch.gather(flat, 1, idx.unsqueeze(-1).expand(-1, -1, 3))

    def _window(self, flat: torch.Tensor, centre: torch.Tensor, offsets: torch.Tensor):
        """Window centre ``base (N, L, 2)`` (within half a pixel of ``centre``), pixel positions
        (N, L, K, 2) and colours (N, L, K, 3) of the even-sided window."""
        N, L = centre.shape[0], centre.shape[1]
        K = offsets.shape[0]
        base = torch.floor(centre) + 0.5                  # offsets are half-integers (even window)
        xy = (base.unsqueeze(2) + offsets.view(1, 1, K, 2)).clamp(0, self.size - 1)
        cols = self._gather(flat, xy.reshape(N, L * K, 2)).reshape(N, L, K, 3)
        return base, xy, cols

    def _solve2(self, J: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
        """Weighted least-squares step ``(J^T W J)^-1 J^T W r`` for J (..., 3, 2), r (..., 3) -> (..., 2)."""
        J = J * self.channel_sqrt_w.view(3, 1)
        r = r * self.channel_sqrt_w
        jtj = J.transpose(-1, -2) @ J
        p, q, s = jtj[..., 0, 0] + 1e-4, jtj[..., 0, 1], jtj[..., 1, 1] + 1e-4
        det = (p * s - q * q).clamp_min(1e-12)
        jtr = (J.transpose(-1, -2) @ r.unsqueeze(-1)).squeeze(-1)
        return torch.stack([s * jtr[..., 0] - q * jtr[..., 1], p * jtr[..., 1] - q * jtr[..., 0]], -1) / det.unsqueeze(-1)

    def _quadratic(self, flat: torch.Tensor, centre: torch.Tensor):
        """Fit c(u) = a0 + a1 ux + a2 uy + a3 ux^2 + a4 ux uy + a5 uy^2 around ``centre`` and solve
        c(u) = target by Gauss-Newton; returns the position (N, L, 2) and the colour residual (N, L)."""
        base, _, cols = self._window(flat, centre, self.offsets2)
        a = torch.einsum("mk,nlkc->nlmc", self.fit, cols)                   # (N, L, 6, 3)
        t = self.targets.unsqueeze(0)
        a0, a1, a2, a3, a4, a5 = (a[:, :, i] for i in range(6))
        u = self._solve2(torch.stack([a1, a2], -1), t - a0)
        u = u.clamp(-self.fit_window / 2.0, self.fit_window / 2.0)
        for _ in range(3):
            ux, uy = u[..., :1], u[..., 1:]
            c = a0 + a1 * ux + a2 * uy + a3 * ux * ux + a4 * ux * uy + a5 * uy * uy
            J = torch.stack([a1 + 2 * a3 * ux + a4 * uy, a2 + a4 * ux + 2 * a5 * uy], -1)
            u = (u + self._solve2(J, t - c)).clamp(-self.fit_window / 2.0, self.fit_window / 2.0)
        ux, uy = u[..., :1], u[..., 1:]
        c = a0 + a1 * ux + a2 * uy + a3 * ux * ux + a4 * ux * uy + a5 * uy * uy
        return base + u, ((t - c) ** 2).sum(-1)

    def forward(self, image: torch.Tensor):
        N = image.shape[0]
        S, f = self.size, self.coarse
        flat = image.permute(0, 2, 3, 1).reshape(N, S * S, 3)
        # 1. coarse cell of the nearest colour; cells touching the background are not candidates
        pooled = nn.functional.avg_pool2d(image, f)                      # (N, 3, S/f, S/f)
        bg = (image.amax(1, keepdim=True) < self.background).float()
        mixed = nn.functional.max_pool2d(bg, f)                          # (N, 1, S/f, S/f)
        g = S // f
        pc = pooled.permute(0, 2, 3, 1).reshape(N, g * g, 3)
        d2 = (pc * pc).sum(-1, keepdim=True) - 2.0 * pc @ self.targets.t() + self.targets_sq   # (N, g*g, L)
        d2 = d2 + 1e6 * mixed.reshape(N, g * g, 1)
        cell = torch.argmin(d2, dim=1)                                    # (N, L)
        cy = torch.div(cell, g, rounding_mode="floor")
        cx = cell - cy * g
        centre = torch.stack([cx, cy], -1).float() * f + (f - 1) / 2.0    # (N, L, 2)
        t = self.targets.view(1, -1, 1, 3)
        # 2. Gaussian-weighted (in colour) centroid in a window around the cell
        _, xy, cols = self._window(flat, centre, self.offsets1)
        w = torch.exp(-((cols - t) ** 2).sum(-1) / (2 * self.sigma1 ** 2))   # (N, L, K)
        sw = w.sum(-1, keepdim=True).clamp_min(1e-12)
        est = (w.unsqueeze(-1) * xy).sum(2) / sw
        # 3. two passes of the local quadratic fit, each centred on the previous estimate
        est, res = self._quadratic(flat, est)
        est, res = self._quadratic(flat, est)
        est = est.clamp(0.0, S - 1.0)
        # 4. confidence from the fit residual and the colour found at the estimate (bilinear)
        x0 = torch.floor(est)
        fr = est - x0
        c00 = self._gather(flat, x0)
        c10 = self._gather(flat, x0 + torch.tensor([1.0, 0.0]))
        c01 = self._gather(flat, x0 + torch.tensor([0.0, 1.0]))
        c11 = self._gather(flat, x0 + 1.0)
        fx, fy = fr[..., :1], fr[..., 1:]
        col = (c00 * (1 - fx) + c10 * fx) * (1 - fy) + (c01 * (1 - fx) + c11 * fx) * fy
        dist2 = torch.maximum(((col - self.targets.unsqueeze(0)) ** 2).sum(-1), res)
        conf = torch.exp(-dist2 / (2 * self.tau ** 2))
        return est, conf, conf.mean(-1)


@dataclass
class LandmarkSet:
    """Landmarks on the template: triangle index, barycentric coordinates, template points."""

    face_index: np.ndarray      # (L,) int
    barycentric: np.ndarray     # (L, 3)
    points: np.ndarray          # (L, 3) mm, template frame


def sample_landmarks(template: trimesh.Trimesh, count: int, seed: int = 0, candidates: int = 60_000) -> LandmarkSet:
    """``count`` landmarks spread over the front of the template by farthest-point sampling.

    Candidates are area-uniform random surface points on triangles facing forward (template normal
    z > 0, the face rather than the back of the head); farthest-point sampling then keeps ``count``
    of them, starting from the one nearest to the bounding-box centre's projection. Deterministic
    for a given template, count and seed.
    """
    v = np.asarray(template.vertices, dtype=np.float64)
    f = np.asarray(template.faces, dtype=np.int64)
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(n, axis=1)
    front = (n[:, 2] > 0) & (area > 0)
    if not front.any():
        front = area > 0
    rng = np.random.default_rng(seed)
    prob = np.where(front, area, 0.0)
    fi = rng.choice(len(f), size=max(candidates, 4 * count), p=prob / prob.sum())
    r = rng.random((len(fi), 2))
    s = np.sqrt(r[:, 0])
    bary = np.stack([1 - s, s * (1 - r[:, 1]), s * r[:, 1]], 1)
    pts = np.einsum("nk,nkc->nc", bary, tri[fi])
    centre = 0.5 * (v.min(0) + v.max(0))
    centre[2] = v[:, 2].max()
    chosen = np.empty(count, dtype=np.int64)
    chosen[0] = int(np.argmin(np.linalg.norm(pts - centre, axis=1)))
    dmin = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    for i in range(1, count):
        chosen[i] = int(np.argmax(dmin))
        dmin = np.minimum(dmin, np.linalg.norm(pts - pts[chosen[i]], axis=1))
    return LandmarkSet(fi[chosen], bary[chosen], pts[chosen])


def embedding_dict(name: str, landmarks: LandmarkSet, source: str) -> dict:
    """The actor-package landmark embedding (docs/detector_spec.md)."""
    return {"detector": name, "count": int(len(landmarks.face_index)),
            "face_index": [int(i) for i in landmarks.face_index],
            "barycentric": [[float(x) for x in b] for b in landmarks.barycentric], "source": source}


def spec_dict(name: str, count: int, size: int, first_frame: str = "full_frame", margin: float = 0.25,
              threshold: float = 0.3) -> dict:
    """The detector spec JSON (docs/detector_spec.md, format 1) of a synthetic dense detector."""
    return {
        "format": "capture-detector",
        "version": 1,
        "name": name,
        "kind": "dense",
        "input": {"name": INPUT_NAME, "layout": "NCHW", "size": [size, size], "color": "RGB", "dtype": "float32",
                  "scale": 1.0, "mean": [0.0, 0.0, 0.0], "std": [1.0, 1.0, 1.0]},
        "query": None,
        "crop": {"margin": margin, "align": None, "first_frame": first_frame, "track": True},
        "outputs": {"landmarks": {"name": OUTPUTS[0], "frame": "crop_pixels"},
                    "confidence": {"name": OUTPUTS[1], "kind": "probability"},
                    "presence": {"name": OUTPUTS[2], "threshold": threshold}},
        "landmarks": {"count": int(count)},
    }


def export_onnx(detector: ColourCodeDetector) -> bytes:
    """The detector as ONNX bytes (opset 17, dynamic batch N, static S x S input)."""
    buf = io.BytesIO()
    dummy = torch.zeros(1, 3, detector.size, detector.size)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(detector, (dummy,), buf, dynamo=False, opset_version=17, input_names=[INPUT_NAME],
                          output_names=list(OUTPUTS),
                          dynamic_axes={INPUT_NAME: {0: "N"}, OUTPUTS[0]: {0: "N"}, OUTPUTS[1]: {0: "N"},
                                        OUTPUTS[2]: {0: "N"}})
    return buf.getvalue()


def landmark_colours(vertex_colours: np.ndarray, faces: np.ndarray, landmarks: LandmarkSet) -> np.ndarray:
    """``(L, 3)`` colours of landmarks: the barycentric mix of their triangle's vertex colours (exactly
    what the rasteriser paints there)."""
    return np.einsum("lk,lkc->lc", landmarks.barycentric, np.asarray(vertex_colours)[np.asarray(faces)[landmarks.face_index]])


def build_detector(targets: np.ndarray, size: int = 768) -> ColourCodeDetector:
    """The detector of landmarks with colours ``targets (L, 3)``."""
    return ColourCodeDetector(targets, size=size)


def square_crop(frame: np.ndarray, box: tuple[float, float, float, float], margin: float, size: int):
    """Square crop of ``frame (H, W, 3)`` around ``box (x0, y0, x1, y1)`` enlarged by ``margin`` of its
    size on each side, resampled (bilinear) to ``size x size``.

    Returns the crop and the 2x3 affine ``M`` with ``crop_px = M @ [x, y, 1]`` (pixel centres at integers);
    frame pixels are ``(crop_px - M[:, 2]) / M[0, 0]``.
    """
    import cv2

    x0, y0, x1, y1 = box
    side = max(x1 - x0, y1 - y0) * (1.0 + 2.0 * margin)
    cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
    s = size / side
    # crop pixel u covers frame [cx - side/2 + u/s, ...]: u + 0.5 = s (x + 0.5 - (cx - side/2))
    M = np.array([[s, 0.0, s * (0.5 - (cx - side / 2)) - 0.5], [0.0, s, s * (0.5 - (cy - side / 2)) - 0.5]])
    crop = cv2.warpAffine(frame, M, (size, size), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                          borderValue=(0, 0, 0))
    return crop, M
