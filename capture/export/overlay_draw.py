"""Drawing one overlay frame (pure: arrays in, a BGR image out; no files). Used by :mod:`capture.export.overlay`.

Layers (``ExportOptions.overlay_layers``; every size scales with the frame height, ``u = height / 720``):

* ``mesh``: the fitted mesh rendered with the project's z-buffer rasteriser
  (:func:`capture.synth.raster.rasterize`, the one ``capture synth`` uses) and Lambert-shaded
  (:mod:`capture.synth.look`), blended at 40 % in a pale blue so the face stays visible beneath. The
  render covers the face's bounding box at no more than :data:`RASTER_HEIGHT` pixels high and is
  scaled up to the frame (the shading is smooth; the lines below are drawn at full resolution).
  Only triangles facing the camera are rasterised.
* ``wireframe``: the edges of the visible front-facing triangles, thin and translucent.
* ``contours``, crisp: the occluding silhouette (edges between a triangle facing the camera and one
  facing away) and the template's border in yellow; the template's openings (lid margins, inner lip
  line), the occluding rims of lids and lips (silhouette edges within :data:`OPENING_RINGS` triangle
  rings of an opening) and the brow lines (:mod:`capture.export.features`) in magenta. Hidden parts are not drawn: an
  edge is drawn where it is no farther than the rendered surface (z-buffer) plus
  :data:`DEPTH_TOLERANCE_MM`.
* ``landmarks``: each detected landmark as a small dot and its residual (detected -> fitted) as a
  line magnified :data:`RESIDUAL_GAIN` times, both coloured by the residual's length: green up to
  ``u`` px, through yellow, red from ``5 u`` px. Landmarks with confidence below 0.5 are small grey
  rings (they carry little weight in the fit).
* ``header``: one line at the top left on a dark band: frame, time code (``HH:MM:SS:FF`` at the
  video's rate), reprojection RMS over the confident landmarks (px), and flags: ``NO FACE`` (the
  detector found none), ``BRIDGED`` (the frame's pose is bridged from its neighbours), ``LOW CONF``
  (median landmark confidence below 0.5), ``SKIPPED``; then the residual colour key.

Projection: vertices (camera frame, mm) through the camera's K and OpenCV distortion
(``cv2.projectPoints``), so lines sit where the lens put the face.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from capture.export.features import FaceFeatures

RASTER_HEIGHT = 200               # px: the shaded render's largest height (then scaled to the frame)
MESH_BGR = np.array([255.0, 215.0, 170.0])   # pale blue, times the Lambert intensity
MESH_ALPHA = 0.4
WIRE_BGR = (255, 235, 200)
WIRE_ALPHA = 0.35
SILHOUETTE_BGR = (0, 220, 255)    # yellow
FEATURE_BGR = (255, 90, 255)      # magenta
LOW_CONF_BGR = (150, 150, 150)
DEPTH_TOLERANCE_MM = 4.0
RESIDUAL_GAIN = 4.0
OPENING_RINGS = 6                 # silhouette edges this close (triangle rings) to an opening are its rim
CONFIDENT = 0.5
_SHIFT = 4                        # sub-pixel drawing: coordinates * 2**4
_ONE = 1 << _SHIFT


@dataclass(frozen=True)
class Topology:
    """What the overlay precomputes once per take from the template's triangles.

    ``edges (E, 2)`` unique undirected edges; ``face_edges (F, 3)`` edge ids per triangle;
    ``edge_faces (E, 2)`` the (up to two) triangles of each edge, -1 where there is none.
    """

    faces: np.ndarray
    edges: np.ndarray
    face_edges: np.ndarray
    edge_faces: np.ndarray
    features: FaceFeatures
    near_opening: np.ndarray     # (V,) bool: within OPENING_RINGS rings of an opening's loop (lid, lip rims)

    @classmethod
    def of(cls, faces: np.ndarray, features: FaceFeatures | None = None) -> "Topology":
        from capture.export.features import face_features

        f = np.asarray(faces, np.int64)
        e = np.stack([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], 1).reshape(-1, 2)
        e.sort(axis=1)
        edges, inverse = np.unique(e, axis=0, return_inverse=True)
        inverse = inverse.reshape(-1)
        face_of = np.repeat(np.arange(len(f)), 3)
        order = np.argsort(inverse, kind="stable")
        starts = np.searchsorted(inverse[order], np.arange(len(edges)))
        counts = np.bincount(inverse, minlength=len(edges))
        edge_faces = np.full((len(edges), 2), -1, np.int64)
        edge_faces[:, 0] = face_of[order[starts]]
        two = counts >= 2
        edge_faces[two, 1] = face_of[order[starts[two] + 1]]
        features = features if features is not None else face_features(f)
        near = np.zeros(int(f.max()) + 1, bool)
        for loop in features.openings:
            near[loop] = True
        for _ in range(OPENING_RINGS):   # grow by one ring of triangles
            near[f[near[f].any(1)].ravel()] = True
        return cls(f, edges, inverse.reshape(-1, 3), edge_faces, features, near)


def project(vertices: np.ndarray, camera) -> np.ndarray:
    """(V, 3) camera-frame mm -> (V, 2) pixels through K and the OpenCV distortion of ``camera``."""
    import cv2

    K = np.asarray(camera.K, np.float64)
    dist = np.asarray(getattr(camera, "dist", ()), np.float64).reshape(-1)
    pts, _ = cv2.projectPoints(np.asarray(vertices, np.float64).reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K,
                               dist if dist.size else None)
    return pts.reshape(-1, 2)


def vertex_normals_fast(vertices: np.ndarray, faces: np.ndarray, face_normals: np.ndarray) -> np.ndarray:
    """Unit vertex normals (V, 3) from area-weighted ``face_normals (F, 3)`` (cross products, length 2 x area);
    the same as :func:`capture.synth.look.vertex_normals`, summed with ``np.bincount``."""
    V = len(vertices)
    idx = np.asarray(faces, np.int64).ravel()
    n = np.stack([np.bincount(idx, np.repeat(face_normals[:, c], 3), minlength=V) for c in range(3)], 1)
    return n / np.linalg.norm(n, axis=1, keepdims=True).clip(1e-12)


def error_colour(err: np.ndarray, good: float, bad: float) -> np.ndarray:
    """BGR (N, 3) float: green at ``err <= good``, yellow halfway, red at ``err >= bad``."""
    x = np.clip((np.asarray(err, np.float64) - good) / max(bad - good, 1e-9), 0.0, 1.0)
    g = np.where(x < 0.5, 220.0, 220.0 * (1 - x) * 2)
    r = np.where(x < 0.5, 440.0 * x + 30.0, 255.0)
    return np.stack([np.full_like(x, 30.0), g, np.minimum(r, 255.0)], 1)


def _fixed(p: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(p, np.float64) * _ONE).astype(np.int32)


def _segments(img, px: np.ndarray, pairs: np.ndarray, colour, thickness: int) -> None:
    import cv2

    if len(pairs):
        cv2.polylines(img, list(_fixed(px[pairs])), False, colour, thickness, cv2.LINE_AA, _SHIFT)


class FrameRenderer:
    """Draws the overlay of frames of one take: ``render(image, fit, detection) -> image``."""

    def __init__(self, topology: Topology, camera, image_size: tuple[int, int], fps: float,
                 layers: tuple[str, ...]):
        self.topo, self.camera, self.fps = topology, camera, float(fps)
        self.size = (int(image_size[0]), int(image_size[1]))
        self.layers = set(layers)
        self.u = self.size[1] / 720.0
        self.line = max(1, int(round(1.6 * self.u)))

    # -- mesh -----------------------------------------------------------------------------------
    def _mesh(self, out: np.ndarray, v: np.ndarray) -> None:
        import cv2

        from capture.synth.look import lambert
        from capture.synth.raster import rasterize

        w, h = self.size
        f = self.topo.faces
        px = project(v, self.camera)
        ok_v = np.isfinite(px).all(1) & (v[:, 2] > 1e-3) & (np.abs(px) < 1e6).all(1)
        f0, f1, f2 = f[:, 0], f[:, 1], f[:, 2]
        v0 = v[f0]
        e1, e2 = v[f1] - v0, v[f2] - v0
        normal = np.stack([e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1], e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
                           e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]], 1)    # (F, 3): e1 x e2
        # facing the camera (at the origin): the normal points back at it; columns, not reductions over 3
        front = ((normal[:, 0] * v0[:, 0] + normal[:, 1] * v0[:, 1] + normal[:, 2] * v0[:, 2] < 0)
                 & ok_v[f0] & ok_v[f1] & ok_v[f2])
        if not front.any():
            return
        used = np.zeros(len(v), bool)
        used[f[front].ravel()] = True
        lo = np.floor(px[used].min(0)).clip(0, [w - 1, h - 1]).astype(int)
        hi = np.ceil(px[used].max(0)).clip(0, [w - 1, h - 1]).astype(int)
        bw, bh = hi - lo + 1
        if bw < 2 or bh < 2:
            return
        r = min(1.0, RASTER_HEIGHT / bh)
        rw, rh = max(2, int(np.ceil(bw * r))), max(2, int(np.ceil(bh * r)))
        uv = (px - lo) * r
        raster = rasterize(uv, v[:, 2].astype(np.float64), f[front], (rw, rh))
        covered = raster.face >= 0
        zbuf = raster.depth
        if "mesh" in self.layers and covered.any():
            n = vertex_normals_fast(v, f, normal)
            nf = raster.interpolate(n.astype(np.float32), f[front], (0.0, 0.0, -1.0))
            nf /= np.linalg.norm(nf, axis=-1, keepdims=True).clip(1e-6)
            shade = np.clip(lambert(nf)[..., None] * MESH_BGR, 0, 255).astype(np.uint8)
            alpha = (covered * MESH_ALPHA).astype(np.float32)
            if r < 1.0:
                shade = cv2.resize(shade, (bw, bh), interpolation=cv2.INTER_LINEAR)
                alpha = cv2.resize(alpha, (bw, bh), interpolation=cv2.INTER_LINEAR)
            else:
                shade, alpha = np.ascontiguousarray(shade[:bh, :bw]), np.ascontiguousarray(alpha[:bh, :bw])
            roi = out[lo[1]:lo[1] + bh, lo[0]:lo[0] + bw]
            roi[...] = cv2.blendLinear(shade, np.ascontiguousarray(roi), alpha, 1.0 - alpha)
        if not ({"wireframe", "contours"} & self.layers):
            return
        # visibility of a point: no farther than the (3x3 max-filtered) z-buffer + tolerance
        zmax = cv2.dilate(np.where(np.isfinite(zbuf), zbuf, 1e9).astype(np.float32), np.ones((3, 3), np.uint8))

        def visible(p2: np.ndarray, z: np.ndarray) -> np.ndarray:
            q = np.round((p2 - lo) * r).astype(int)
            inside = (q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] < rw) & (q[:, 1] < rh)
            ok = np.ones(len(q), bool)
            qi = q[inside]
            ok[inside] = z[inside] <= zmax[qi[:, 1], qi[:, 0]] + DEPTH_TOLERANCE_MM
            return ok

        E = self.topo.edges
        ef = self.topo.edge_faces

        def seen(eids: np.ndarray) -> np.ndarray:
            """Of the edges ``eids``, those with both ends projected and their midpoint not hidden."""
            a, b = E[eids, 0], E[eids, 1]
            eids = eids[ok_v[a] & ok_v[b]]
            a, b = E[eids, 0], E[eids, 1]
            return eids[visible(0.5 * (px[a] + px[b]), 0.5 * (v[a, 2] + v[b, 2]))]

        if "wireframe" in self.layers:
            on = np.zeros(len(self.topo.edges), bool)
            on[self.topo.face_edges[front].ravel()] = True
            eids = seen(np.flatnonzero(on))
            roi = out[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1]          # the face's box only (cheap at 4K)
            layer = roi.copy()
            _segments(layer, px - lo, E[eids], WIRE_BGR, 1)
            roi[...] = cv2.addWeighted(layer, WIRE_ALPHA, roi, 1 - WIRE_ALPHA, 0)
        if "contours" in self.layers:
            fa = np.where(ef[:, 0] >= 0, front[ef[:, 0]], False)
            fb = np.where(ef[:, 1] >= 0, front[ef[:, 1]], False)
            two = ef[:, 1] >= 0
            sil = (two & (fa != fb)) | (~two & fa)       # occluding contour, or the border seen from the front
            sel = seen(np.flatnonzero(sil))
            rim = self.topo.near_opening[E[sel]].any(1)  # the lids' and lips' own occluding rims: features
            _segments(out, px, E[sel[~rim]], SILHOUETTE_BGR, self.line)
            _segments(out, px, E[sel[rim]], FEATURE_BGR, self.line)
            for loop in self.topo.features.openings:
                pairs = np.stack([loop, np.roll(loop, -1)], 1)
                pairs = pairs[ok_v[pairs].all(1)]
                if len(pairs):
                    m2 = 0.5 * (px[pairs[:, 0]] + px[pairs[:, 1]])
                    mz = 0.5 * (v[pairs[:, 0], 2] + v[pairs[:, 1], 2])
                    _segments(out, px, pairs[visible(m2, mz)], FEATURE_BGR, self.line)
            for brow in self.topo.features.brows:
                p3 = brow.points(v)
                if not (p3[:, 2] > 1e-3).all():
                    continue
                p2 = project(p3, self.camera)
                pairs = np.stack([np.arange(len(p2) - 1), np.arange(1, len(p2))], 1)
                keep = visible(0.5 * (p2[pairs[:, 0]] + p2[pairs[:, 1]]), 0.5 * (p3[pairs[:, 0], 2] + p3[pairs[:, 1], 2]))
                _segments(out, p2, pairs[keep], FEATURE_BGR, self.line)

    # -- landmarks -------------------------------------------------------------------------------
    def _landmarks(self, out: np.ndarray, fit, detection) -> None:
        import cv2

        pts = np.asarray(detection.points, np.float64).reshape(-1, 2)
        conf = getattr(detection, "confidence", None)
        conf = np.ones(len(pts)) if conf is None else np.nan_to_num(np.asarray(conf, np.float64), nan=0.0)
        lf = getattr(fit, "landmarks_fit", None)
        has_fit = lf is not None and np.shape(lf) == pts.shape and getattr(fit, "status", "fitted") != "skipped"
        lf = np.asarray(lf, np.float64) if has_fit else np.full_like(pts, np.nan)
        ok = np.isfinite(pts).all(1)
        res = lf - pts
        err = np.linalg.norm(res, axis=1)
        rad = max(1.0, 1.5 * self.u)
        weak = ok & (conf < CONFIDENT)
        for (x, y) in pts[weak]:
            cv2.circle(out, (int(round(x * _ONE)), int(round(y * _ONE))), int(round(rad * _ONE)), LOW_CONF_BGR, 1,
                       cv2.LINE_AA, _SHIFT)
        strong = np.flatnonzero(ok & ~weak)
        # one drawing call per colour level (a few) instead of one per landmark
        level = np.clip(np.round(np.nan_to_num(err[strong], nan=0.0) / (5.0 * self.u) * 8), 0, 8).astype(int)
        thick = max(1, int(round(self.u)))
        for lev in np.unique(level):
            idx = strong[level == lev]
            c = tuple(float(x) for x in error_colour(np.array([lev / 8 * 5.0 * self.u]), self.u, 5.0 * self.u)[0])
            has = idx[np.isfinite(err[idx])]
            if len(has):
                segs = _fixed(np.stack([pts[has], pts[has] + RESIDUAL_GAIN * res[has]], 1))
                cv2.polylines(out, list(segs), False, c, thick, cv2.LINE_AA, _SHIFT)
            dots = _fixed(np.stack([pts[idx], pts[idx]], 1))       # zero-length strokes: round dots
            cv2.polylines(out, list(dots), False, c, max(2, int(round(2 * rad))), cv2.LINE_AA, _SHIFT)

    # -- header ----------------------------------------------------------------------------------
    def header_parts(self, fit, detection) -> tuple[str, list[str]]:
        """The header's text and its flags (also used by tests and the report)."""
        from capture.export.curves import timecode

        frame = int(fit.frame)
        err = confident_rms(fit, detection)
        if err is None:
            rms = getattr(fit, "reprojection_rms_px", None)
            err = float(rms) if rms is not None and np.isfinite(rms) else None
        text = f"frame {frame}  {timecode(frame, self.fps)[:-4]}  err {'-' if err is None else f'{err:.2f} px'}"
        flags = []
        status = getattr(fit, "status", "fitted")
        if detection is not None and not detection.face_found:
            flags.append("NO FACE")
        if status == "bridged":
            flags.append("BRIDGED")
        if status == "skipped":
            flags.append("SKIPPED")
        conf = None if detection is None else getattr(detection, "confidence", None)
        if conf is not None and detection.face_found:
            c = np.asarray(conf, np.float64)
            c = c[np.isfinite(c)]
            if c.size and np.median(c) < CONFIDENT:
                flags.append("LOW CONF")
        return text, flags

    def _header(self, out: np.ndarray, fit, detection) -> None:
        import cv2

        text, flags = self.header_parts(fit, detection)
        font = cv2.FONT_HERSHEY_SIMPLEX
        fs = max(0.42, 0.55 * self.u)
        th = max(1, int(round(1.2 * self.u)))
        pad = max(3, int(round(6 * self.u)))
        (tw, tht), base = cv2.getTextSize(text, font, fs, th)
        items = [(text, (255, 255, 255), None)]
        flag_bg = {"NO FACE": (40, 40, 220), "BRIDGED": (0, 140, 255), "SKIPPED": (40, 40, 220),
                   "LOW CONF": (0, 200, 230)}
        for fl in flags:
            items.append((fl, (0, 0, 0) if fl == "LOW CONF" else (255, 255, 255), flag_bg[fl]))
        key = "landmarks" in self.layers
        widths = [cv2.getTextSize(s, font, fs, th)[0][0] for s, _, _ in items]
        band_h = tht + base + 2 * pad
        x = pad
        total = sum(widths) + pad * 3 * len(items) + (int(230 * max(self.u, 0.6)) if key else 0)
        band = out[0:band_h, 0:min(self.size[0], total + pad)]
        band[...] = (band * 0.35).astype(np.uint8)
        y = pad + tht
        for (s, colour, bg), wdt in zip(items, widths):
            if bg is not None:
                cv2.rectangle(out, (x - pad // 2, pad // 2), (x + wdt + pad // 2, band_h - pad // 2), bg, -1)
            cv2.putText(out, s, (x, y), font, fs, colour, th, cv2.LINE_AA)
            x += wdt + 3 * pad
        if key:   # the residual colour key: dot, threshold; dot, middle; dot, threshold
            r = max(2, int(round(3 * self.u)))
            for value, label in ((self.u, f"<{self.u:.2g}"), (3 * self.u, f"{3 * self.u:.2g}"),
                                 (5 * self.u, f">{5 * self.u:.2g} px")):
                c = tuple(float(v) for v in error_colour(np.array([value]), self.u, 5 * self.u)[0])
                cv2.circle(out, (x + r, y - tht // 2), r, c, -1, cv2.LINE_AA)
                x += 2 * r + max(2, pad // 2)
                cv2.putText(out, label, (x, y), font, 0.8 * fs, (230, 230, 230), th, cv2.LINE_AA)
                x += cv2.getTextSize(label, font, 0.8 * fs, th)[0][0] + pad

    def render(self, image: np.ndarray, fit, detection=None, vertices: np.ndarray | None = None) -> np.ndarray:
        """The overlay of one frame on a copy of ``image`` (BGR uint8 (H, W, 3))."""
        return self.draw_on(np.array(image, dtype=np.uint8, copy=True), fit, detection, vertices)

    def draw_on(self, out: np.ndarray, fit, detection=None, vertices: np.ndarray | None = None) -> np.ndarray:
        """Draw the overlay of one frame into ``out`` (BGR uint8 (H, W, 3), changed in place) and return it.
        Reads nothing but its arguments and the take's constants, so frames can be drawn in parallel."""
        if vertices is not None and ({"mesh", "wireframe", "contours"} & self.layers):
            self._mesh(out, np.asarray(vertices, np.float64))
        if detection is not None and "landmarks" in self.layers:
            self._landmarks(out, fit, detection)
        if "header" in self.layers:
            self._header(out, fit, detection)
        return out


def confident_residuals(fit, detection) -> tuple[np.ndarray, np.ndarray] | None:
    """``(lengths (L,), used (L,) bool)``: each landmark's residual length (fitted minus detected, px) and whether it
    counts (finite, confidence >= 0.5 where confidences are given); None for a frame without a face or a fit."""
    if detection is None or not detection.face_found:
        return None
    lf = getattr(fit, "landmarks_fit", None)
    pts = np.asarray(detection.points, np.float64).reshape(-1, 2)
    if lf is None or np.shape(lf) != pts.shape or getattr(fit, "status", "fitted") == "skipped":
        return None
    lf = np.asarray(lf, np.float64)
    ok = np.isfinite(pts).all(1) & np.isfinite(lf).all(1)
    conf = getattr(detection, "confidence", None)
    if conf is not None:
        ok &= np.nan_to_num(np.asarray(conf, np.float64), nan=0.0) >= CONFIDENT
    return np.where(ok, np.linalg.norm(np.where(ok[:, None], lf - pts, 0.0), axis=1), np.nan), ok


def residual_rms(residuals: tuple[np.ndarray, np.ndarray] | None) -> float | None:
    """RMS (px) of :func:`confident_residuals`' used landmarks; None where there are none."""
    if residuals is None or not residuals[1].any():
        return None
    return float(np.sqrt(np.mean(residuals[0][residuals[1]] ** 2)))


def confident_rms(fit, detection) -> float | None:
    """RMS (px) of fitted minus detected landmarks with confidence >= 0.5 (all when none is given)."""
    return residual_rms(confident_residuals(fit, detection))
