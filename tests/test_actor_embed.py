"""``capture actor embed``: every input form gives the right surface points; bundled actors get a user copy."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from capture.actor.package import bundled_actor, list_actors, resolve_actor
from capture.cli import main
from capture.detector import embedded_points, read_embedding
from capture.detector import synthetic as S
from capture.detector.embed import embedding_from_canonical_mesh, embedding_from_triangles

DEMO = bundled_actor("demo")


@pytest.fixture(scope="module")
def template():
    return trimesh.load(DEMO / "template.ply", process=False, maintain_order=True, force="mesh")


def _detector(tmp_path, count, name="face_test"):
    pts = np.random.default_rng(0).uniform(5, 60, size=(count, 2))
    spec = S.detector_spec(name=name, count=count, first_frame="full_frame")
    return S.save_detector(S.constant_model(pts), spec, tmp_path / "det", name)


def _surface_points(template, n, seed=0):
    rng = np.random.default_rng(seed)
    face_region = np.flatnonzero(template.triangles_center[:, 2] > 60)  # the front of the face
    fi = rng.choice(face_region, n, replace=False)
    bc = rng.dirichlet([2, 2, 2], n)
    return fi, bc, np.einsum("lk,lkd->ld", bc, template.triangles[fi])


def test_vertex_ids_on_a_bundled_actor_go_to_a_user_copy(tmp_path, monkeypatch, capsys, template):
    monkeypatch.setenv("CAPTURE_ACTORS", str(tmp_path / "actors"))
    assert resolve_actor("demo") == DEMO and resolve_actor("demo_actor") == DEMO
    listed = {a["call_name"]: a for a in list_actors()}
    assert listed["demo"]["bundled"] is True
    ids = [100, 2000, 4000, 6000, 8000]
    (tmp_path / "ids.json").write_text(json.dumps(ids))
    det = _detector(tmp_path, 5)
    assert main(["actor", "embed", "demo", "--detector", str(det), "--vertices", str(tmp_path / "ids.json")]) == 0
    out = capsys.readouterr().out
    assert "actor 'demo' is bundled (read-only): copied it to" in out
    copy = tmp_path / "actors" / "demo"
    assert resolve_actor("demo") == copy and not (DEMO / "landmarks" / "face_test.json").exists()
    emb = read_embedding(copy, "face_test", template, 5)
    np.testing.assert_allclose(embedded_points(emb, template), template.vertices[ids], atol=1e-9)
    listed = {a["call_name"]: a for a in list_actors()}
    assert not listed["demo"].get("bundled") and listed["demo"]["path"] == str(copy)
    # again: the copy is used (one-line note), and an existing embedding needs --overwrite
    assert main(["actor", "embed", "demo", "--detector", str(det), "--vertices", str(tmp_path / "ids.json")]) == 2
    err = capsys.readouterr().err
    assert "already has an embedding for detector 'face_test'" in err and err.count("\n") == 1


def test_triangles_of_another_mesh_with_the_template_topology(tmp_path, template):
    fi, bc, truth = _surface_points(template, 40, seed=1)
    rng = np.random.default_rng(2)
    perm = rng.permutation(len(template.faces))          # the other mesh lists its triangles in another order
    faces = np.roll(template.faces[perm], 1, axis=1)     # ... starting at another corner
    inv = np.argsort(perm)
    other_fi = inv[fi]
    other_bc = np.roll(bc, 1, axis=1)
    # one quad is split along the other diagonal in the other mesh
    t0 = other_fi[0]
    a, b, c = faces[t0]
    nb = [k for k in range(len(faces)) if k != t0 and len({a, c} & set(faces[k])) == 2 and b not in faces[k]][0]
    d = [x for x in faces[nb] if x not in (a, c)][0]
    faces[t0], faces[nb] = [a, b, d], [b, c, d]
    other = trimesh.Trimesh(template.vertices, faces, process=False)
    other_bc[0] = [0.2, 0.5, 0.3]
    v = template.vertices
    expected0 = 0.2 * v[a] + 0.5 * v[b] + 0.3 * v[d]
    emb, report = embedding_from_triangles(template, other_fi, other_bc, "x", topology=other)
    got = embedded_points(emb, template)
    np.testing.assert_allclose(got[1:], truth[1:], atol=1e-9)
    assert report["moved"] == 1
    moved = report["moved_to_surface"]["max_mm"]
    assert np.linalg.norm(got[0] - expected0) == pytest.approx(moved, abs=1e-6) and moved < 1.0


@pytest.mark.parametrize("with_pairs", [True, False])
def test_canonical_mesh_aligned_by_similarity_then_projected(tmp_path, template, with_pairs):
    fi, bc, truth = _surface_points(template, 60, seed=3)
    vids = np.array([1500, 3000, 4500, 6100, 7700, 9000])
    on_vertex = template.vertices[vids]
    pts = np.vstack([truth, on_vertex])                   # the last six landmarks sit on template vertices
    rot = Rotation.from_euler("xyz", [6, -4, 3], degrees=True).as_matrix()
    canonical = ((pts - [1.0, 20.0, 90.0]) @ rot) / 10.0  # the detector's mesh: cm, its own origin and pose
    pairs = np.stack([np.arange(60, 66), vids], axis=1) if with_pairs else None
    emb, report = embedding_from_canonical_mesh(template, canonical * 10.0, "x", pairs)
    err = np.linalg.norm(embedded_points(emb, template) - pts, axis=1)
    if with_pairs:
        assert report["pairs_residual"]["max_mm"] < 1e-6 and err.max() < 1e-6
        assert report["transform"]["scale"] == pytest.approx(1.0, abs=1e-9)
    else:
        assert np.median(err) < 0.05 and err.max() < 0.5, (np.median(err), err.max())
    assert report["surface_distance"]["max_mm"] < (1e-6 if with_pairs else 0.5)


def test_embed_command_with_mesh_units_and_pairs_and_errors(tmp_path, monkeypatch, capsys, template):
    monkeypatch.setenv("CAPTURE_ACTORS", str(tmp_path / "actors"))
    fi, bc, truth = _surface_points(template, 8, seed=4)
    vids = [2100, 5200, 7300]
    pts = np.vstack([truth, template.vertices[vids]])
    trimesh.PointCloud(pts / 10.0).export(tmp_path / "canonical.ply")
    (tmp_path / "pairs.txt").write_text("8 2100\n9 5200\n10 7300\n")
    det = _detector(tmp_path, 11, "mesh11")
    args = ["actor", "embed", "demo", "--detector", str(det), "--mesh", str(tmp_path / "canonical.ply"),
            "--units", "cm", "--pairs", str(tmp_path / "pairs.txt")]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "pair residual after the similarity: RMS 0.000 mm" in out and "landmarks of 'mesh11'" in out
    emb = read_embedding(tmp_path / "actors" / "demo", "mesh11", template, 11)
    np.testing.assert_allclose(embedded_points(emb, template), pts, atol=1e-4)   # the PLY holds float32
    report = json.loads((tmp_path / "actors" / "demo" / "landmarks" / "mesh11.report.json").read_text())
    assert report["transform"]["scale"] == pytest.approx(1.0, abs=1e-6)   # --units cm did the x10
    for bad, msg in [(["--points", str(tmp_path / "pairs.txt")], "give exactly one of --vertices"),
                     (["--vertices", str(tmp_path / "pairs.txt")], "gives 6 landmarks but detector 'mesh11' has "
                                                                   "landmarks.count = 11")]:
        assert main(["actor", "embed", "demo", "--detector", str(det), "--overwrite"] + bad
                    + (["--mesh", str(tmp_path / "canonical.ply")] if "--points" in bad else [])) == 2
        err = capsys.readouterr().err
        assert msg in err and err.count("\n") == 1
