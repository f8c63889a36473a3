"""The look video's shading against an analytic sphere (normals from geometry, not from the mesh)."""

from __future__ import annotations

import numpy as np
import trimesh

from capture.synth.look import BACKGROUND_LEVEL, LIGHT, SKIN, lambert, shade
from capture.synth.raster import rasterize


def test_shade_matches_analytic_sphere():
    centre, radius, f = np.array([4.0, -3.0, 120.0]), 30.0, 200.0
    m = trimesh.creation.icosphere(subdivisions=4, radius=radius)
    v = m.vertices + centre
    w = h = 120
    uv = v[:, :2] / v[:, 2:] * f + (w - 1) / 2.0
    r = rasterize(uv, v[:, 2], m.faces, (w, h))
    img = shade(r, v, m.faces)
    ys, xs = np.nonzero(r.face >= 0)
    assert len(xs) > 3000
    # the visible point of each pixel: on its ray at the raster's depth; the sphere's normal there
    p = np.stack([(xs - (w - 1) / 2.0) / f, (ys - (h - 1) / 2.0) / f, np.ones_like(xs, dtype=float)], 1)
    p *= r.depth[ys, xs][:, None]
    n = (p - centre) / radius
    expected = lambert(n, LIGHT)[:, None] * np.asarray(SKIN) * 255.0
    diff = np.abs(img[ys, xs].astype(float) - expected)
    # interpolated vertex normals of a 2,562-vertex sphere are within ~1 degree of the true normal
    assert np.percentile(diff, 99) < 4.0, np.percentile(diff, 99)
    assert (img[r.face < 0] == BACKGROUND_LEVEL).all()
    # lit from the upper left: the upper-left of the sphere is brighter than the lower right
    assert img[40, 40].sum() > img[80, 80].sum()
