"""The rasteriser against its slow reference and against OpenCV's projection (with distortion)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import trimesh

from capture.synth.raster import rasterize, rasterize_reference


def _camera(w=160, h=120):
    f = 150.0
    return np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]]), (w, h)


def _project(p, K, dist):
    uv, _ = cv2.projectPoints(p.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, dist)
    return uv.reshape(-1, 2)


def _sphere():
    m = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    return m.vertices + [5.0, -3.0, 200.0], m.faces


def test_fast_matches_reference():
    v, f = _sphere()
    K, size = _camera(64, 48)
    uv, z = _project(v, K, np.zeros(5)) * 0.3 + 10, v[:, 2]
    a, b = rasterize(uv, z, f, size), rasterize_reference(uv, z, f, size)
    assert a.face.shape == b.face.shape == (48, 64)
    same = a.face == b.face
    assert same.mean() > 0.995  # ties on shared edges may pick either triangle
    np.testing.assert_allclose(a.depth[same], b.depth[same], rtol=1e-6)
    np.testing.assert_allclose(a.bary[same], b.bary[same], atol=1e-5)


@pytest.mark.parametrize("dist", [np.zeros(5), np.array([-0.25, 0.08, 0.001, -0.002, 0.0])])
def test_rendered_surface_point_projects_to_its_pixel(dist):
    """Every covered pixel shows a surface point that cv2.projectPoints maps back onto that pixel."""
    v, f = _sphere()
    K, size = _camera()
    r = rasterize(_project(v, K, dist), v[:, 2], f, size)
    pos = r.interpolate(v, f, (0, 0, 0))
    ys, xs = np.nonzero(r.face >= 0)
    assert len(xs) > 2000
    back = _project(pos[ys, xs].astype(np.float64), K, dist)
    err = np.linalg.norm(back - np.stack([xs, ys], 1), axis=1)
    # float32 attributes (about 1e-5 mm at 200 mm) and, with distortion, the straight triangle edges
    assert np.percentile(err, 99) < (0.02 if not dist.any() else 0.1), np.percentile(err, 99)


def test_depth_order_nearest_wins():
    K, size = _camera()
    tri = np.array([[-30, -30, 0], [30, -30, 0], [0, 30, 0.0]])
    v = np.concatenate([tri + [0, 0, 300.0], tri * 0.5 + [0, 0, 200.0]])
    f = np.array([[0, 1, 2], [3, 4, 5]])
    for order in (f, f[::-1]):
        r = rasterize(_project(v, K, np.zeros(5)), v[:, 2], order, size)
        cy, cx = 60, 80
        near = int(np.flatnonzero((order == [3, 4, 5]).all(1))[0])
        assert r.face[cy, cx] == near and abs(r.depth[cy, cx] - 200.0) < 1e-3
        assert (r.face == 1 - near).any() and np.isinf(r.depth[0, 0])


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="uv"):
        rasterize(np.zeros((3, 3)), np.ones(3), np.array([[0, 1, 2]]), (4, 4))
    with pytest.raises(ValueError, match="z"):
        rasterize(np.zeros((3, 2)), np.ones(2), np.array([[0, 1, 2]]), (4, 4))
