"""The input chart (models/input_chart.py): where the networks read a template point."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import trimesh

from models.aim import AIMConfig, AnatomicalFaceModel
from models.input_chart import InputChart, chart_from_state, tearing_shape


def lips(gap_mm: float = 0.3, n: int = 24):
    """Two strips of triangles (an upper and a lower lip) ``gap_mm`` apart along y, 2 mm cells.

    Returns ``(vertices (V, 3), faces (F, 3), lower (V,) bool)``."""
    xs = np.arange(n) * 2.0
    verts, faces, lower = [], [], []
    for side, y0 in ((0, gap_mm / 2), (1, -gap_mm / 2)):
        sign = 1.0 if side == 0 else -1.0
        base = len(verts)
        for j in range(3):                       # three rows moving away from the contact line
            for x in xs:
                verts.append((x, y0 + sign * 2.0 * j, 0.0))
                lower.append(side == 1)
        for j in range(2):
            for i in range(n - 1):
                a, b = base + j * n + i, base + (j + 1) * n + i
                faces += [(a, a + 1, b), (a + 1, b + 1, b)]
    return np.array(verts), np.array(faces), np.array(lower)


def test_tearing_shape_finds_the_shape_that_parts_touching_surfaces():
    v, f, lower = lips()
    open_mouth = v + lower[:, None] * np.array([0.0, -10.0, 2.0])   # the lower lip drops 10 mm
    rigid = v + np.array([3.0, 1.0, 0.0])                          # everything moves: nothing parts
    smile = v + (v[:, 0:1] - 23.0) ** 2 / 200.0 * np.array([0.0, 1.0, 0.0])  # smooth: pairs stay together
    tear = tearing_shape(v, f, np.stack([v, rigid, open_mouth, smile]))
    assert tear.shape == 2
    assert tear.touching == 24                 # the contact rows' straight pairs (diagonals are 2.02 mm apart)
    assert tear.pairs == 24                    # each 0.3 -> 10.5 mm
    assert tear.worst_mm[0] == pytest.approx(0.3) and tear.worst_mm[1] == pytest.approx(np.hypot(10.3, 2.0))
    assert tearing_shape(v, f, np.stack([v, rigid, smile])).shape is None


def test_chart_is_exact_on_the_surface_and_takes_the_nearest_surface_point_off_it():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    rng = np.random.default_rng(0)
    offset = rng.normal(size=v.shape)
    chart = InputChart.from_shape(v, f, v + offset, 0.5)
    t = lambda a: torch.as_tensor(a, dtype=torch.float32)
    # vertices move by their own offset
    np.testing.assert_allclose(chart(t(v)).numpy(), v + 0.5 * offset, atol=1e-5)
    # points inside triangles: the barycentric blend of their corners' offsets (slow reference per point)
    tri = rng.integers(0, len(f), 50)
    bary = rng.dirichlet(np.ones(3), 50)
    p = np.einsum("pk,pkc->pc", bary, v[f[tri]])
    want = p + 0.5 * np.einsum("pk,pkc->pc", bary, offset[f[tri]])
    np.testing.assert_allclose(chart(t(p)).numpy(), want, atol=1e-4)
    # 0.5 mm off the surface along the triangle's normal: the same surface point's offset
    normal = np.cross(v[f[tri, 1]] - v[f[tri, 0]], v[f[tri, 2]] - v[f[tri, 0]])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    q = p + 0.5 * normal
    np.testing.assert_allclose(chart(t(q)).numpy(), want + 0.5 * normal, atol=1e-4)
    # batch shapes pass through, and the derivative is the true one of the affine blend on each triangle
    # (double precision central differences; forward-mode under torch.func with the triangles given)
    assert chart(t(p).reshape(5, 10, 3)).shape == (5, 10, 3)
    c = torch.as_tensor(p[:10]).requires_grad_(True)
    chart64 = chart.double()
    assert torch.autograd.gradcheck(lambda x: chart64(x), (c,), eps=1e-4, atol=1e-6)
    located, _ = chart64.locate(p[:10])
    tangent = torch.zeros(10, 3, dtype=torch.float64)
    tangent[:, 1] = 1.0
    _, d = torch.func.jvp(lambda x: chart64(x, located), (c.detach(),), (tangent,))
    h = 1e-4
    fd = (chart64(c.detach() + h * tangent, located) - chart64(c.detach() - h * tangent, located)) / (2 * h)
    torch.testing.assert_close(d, fd, rtol=1e-6, atol=1e-8)
    assert (d - tangent).abs().max() > 1e-3          # not the identity: the offsets change along the surface


def test_touching_lips_are_apart_in_the_chart():
    v, f, lower = lips()
    open_mouth = v + lower[:, None] * np.array([0.0, -10.0, 0.0])
    chart = InputChart.from_shape(v, f, open_mouth, 0.3)
    x = chart(torch.as_tensor(v, dtype=torch.float32)).numpy()
    up, low = np.flatnonzero(~lower)[:24], np.flatnonzero(lower)[:24]  # the contact rows
    np.testing.assert_allclose(np.linalg.norm(x[up] - x[low], axis=1), 3.3, atol=1e-5)
    # a point on the upper lip's contact edge 0.1 mm from the lower lip keeps the upper lip's (zero) offset
    p = torch.tensor([[5.0, 0.15, 0.0]])
    np.testing.assert_allclose(chart(p).numpy(), p.numpy(), atol=1e-6)


def test_model_reads_points_through_its_chart_and_saves_it():
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    torch.manual_seed(0)
    model = AnatomicalFaceModel(AIMConfig(n_expressions=2, width=32))
    c = torch.as_tensor(v, dtype=torch.float32)
    plain = model(c)
    model.chart = InputChart.from_shape(v, f, v * 1.1, 0.5)   # inputs 5 % further out
    charted = model(c)
    moved = AnatomicalFaceModel(AIMConfig(n_expressions=2, width=32))
    moved.load_state_dict({k: val for k, val in model.state_dict().items() if not k.startswith("chart.")})
    want = moved.assemble(c, {n: getattr(moved, n)(moved.normalize(c * 1.05)) for n in moved.NETWORKS})
    torch.testing.assert_close(charted.expressions, want.expressions, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(charted.neutral, want.neutral, rtol=1e-4, atol=1e-4)
    assert (charted.expressions - plain.expressions).abs().max() > 1e-3   # the chart changed what the networks read
    # the bone point stays an offset from c itself, not from the chart point
    torch.testing.assert_close(model.bone(c), c + model.config.bone_offset_mm * model.B(model.normalize(c * 1.05)))
    # a saved model comes back with its chart; a model saved before charts existed has none
    state = model.state_dict()
    again = AnatomicalFaceModel(AIMConfig(n_expressions=2, width=32))
    again.chart = chart_from_state(state)
    again.load_state_dict(state)
    torch.testing.assert_close(again(c).expressions, charted.expressions)
    assert chart_from_state(moved.state_dict()) is None


def test_closest_surface_point_matches_trimesh_on_the_demo_template():
    """The candidate search (triangles at the nearest vertices and centroids, no spatial index) finds the same
    closest surface points as trimesh's exact query: on the face, a few mm off it, and mirrored vertices."""
    from capture.demo import bundled_demo_actor

    mesh = trimesh.load(bundled_demo_actor() / "template.ply", process=False)
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    chart = InputChart.from_shape(v, f, v, 0.0)
    rng = np.random.default_rng(1)
    tri, bary = rng.integers(0, len(f), 1500), rng.dirichlet(np.ones(3), 1500)
    on = np.einsum("pk,pkc->pc", bary, v[f[tri]])
    mirrored = v[rng.integers(0, len(v), 1500)] * np.array([-1.0, 1.0, 1.0])   # the template's x = 0 plane
    for points in (on, on + rng.normal(scale=2.0, size=on.shape), mirrored):
        tri, closest = chart.locate(points)
        on_triangle = trimesh.triangles.closest_point(v[f[tri]], points)
        np.testing.assert_allclose(closest, on_triangle, atol=1e-9)       # the point lies on its triangle
        _, exact, _ = trimesh.proximity.closest_point(mesh, points)
        np.testing.assert_allclose(np.linalg.norm(closest - points, axis=1), exact, atol=1e-9)


def test_the_sample_scans_tear_at_the_lips_in_jawopen():
    """On the ICT sample the lips touch in the neutral; jawOpen parts the most touching pairs, by far."""
    from capture.actor.sample import sample_shapes_dir
    from capture.io.meshes import load_shape_dir

    shapes = load_shape_dir(sample_shapes_dir())
    tear = tearing_shape(shapes.vertices[0], shapes.faces, shapes.vertices)
    assert shapes.names[tear.shape] == "jawOpen"
    assert tear.pairs > 1000 and tear.worst_mm[0] < 0.5 < 5 < tear.worst_mm[1]
    others = np.delete(shapes.vertices, tear.shape, axis=0)   # the runner-up parts an order of magnitude fewer
    assert tearing_shape(shapes.vertices[0], shapes.faces, others).pairs < tear.pairs / 5
