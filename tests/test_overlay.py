"""The overlay's drawing: feature lines from topology, the silhouette and shading of a sphere against its
analytic outline, landmark colours by residual, header flags, and sizes that scale with the frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import trimesh

from calib.camera import Camera
from capture.export.features import boundary_loops, brow_lines, face_features
from capture.export.overlay_draw import (SILHOUETTE_BGR, FrameRenderer, Topology, error_colour,
                                         vertex_normals_fast)


@dataclass
class Fit:
    frame: int
    landmarks_fit: np.ndarray | None = None
    status: str = "fitted"
    reprojection_rms_px: float = 0.5


@dataclass
class Det:
    points: np.ndarray
    confidence: np.ndarray | None
    face_found: bool = True


def grid_with_hole(n: int = 8):
    """An n x n vertex grid (unit spacing) with the 2 x 2 middle quads removed: a border and one hole."""
    ij = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
    v = np.column_stack([ij, np.zeros(len(ij))]).astype(float)
    faces = []
    mid = n // 2 - 1
    for i in range(n - 1):
        for j in range(n - 1):
            if mid <= i <= mid + 1 and mid <= j <= mid + 1:
                continue
            a, b, c, d = i * n + j, (i + 1) * n + j, (i + 1) * n + j + 1, i * n + j + 1
            faces += [[a, b, c], [a, c, d]]
    return v, np.array(faces)


def test_boundary_loops_border_and_hole():
    v, f = grid_with_hole(8)
    loops = boundary_loops(f)
    assert [len(x) for x in loops] == [4 * 7, 4 * 2]           # the border, then the 2x2-quad hole
    for loop in loops:                                           # consecutive vertices are mesh edges
        pairs = {tuple(sorted(p)) for p in zip(loop, np.roll(loop, -1))}
        edges = {tuple(sorted(e)) for e in trimesh.Trimesh(v, f, process=False).edges_unique}
        assert pairs <= edges
    feats = face_features(f)
    assert len(feats.border) == 1 and len(feats.openings) == 1 and feats.brows == []


def test_edge_faces_match_trimesh_adjacency():
    m = trimesh.creation.icosphere(subdivisions=2)
    topo = Topology.of(m.faces)
    pairs = {tuple(sorted(p)) for p in topo.edge_faces.tolist()}
    assert pairs == {tuple(sorted(p)) for p in m.face_adjacency.tolist()}
    v, f = grid_with_hole(6)
    t2 = Topology.of(f)
    assert ((t2.edge_faces[:, 1] == -1).sum()) == 4 * 5 + 4 * 2   # boundary edges have one face


def test_vertex_normals_fast_equals_the_synth_normals():
    from capture.synth.look import vertex_normals

    m = trimesh.creation.icosphere(subdivisions=2)
    v = np.asarray(m.vertices) * [1.0, 2.0, 0.5]
    tri = v[m.faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    np.testing.assert_allclose(vertex_normals_fast(v, m.faces, fn), vertex_normals(v, m.faces), atol=1e-12)


def test_brow_lines_follow_the_brow_shapes():
    v, f = grid_with_hole(12)
    move = np.zeros((2, len(v), 3))
    brow = v[:, 1] >= 8                                         # a band across the top moves with the "brows"
    move[0, brow, 1] = 1.0
    lines = brow_lines(v, move, ["browInnerUp_L", "mouthSmile_L"], bins=3)
    assert len(lines) == 2
    for ln in lines:   # every point is a convex combination of brow vertices
        assert brow[ln.indices[ln.weights > 0]].all()
        np.testing.assert_allclose(ln.weights.sum(1), 1.0)
    pts = [ln.points(v) for ln in lines]
    assert pts[0][:, 0].max() < pts[1][:, 0].min()              # one line per side, each ordered along x
    assert all((np.diff(p[:, 0]) > 0).all() for p in pts)
    assert brow_lines(v, move, ["jawOpen", "mouthSmile_L"]) == []


W, H = 320, 240


@pytest.fixture(scope="module")
def sphere_scene():
    m = trimesh.creation.icosphere(subdivisions=4, radius=40.0)
    v = np.asarray(m.vertices) + [0.0, 0.0, 400.0]
    f = 300.0
    cam = Camera(K=[[f, 0, (W - 1) / 2], [0, f, (H - 1) / 2], [0, 0, 1]], dist=[], image_size=(W, H))
    radius_px = f * 40.0 / np.sqrt(400.0 ** 2 - 40.0 ** 2)      # the outline of a sphere seen in perspective
    return m, v, cam, radius_px


def _is_colour(img, bgr, tol=60):
    return (np.abs(img.astype(int) - np.array(bgr)).sum(-1) < tol)


def test_sphere_silhouette_lies_on_its_analytic_outline(sphere_scene):
    m, v, cam, radius = sphere_scene
    ren = FrameRenderer(Topology.of(m.faces), cam, (W, H), 25.0, ("contours",))
    out = ren.render(np.zeros((H, W, 3), np.uint8), Fit(0), None, v)
    ys, xs = np.nonzero(_is_colour(out, SILHOUETTE_BGR, 120))
    assert len(xs) > 100
    r = np.hypot(xs - (W - 1) / 2, ys - (H - 1) / 2)
    assert np.abs(r - radius).max() < 2.0, (r.min(), r.max(), radius)   # line width 1-2 px at 240p


def test_sphere_shading_covers_its_disk_semi_transparently(sphere_scene):
    m, v, cam, radius = sphere_scene
    ren = FrameRenderer(Topology.of(m.faces), cam, (W, H), 25.0, ("mesh",))
    bg = np.full((H, W, 3), 100, np.uint8)
    out = ren.render(bg, Fit(0), None, v)
    yy, xx = np.mgrid[0:H, 0:W]
    r = np.hypot(xx - (W - 1) / 2, yy - (H - 1) / 2)
    changed = np.abs(out.astype(int) - 100).sum(-1) > 6
    inside, outside = r < radius - 3, r > radius + 3
    assert changed[inside].mean() > 0.99 and changed[outside].mean() == 0.0
    # 40 % of a pale shade over 60 % of the frame: never the plain shade, never the plain frame
    centre = out[H // 2, W // 2].astype(int)
    assert 100 < centre.max() < 0.6 * 100 + 0.4 * 255 + 2


def test_landmarks_are_coloured_by_their_residual():
    cam = Camera(K=[[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]], dist=[], image_size=(W, H))
    ren = FrameRenderer(Topology.of(np.array([[0, 1, 2]])), cam, (W, H), 25.0, ("landmarks",))
    det = Det(np.array([[60.0, 120.0], [200.0, 120.0], [260.0, 60.0]]), np.array([1.0, 1.0, 0.1]))
    fit = Fit(0, landmarks_fit=det.points + [[0.0, 0.0], [10.0, 0.0], [0.0, 0.0]])
    out = ren.render(np.zeros((H, W, 3), np.uint8), fit, det)
    good, bad = out[120, 60].astype(int), out[120, 200].astype(int)
    assert good[1] > 150 and good[2] < 120                        # green: no residual
    assert bad[2] > 200 and bad[1] < 80                           # red: 10 px at 240p (> 5 u px)
    # the residual is drawn magnified 4x towards the fitted point: red pixels 30 px right of it
    assert (out[119:122, 225:235, 2] > 150).any()
    assert out[60, 260].max() < 200 and out[60, 260].max() > 60   # low confidence: a grey ring, not a dot
    np.testing.assert_allclose(error_colour(np.array([0.0]), 1, 5)[0], [30, 220, 30])


def test_header_flags_and_scaling():
    cam = Camera(K=[[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]], dist=[], image_size=(W, H))
    topo = Topology.of(np.array([[0, 1, 2]]))
    ren = FrameRenderer(topo, cam, (W, H), 25.0, ("header",))
    det = Det(np.zeros((4, 2)), np.array([0.1, 0.2, 0.3, 0.9]), face_found=True)
    text, flags = ren.header_parts(Fit(51, landmarks_fit=np.zeros((4, 2)), status="bridged"), det)
    assert text.startswith("frame 51  00:00:02:01") and flags == ["BRIDGED", "LOW CONF"]
    _, flags = ren.header_parts(Fit(3), Det(np.full((4, 2), np.nan), None, face_found=False))
    assert flags == ["NO FACE"]

    def band_height(h: int) -> int:
        w = h * 16 // 9
        r = FrameRenderer(topo, cam, (w, h), 25.0, ("header",))
        img = np.full((h, w, 3), 200, np.uint8)
        out = r.render(img, Fit(7, landmarks_fit=np.zeros((4, 2))), Det(np.zeros((4, 2)), None))
        dark = (out[:, 2] < 100).all(-1)                         # the darkened band at the left edge
        return int(np.flatnonzero(~dark)[0])

    h360, h720, h2160 = band_height(360), band_height(720), band_height(2160)
    assert h360 >= 16                                            # readable at 360p
    assert 2.6 < h2160 / h720 < 3.4                              # scales with the frame height


def test_overlay_option_parsing():
    from capture.export import ExportOptions
    from capture.io.errors import CaptureError
    from capture.run.inputs import RunConfig, parse_overlay

    assert parse_overlay(None) == ("mesh", "contours", "landmarks", "header")
    assert parse_overlay("Wireframe, contours,wireframe") == ("wireframe", "contours")
    assert parse_overlay("none") == ()
    with pytest.raises(CaptureError, match="unknown overlay layer 'dots'.*known layers: mesh, wireframe"):
        parse_overlay("mesh,dots")
    with pytest.raises(ValueError):
        ExportOptions(overlay_layers="mesh")
    # kept in the run's settings (run.json / report.json) and in the export key as JSON data
    assert RunConfig(video="v.mp4", actor="a", overlay=("mesh",)).to_dict()["overlay"] == ["mesh"]
    assert ExportOptions(overlay_layers=("mesh",)).to_dict()["overlay_layers"] == ["mesh"]
