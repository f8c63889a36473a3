"""The take's *look* video: the same frames Lambert-shaded in a skin tone, for people to watch.

The coded video (``take.mp4``) is what the synthetic detector reads; it is flat colour, a position
code, and does not look like a face. ``capture synth --look`` also writes ``take_look.mp4``: the
very same rasterised surface (same frame, same pixels covered) shaded with one directional light
and an ambient term. It is a picture for a person only: nothing in the project reads it, and the
detector never sees it (it reads the coded video; the look carries no code).

Shading (camera frame, OpenCV: x right, y down, z forward): per-pixel normals are the vertex normals
(area-weighted face normals, outward for the template's winding) interpolated with the raster's
barycentric coordinates and renormalised; intensity = ``ambient + diffuse * max(0, n . l)`` for the
unit direction ``l`` toward the light (default from the upper left, in front of the face).

Example:
    >>> import trimesh
    >>> from capture.synth.raster import rasterize
    >>> m = trimesh.creation.icosphere(subdivisions=2, radius=10.0)
    >>> v = m.vertices + [0.0, 0.0, 50.0]
    >>> uv = v[:, :2] / v[:, 2:] * 40 + 20
    >>> img = shade(rasterize(uv, v[:, 2], m.faces, (40, 40)), v, m.faces)
    >>> img.shape, img.dtype.name, bool(img[20, 20].sum() > img[0, 0].sum())
    ((40, 40, 3), 'uint8', True)
"""

from __future__ import annotations

import numpy as np

from capture.synth.raster import Raster

#: Diffuse albedo of the skin tone (linear RGB, 0..1), background level (0..255).
SKIN = (0.86, 0.66, 0.54)
BACKGROUND_LEVEL = 40.0
#: Direction toward the light in the camera frame (from the upper left, in front of the face).
LIGHT = (-0.45, -0.55, -0.70)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Unit vertex normals ``(V, 3)``: sums of the incident faces' area-weighted normals (the faces'
    winding sets the side)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])       # length = 2 x area
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    return n / np.linalg.norm(n, axis=1, keepdims=True).clip(1e-12)


def lambert(normals: np.ndarray, light=LIGHT, ambient: float = 0.25, diffuse: float = 0.75) -> np.ndarray:
    """Intensity ``(...)`` in 0..1 of unit ``normals (..., 3)`` under the unit direction ``light``."""
    l = np.asarray(light, dtype=np.float64)
    l = l / np.linalg.norm(l)
    return ambient + diffuse * np.clip(np.asarray(normals) @ l, 0.0, None)


def shade(raster: Raster, vertices_cam: np.ndarray, faces: np.ndarray, light=LIGHT) -> np.ndarray:
    """The shaded picture ``(H, W, 3)`` uint8 RGB of a rasterised mesh (vertices in camera mm)."""
    n = raster.interpolate(vertex_normals(vertices_cam, faces).astype(np.float32), faces, (0.0, 0.0, 0.0))
    n = n / np.linalg.norm(n, axis=-1, keepdims=True).clip(1e-12)
    # a normal facing away (the inside of a lip or an eyelid seen through an opening) is turned
    # toward the camera, as a two-sided surface
    flip = (n[..., 2] > 0.0)[..., None]
    n = np.where(flip, -n, n)
    img = lambert(n, light)[..., None] * np.asarray(SKIN) * 255.0
    img[raster.face < 0] = BACKGROUND_LEVEL
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)
