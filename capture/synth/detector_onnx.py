"""The synthetic dense detector: finds each landmark's position colour in the pixels of a crop.

Every landmark is a template point (triangle, barycentric) with a known colour (its position code,
:mod:`capture.synth.texture`). The model reads only the image (N, 3, S, S), RGB levels 0..255:

1. **Coarse**: the image is average-pooled by ``coarse`` (8) and, per landmark, the cell whose
   colour is nearest to the landmark's colour is taken (arg-min of the squared colour distance,
   computed as one matrix product).
2. **Centroid**: in a ``window`` x ``window`` pixel window around that cell, pixels are weighted by
   a Gaussian of their colour distance to the target (sigma ``sigma1`` levels); the weighted mean
   pixel is the first estimate.
3. **Robust local quadratic fit** (twice, each centred on the previous estimate): in a
   ``fit_window`` x ``fit_window`` window (26 px, Gaussian weights of ``fit_sigma`` 7 px) the
   colour field minus the target is fitted as a quadratic in the pixel offset by weighted least
   squares (a 6 x 6 solve per landmark, unrolled Cholesky). Background pixels get no weight, and
   ``irls`` (3) reweighting passes give every pixel a Cauchy weight of its colour residual (scale
   ``robust``, 3 levels): pixels of another surface (across a lip or eyelid opening, behind the
   nose) drop out instead of bending the fit. The quadratic is then solved for the target colour
   by Gauss-Newton; sub-pixel. The window is wide because the code spans only about one colour
   level per mm: the frames are ordered-dithered (:func:`capture.synth.texture.dither_to_uint8`)
   and the fit averages the dither away (with plain rounding the median error was 0.35 px on the
   sample actor at 1280x720; 0.12 px with the dither and this window).
4. **Confidence**: the product of
   * the colour match: ``exp(-d^2 / (2 tau^2))`` with ``d`` the larger of the colour distance at
     the estimate (bilinear) and the fit's residual there. An occluded landmark's colour is not
     in the image, so its best position shows another surface's colour and this is low;
   * the code's consistency: ramps (0 at half the threshold, 1 at it) of the fraction of the
     window's foreground weight that the quadratic explains (``min_inlier``) and of the same
     fraction under a narrow Gaussian (``near_sigma``) at the estimate (``min_near``): low next
     to an occluding contour or an opening, where the window mixes surfaces;
   * the viewing angle: a ramp of the cosine estimated from the fitted colour gradient (the
     code's template mm per pixel are stretched by 1 / cos across a surface seen obliquely) below
     ``min_cos``: grazing landmarks at silhouettes are flagged rather than reported wrong.

   The presence score is the mean confidence.

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


INPUT_NAME = "image"
OUTPUTS = ("landmarks", "confidence", "face_score")


def _cholesky_solve(G: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """Solve ``G X = B`` for symmetric positive definite ``G (..., n, n)`` and ``B (..., n, m)``.

    Unrolled Cholesky with Python loops over the (small, static) n, so it traces to elementwise ONNX
    ops (ONNX has no linear solver). The caller regularises G.
    """
    n = G.shape[-1]
    Lc: list[list[torch.Tensor]] = [[G[..., 0, 0]] * n for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            acc = G[..., i, j]
            for k in range(j):
                acc = acc - Lc[i][k] * Lc[j][k]
            Lc[i][j] = torch.sqrt(acc.clamp_min(1e-12)) if i == j else acc / Lc[j][j]
    y: list[torch.Tensor] = []
    for i in range(n):                                  # forward: L y = B
        acc = B[..., i, :]
        for k in range(i):
            acc = acc - Lc[i][k].unsqueeze(-1) * y[k]
        y.append(acc / Lc[i][i].unsqueeze(-1))
    x: list[torch.Tensor] = [y[0]] * n
    for i in reversed(range(n)):                        # backward: L^T x = y
        acc = y[i]
        for k in range(i + 1, n):
            acc = acc - Lc[k][i].unsqueeze(-1) * x[k]
        x[i] = acc / Lc[i][i].unsqueeze(-1)
    return torch.stack(x, -2)


def _offsets(w: int, stride: int = 1) -> torch.Tensor:
    """(K, 2) x, y offsets of a w x w window: half-integers symmetric about 0; every ``stride``-th
    one outward from the centre (+-0.5, +-(0.5 + stride), ...)."""
    h = torch.arange(0.5, w / 2.0, float(stride), dtype=torch.float32)
    r = torch.cat([-h.flip(0), h])
    yy, xx = torch.meshgrid(r, r, indexing="ij")
    return torch.stack([xx.reshape(-1), yy.reshape(-1)], 1)


class FitWindow(nn.Module):
    """Constants of a robust quadratic fit window (buffers only).

    ``offsets (K, 2)`` pixel offsets; ``design (K, 6)`` the quadratic terms of the offsets scaled to
    [-1, 1] (well conditioned) and ``design_scale (6,)`` back to pixel units; ``design_outer (K, 36)``
    the rows' outer products (for the weighted normal equations); ``spatial (K,)`` Gaussian weights of
    width ``sigma``; ``near (K,)`` a narrow Gaussian (``near_sigma``) divided by ``spatial`` and
    normalised, so that ``(w * near).sum()`` is the explained fraction of the pixels right at the centre.
    """

    def __init__(self, side: int, sigma: float, stride: int, near_sigma: float):
        super().__init__()
        o = _offsets(side, stride)
        self.half = side / 2.0
        n = o / self.half
        d = torch.stack([torch.ones_like(n[:, 0]), n[:, 0], n[:, 1], n[:, 0] ** 2, n[:, 0] * n[:, 1], n[:, 1] ** 2], 1)
        h = self.half
        spatial = torch.exp(-(o ** 2).sum(1) / (2 * sigma ** 2))
        near = torch.exp(-(o ** 2).sum(1) / (2 * near_sigma ** 2))
        self.register_buffer("offsets", o)
        self.register_buffer("design", d)
        self.register_buffer("design_scale", torch.tensor([1.0, 1 / h, 1 / h, 1 / h ** 2, 1 / h ** 2, 1 / h ** 2]))
        self.register_buffer("design_outer", (d[:, :, None] * d[:, None, :]).reshape(-1, 36))
        self.register_buffer("spatial", spatial)
        self.register_buffer("near", near / near.sum() / spatial)


class ColourCodeDetector(nn.Module):
    """Dense landmark detector by colour matching (see the module docstring).

    Args:
        targets: ``(L, 3)`` landmark colours (RGB levels).
        levels_per_mm: ``(3,)`` colour levels per template mm of the code's channels (for the
            grazing-angle test: the fitted colour gradient, turned into template mm per pixel, is
            stretched by 1 / cos(angle) across a surface seen at a grazing angle).
        size: input side S (square crops); must be divisible by ``coarse``.
        coarse: pooling factor of the coarse search.
        window: side of the centroid window (pixels, even).
        sigma1: colour width (levels) of the centroid weights.
        pre_window, pre_sigma, pre_irls: window side, Gaussian width and reweighting passes of the
            first robust fit (a smaller, cheaper first fit measured less accurate: 0.21 against 0.16 px
            RMS on the sample actor, frontal).
        fit_window, fit_sigma: side (even) and Gaussian width (pixels) of the final robust fit.
        fit_stride: the fit reads every ``fit_stride``-th pixel of its window (crops of a face are
            usually upsampled, so neighbouring crop pixels repeat each other).
        robust: colour residual scale (levels) of the fit's Cauchy weights; pixels that the local
            quadratic does not explain (another surface, an opening, the background) drop out.
        irls: reweighting passes of the final robust fit.
        channel_weights: weights of R, G, B in the position solve. Blue codes depth (template z),
            which kinks at every mesh edge in the image; red and green (x, y) map almost linearly to
            pixels, so blue is down-weighted for precision (it still counts for the search and the
            confidence).
        tau: colour tolerance (levels) of the confidence.
        min_inlier: fraction of the fit window's foreground weight that must be explained by the
            local quadratic for full confidence (below it confidence falls to 0 at ``min_inlier/2``).
        min_cos: cosine of the viewing angle below which confidence falls (to 0 at ``min_cos/2``).
        background: a pixel whose channels are all below this level is background.
    """

    def __init__(self, targets: np.ndarray, levels_per_mm=(1.0, 1.0, 1.0), size: int = 768, coarse: int = 8,
                 window: int = 24, sigma1: float = 8.0,
                 pre_window: int = 26, pre_sigma: float = 7.0, pre_irls: int = 3,
                 fit_window: int = 26, fit_sigma: float = 7.0, fit_stride: int = 1,
                 robust: float = 3.0, irls: int = 3, tau: float = 4.0, min_inlier: float = 0.6,
                 min_cos: float = 0.15, near_sigma: float = 4.0, min_near: float = 0.8, background: float = 16.0,
                 channel_weights: tuple[float, float, float] = (1.0, 1.0, 0.1)):
        super().__init__()
        if size % coarse:
            raise ValueError(f"size {size} must be divisible by coarse {coarse}")
        if window % 2 or fit_window % 2 or pre_window % 2:
            raise ValueError(f"window sides must be even, got {window}, {pre_window}, {fit_window}")
        self.size, self.coarse, self.sigma1, self.tau, self.background = size, coarse, sigma1, tau, background
        self.robust, self.irls, self.pre_irls = robust, irls, pre_irls
        self.min_inlier, self.min_cos, self.min_near = min_inlier, min_cos, min_near
        t = torch.as_tensor(np.asarray(targets), dtype=torch.float32)
        self.register_buffer("targets", t)                          # (L, 3)
        self.register_buffer("targets_sq", (t * t).sum(1))          # (L,)
        self.register_buffer("offsets1", _offsets(window))     # (K1, 2) x, y
        self.pre = FitWindow(pre_window, pre_sigma, 1, near_sigma)
        self.fit = FitWindow(fit_window, fit_sigma, fit_stride, near_sigma)
        self.register_buffer("channel_sqrt_w", torch.tensor(channel_weights, dtype=torch.float32).sqrt())
        self.register_buffer("mm_per_level", 1.0 / torch.as_tensor(np.asarray(levels_per_mm), dtype=torch.float32))

    def _gather(self, flat: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
        """Pixels at integer positions ``xy (N, M, 2)`` (clamped) of ``flat (N, S*S, 3)`` -> (N, M, 3)."""
        S = self.size
        xi = xy[..., 0].clamp(0, S - 1)
        yi = xy[..., 1].clamp(0, S - 1)
        idx = (yi * S + xi).long()
        return torch.gather(flat, 1, idx.unsqueeze(-1).expand(-1, -1, 3))

    def _window(self, flat: torch.Tensor, centre: torch.Tensor, offsets: torch.Tensor):
        """Window centre ``base (N, L, 2)`` (within half a pixel of ``centre``), pixel positions
        (N, L, K, 2) and colours (N, L, K, 3) of the even-sided window (pixels outside the image
        read as background)."""
        N, L = centre.shape[0], centre.shape[1]
        K = offsets.shape[0]
        base = torch.floor(centre) + 0.5                  # offsets are half-integers (even window)
        xy = base.unsqueeze(2) + offsets.view(1, 1, K, 2)
        inside = ((xy >= 0) & (xy <= self.size - 1)).all(-1, keepdim=True).float()
        cols = self._gather(flat, xy.reshape(N, L * K, 2)).reshape(N, L, K, 3) * inside
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

    @staticmethod
    def _weighted_fit(win: "FitWindow", cols: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """Quadratic coefficients (N, L, 6, 3) of the colours ``cols (N, L, K, 3)`` with weights (N, L, K)
        in the scaled offsets of ``win``."""
        N, L = w.shape[0], w.shape[1]
        G = (w @ win.design_outer).reshape(N, L, 6, 6)
        G = G + (1e-5 * (w.sum(-1) + 1e-3)).view(N, L, 1, 1) * torch.eye(6)   # against degenerate windows
        B = win.design.t() @ (w.unsqueeze(-1) * cols)                        # (N, L, 6, 3)
        return _cholesky_solve(G, B)

    def _quadratic(self, flat: torch.Tensor, centre: torch.Tensor, win: "FitWindow", irls: int):
        """Robust fit of c(u) = a0 + a1 ux + a2 uy + a3 ux^2 + a4 ux uy + a5 uy^2 around ``centre`` and
        the solve of c(u) = target by Gauss-Newton.

        Weights: the spatial Gaussian, zero on background pixels, and Cauchy weights of the colour
        residual (``irls`` passes), over the window ``win``. Returns the position (N, L, 2), the colour
        residual at it (N, L), the inlier fraction of the foreground weight (N, L), the same under the
        narrow Gaussian (N, L) and the Jacobian dc/du there (N, L, 3, 2).
        """
        base, _, cols = self._window(flat, centre, win.offsets)
        fg = (cols.amax(-1) >= self.background).float()                   # (N, L, K)
        t = self.targets.unsqueeze(0)
        cols = cols - t.unsqueeze(2)                                        # fit the difference to the target
        w0 = fg * win.spatial
        w = w0
        a = self._weighted_fit(win, cols, w)
        for _ in range(irls):
            r2 = ((cols - win.design @ a) ** 2).sum(-1)
            w = w0 / (1.0 + r2 / (self.robust ** 2))
            a = self._weighted_fit(win, cols, w)
        a = a * win.design_scale.view(6, 1)                                 # coefficients in pixel units
        inlier = w.sum(-1) / w0.sum(-1).clamp_min(1e-6)
        near = (w * win.near).sum(-1)
        t = torch.zeros_like(t)                                             # solve c(u) - target = 0
        a0, a1, a2, a3, a4, a5 = (a[:, :, i] for i in range(6))
        u = self._solve2(torch.stack([a1, a2], -1), t - a0)
        u = u.clamp(-win.half, win.half)
        for _ in range(3):
            ux, uy = u[..., :1], u[..., 1:]
            c = a0 + a1 * ux + a2 * uy + a3 * ux * ux + a4 * ux * uy + a5 * uy * uy
            J = torch.stack([a1 + 2 * a3 * ux + a4 * uy, a2 + a4 * ux + 2 * a5 * uy], -1)
            u = (u + self._solve2(J, t - c)).clamp(-win.half, win.half)
        ux, uy = u[..., :1], u[..., 1:]
        c = a0 + a1 * ux + a2 * uy + a3 * ux * ux + a4 * ux * uy + a5 * uy * uy
        J = torch.stack([a1 + 2 * a3 * ux + a4 * uy, a2 + a4 * ux + 2 * a5 * uy], -1)
        return base + u, ((t - c) ** 2).sum(-1), inlier, near, J

    def _view_cosine(self, J: torch.Tensor) -> torch.Tensor:
        """Estimated cosine of the viewing angle (N, L) from the colour Jacobian (N, L, 3, 2): the ratio
        of the smaller to the larger stretch of template mm per pixel."""
        Jm = J * self.mm_per_level.view(3, 1)
        m = Jm.transpose(-1, -2) @ Jm                                       # (N, L, 2, 2)
        p, q, s = m[..., 0, 0], m[..., 0, 1], m[..., 1, 1]
        half_tr = 0.5 * (p + s)
        disc = torch.sqrt((0.25 * (p - s) ** 2 + q * q).clamp_min(0.0))
        lo, hi = (half_tr - disc).clamp_min(0.0), (half_tr + disc).clamp_min(1e-12)
        return torch.sqrt(lo / hi)

    @staticmethod
    def _ramp(x: torch.Tensor, lo: float) -> torch.Tensor:
        """0 at ``lo / 2``, 1 at ``lo`` and above, linear between."""
        return ((x - 0.5 * lo) / (0.5 * lo)).clamp(0.0, 1.0)

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
        # 3. the robust local quadratic fit in a small, then in the wide window, each centred on the
        #    previous estimate
        est, _, _, _, _ = self._quadratic(flat, est, self.pre, self.pre_irls)
        est, res, inlier, near, J = self._quadratic(flat, est, self.fit, self.irls)
        ok = (est == est).all(-1)                                          # not NaN (a degenerate window)
        est = torch.where(ok.unsqueeze(-1), est, centre).clamp(0.0, S - 1.0)
        # 4. confidence: the colour found at the estimate (bilinear) and the fit residual against the
        #    target, times ramps of the local code's consistency and of the viewing angle
        x0 = torch.floor(est)
        fr = est - x0
        c00 = self._gather(flat, x0)
        c10 = self._gather(flat, x0 + torch.tensor([1.0, 0.0]))
        c01 = self._gather(flat, x0 + torch.tensor([0.0, 1.0]))
        c11 = self._gather(flat, x0 + 1.0)
        fx, fy = fr[..., :1], fr[..., 1:]
        col = (c00 * (1 - fx) + c10 * fx) * (1 - fy) + (c01 * (1 - fx) + c11 * fx) * fy
        dist2 = torch.maximum(((col - self.targets.unsqueeze(0)) ** 2).sum(-1), res)
        conf = (torch.exp(-dist2 / (2 * self.tau ** 2)) * self._ramp(inlier, self.min_inlier)
                * self._ramp(self._view_cosine(J), self.min_cos) * self._ramp(near, self.min_near))
        conf = torch.where(ok & (conf == conf), conf, torch.zeros_like(conf))
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


def build_detector(targets: np.ndarray, size: int = 768, levels_per_mm=(1.0, 1.0, 1.0), **options) -> ColourCodeDetector:
    """The detector of landmarks with colours ``targets (L, 3)`` under a code of ``levels_per_mm (3,)``
    (:attr:`capture.synth.texture.PositionCode.levels_per_mm`); ``options`` override
    :class:`ColourCodeDetector`'s defaults."""
    return ColourCodeDetector(targets, levels_per_mm, size=size, **options)


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
