"""Landmark embeddings: file round trip, validation against the template, helpers, query points."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from capture.detector import (Detector, embedded_points, embedding_from_points, embedding_from_vertices,
                              read_embedding, write_embedding)
from capture.detector import synthetic as S
from capture.detector.crop import Crop, input_to_frame
from capture.detector.embedding import LandmarkEmbedding, embedding_path, parse_embedding
from capture.io.errors import CaptureError


@pytest.fixture
def template():
    return trimesh.creation.icosphere(subdivisions=2, radius=50.0)


def test_vertices_and_points_helpers(template, tmp_path):
    ids = [0, 17, 101]
    emb = embedding_from_vertices(template, ids, "face3")
    np.testing.assert_allclose(embedded_points(emb, template), template.vertices[ids], atol=1e-12)
    # points on the surface: barycentric reproduces them; off the surface: the closest point
    rng = np.random.default_rng(1)
    tri = rng.integers(0, len(template.faces), 5)
    w = rng.dirichlet([1, 1, 1], 5)
    on = np.einsum("lk,lkd->ld", w, template.triangles[tri])
    emb = embedding_from_points(template, on * 1.001, "face5")
    np.testing.assert_allclose(embedded_points(emb, template), on, atol=0.2)
    np.testing.assert_allclose(emb.barycentric.sum(axis=1), 1.0)
    with pytest.raises(CaptureError, match="mm from the template"):
        embedding_from_points(template, [[0.0, 0.0, 500.0]], "far")


def test_write_read_round_trip_and_validation(template, tmp_path):
    emb = embedding_from_vertices(template, [1, 2, 3], "face3", source="vertex ids 1 2 3")
    path = write_embedding(tmp_path, emb, template)
    assert path == tmp_path / "landmarks" / "face3.json"
    back = read_embedding(tmp_path, "face3", template, detector_count=3)
    np.testing.assert_array_equal(back.face_index, emb.face_index)
    np.testing.assert_allclose(back.barycentric, emb.barycentric)
    assert back.source == "vertex ids 1 2 3"
    with pytest.raises(CaptureError, match="gives 68"):
        read_embedding(tmp_path, "face3", template, detector_count=68)
    with pytest.raises(CaptureError, match="no landmark embedding for detector 'other'"):
        read_embedding(tmp_path, "other")


def _write(tmp_path, obj):
    p = embedding_path(tmp_path, "d")
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_text(json.dumps(obj))


@pytest.mark.parametrize("change, message", [
    ({"face_index": [0, 99999]}, r"face_index\[1\] = 99999 but the template has triangles 0..319"),
    ({"barycentric": [[1, 0, 0], [0.5, 0.2, 0.2]]}, "barycentric row 1 sums to 0.9"),
    ({"barycentric": [[1, 0, 0], [1.5, -0.5, 0]]}, "barycentric row 1 has a negative weight"),
    ({"count": 3}, "face_index should be 3 integers"),
    ({"extra": 1}, "unknown key 'extra'"),
    ({"detector": "x"}, "is for detector 'x', not 'd'"),
])
def test_bad_embeddings(template, tmp_path, change, message):
    obj = {"detector": "d", "count": 2, "face_index": [0, 1], "barycentric": [[1, 0, 0], [0, 1, 0]], "source": ""}
    obj.update(change)
    _write(tmp_path, obj)
    with pytest.raises(CaptureError, match=message):
        read_embedding(tmp_path, "d", template)


def test_query_points_from_embedding_drive_a_query_detector(template, tmp_path):
    # template points chosen so that their x, y are valid crop pixels of the query model
    emb = embedding_from_vertices(template, [0, 5, 9], "q")
    pts = embedded_points(emb, template)
    spec = S.detector_spec(name="q", kind="query", query={"name": "points"}, first_frame="full_frame", track=False)
    det = Detector.load(S.save_detector(S.query_model(3), spec, tmp_path))
    frame = np.zeros((64, 64, 3), np.uint8)
    r = det.detect([frame], query_points=pts)[0]
    np.testing.assert_allclose(r.points, input_to_frame(pts[:, :2], Crop(31.5, 31.5, 64.0), (64, 64)), atol=1e-4)


def test_parse_accepts_documented_minimal_form():
    emb = parse_embedding({"detector": "d", "count": 1, "face_index": [4], "barycentric": [[0.2, 0.3, 0.5]],
                           "source": "by hand"})
    assert isinstance(emb, LandmarkEmbedding) and emb.count == 1


def test_sample_actor_multipie68_embedding(tmp_path):
    """The bundled sample's 68 landmark vertex ids make a valid embedding on its neutral mesh."""
    from capture.actor.sample import sample_actor_dir

    root = sample_actor_dir()
    meta = json.loads((root / "sample.json").read_text())
    neutral = trimesh.load(root / "shapes" / "neutral.ply", process=False, maintain_order=True, force="mesh")
    ids = meta["landmarks_multipie68"]
    emb = embedding_from_vertices(neutral, ids, "multipie68", source="sample.json landmarks_multipie68")
    write_embedding(tmp_path, emb, neutral)
    back = read_embedding(tmp_path, "multipie68", neutral, detector_count=68)
    np.testing.assert_allclose(embedded_points(back, neutral), neutral.vertices[ids], atol=1e-9)
    # the same points given as 3D positions give the same template points
    emb2 = embedding_from_points(neutral, neutral.vertices[ids], "multipie68")
    np.testing.assert_allclose(embedded_points(emb2, neutral), neutral.vertices[ids], atol=1e-6)
