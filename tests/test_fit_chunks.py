"""Reading a finished fit's chunks partly: only some fields (the report's summaries skip the meshes), only
the chunks that hold some frames (the report's worst-frame thumbnails). Against the whole read."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np

from capture.fit.records import FrameFit
from capture.run.stages import DONE_JSON, fits_at, iter_fits
from capture.run.store import save_frame_fits


def _fit_dir(tmp_path, frames, chunk=4):
    rng = np.random.default_rng(0)
    fits = [FrameFit(frame=i, head_R=np.eye(3), head_t=rng.normal(size=3), jaw_R=np.eye(3), jaw_t=np.zeros(3),
                     code=rng.normal(size=2), coefficients_landmarks=rng.normal(size=(5, 3)),
                     vertices=rng.normal(size=(7, 3)).astype(np.float32), landmarks_fit=rng.normal(size=(5, 2)),
                     reprojection_rms_px=float(rng.random()), status="fitted" if i % 3 else "bridged")
            for i in frames]
    chunks = []
    for k in range(0, len(fits), chunk):
        name = f"frames_{frames[k]:06d}.npz"
        save_frame_fits(tmp_path / name, fits[k:k + chunk])
        chunks.append(name)
    (tmp_path / DONE_JSON).write_text(json.dumps({"key": {}, "chunks": chunks, "frames": list(frames)}))
    return fits, chunks


def test_fields_read_equal_the_whole_read_and_leave_the_rest_out(tmp_path):
    frames = [3, 4, 5, 9, 10, 11, 12, 20, 21, 30]         # gaps, as a --frames run or skipped frames leave
    _fit_dir(tmp_path, frames)
    whole = list(iter_fits(tmp_path))
    part = list(iter_fits(tmp_path, ("head_t", "status")))
    assert [f.frame for f in part] == [f.frame for f in whole] == frames
    for a, b in zip(part, whole):
        np.testing.assert_array_equal(a.head_t, b.head_t)
        assert a.status == b.status
        assert a.vertices is None and a.landmarks_fit is None and b.vertices is not None


def test_fits_at_reads_only_the_chunks_that_hold_the_frames(tmp_path):
    frames = [3, 4, 5, 9, 10, 11, 12, 20, 21, 30]
    _, chunks = _fit_dir(tmp_path, frames)            # chunks from frames 3, 10, 21
    whole = {f.frame: f for f in iter_fits(tmp_path)}
    (tmp_path / chunks[1]).write_bytes(b"not an npz")  # frames 10-20: a read of it would fail
    got = fits_at(tmp_path, [30, 4, 9, 3])
    assert sorted(got) == [3, 4, 9, 30]
    for i, f in got.items():
        np.testing.assert_array_equal(f.vertices, whole[i].vertices)
        np.testing.assert_array_equal(f.landmarks_fit, whole[i].landmarks_fit)
    assert fits_at(tmp_path, []) == {}


def _fit(i, w):
    return FrameFit(frame=i, head_R=np.eye(3), head_t=np.full(3, float(i)), jaw_R=np.eye(3), jaw_t=np.zeros(3),
                    code=np.zeros(2), coefficients_landmarks=w, vertices=np.zeros((7, 3), np.float32),
                    landmarks_fit=np.zeros((5, 2)), reprojection_rms_px=0.5, status="fitted")


def test_repeated_coefficient_rows_travel_and_are_stored_as_one_row(tmp_path):
    """The 2D fit without F_W has one coefficient vector at every landmark: repeated_rows makes it a view of
    one row, which pickles (to and from the fit process) and is stored (the fit cache) as that row, and comes
    back equal; coefficients that differ per landmark stay whole."""
    import pickle
    import zipfile

    from capture.fit.records import is_repeated_rows, repeated_rows
    from capture.run.store import load_frame_fits

    rng = np.random.default_rng(1)
    L, E = 468, 24
    rows = rng.normal(size=(3, E))
    full = [np.tile(r, (L, 1)) for r in rows]
    views = [repeated_rows(w) for w in full]
    assert all(is_repeated_rows(v) and not v.flags.writeable for v in views)
    for v, w in zip(views, full):
        np.testing.assert_array_equal(v, w)
    varied = rng.normal(size=(L, E))
    assert repeated_rows(varied) is varied and not is_repeated_rows(varied)
    one_off = full[0].copy()
    one_off[100, 3] += 1e-12                          # rows equal but for one number: not repeated
    assert not is_repeated_rows(repeated_rows(one_off))

    # pickled: one row, not L x E numbers
    packed, whole = pickle.dumps(_fit(0, views[0]), protocol=5), pickle.dumps(_fit(0, full[0]), protocol=5)
    assert len(whole) - len(packed) > 0.9 * L * E * 8
    back = pickle.loads(packed)
    assert is_repeated_rows(back.coefficients_landmarks)
    np.testing.assert_array_equal(back.coefficients_landmarks, full[0])
    assert pickle.loads(whole).coefficients_landmarks.flags.writeable   # a whole array comes back whole

    # stored: a chunk of repeated rows holds (n, E) and the counts, and reads back as the same views
    save_frame_fits(tmp_path / "rows.npz", [_fit(i, v) for i, v in enumerate(views)])
    with zipfile.ZipFile(tmp_path / "rows.npz") as z:
        sizes = {i.filename: i.file_size for i in z.infolist()}
    assert "coefficients_landmarks.npy" not in sizes and sizes["coefficients_landmarks@row.npy"] < 3 * E * 8 + 200
    for part in (None, ("coefficients_landmarks",)):
        got = load_frame_fits(tmp_path / "rows.npz", FrameFit, part)
        for g, w in zip(got, full):
            assert is_repeated_rows(g.coefficients_landmarks)
            np.testing.assert_array_equal(g.coefficients_landmarks, w)
    # a chunk where one frame's coefficients differ per landmark is stored whole, and read back equal
    mixed = [_fit(0, views[0]), _fit(1, varied), _fit(2, views[2])]
    save_frame_fits(tmp_path / "mixed.npz", mixed)
    got = load_frame_fits(tmp_path / "mixed.npz", FrameFit)
    for g, m in zip(got, mixed):
        np.testing.assert_array_equal(g.coefficients_landmarks, m.coefficients_landmarks)


def test_fields_written_frame_by_frame_read_back_as_stacked(tmp_path, monkeypatch):
    """Large fields (the meshes) are written row by row instead of stacked first: with every field forced
    that way, each frame reads back the same as from a chunk written the stacked way (bridged frames with
    None fields among them)."""
    import capture.run.store as store

    rng = np.random.default_rng(1)
    fits = [FrameFit(frame=i, head_R=np.eye(3), head_t=rng.normal(size=3), jaw_R=np.eye(3), jaw_t=np.zeros(3),
                     code=rng.normal(size=2), coefficients_landmarks=rng.normal(size=(5, 3)),
                     vertices=rng.normal(size=(40, 3)).astype(np.float32), landmarks_fit=rng.normal(size=(5, 2)),
                     reprojection_rms_px=float(rng.random()), status="fitted" if i % 3 else "bridged",
                     coefficients_base=None if i % 3 == 0 else rng.normal(size=3))
            for i in range(7)]
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    save_frame_fits(tmp_path / "a" / "frames_000000.npz", fits)
    monkeypatch.setattr(store, "STACK_BYTES", 0)
    save_frame_fits(tmp_path / "b" / "frames_000000.npz", fits)
    for d in ("a", "b"):
        (tmp_path / d / DONE_JSON).write_text(json.dumps({"key": {}, "chunks": ["frames_000000.npz"],
                                                          "frames": list(range(7))}))
    stacked, rows = list(iter_fits(tmp_path / "a")), list(iter_fits(tmp_path / "b"))
    assert len(stacked) == len(rows) == 7
    for a, b in zip(stacked, rows):
        for name in ("head_t", "code", "coefficients_landmarks", "vertices", "landmarks_fit", "coefficients_base"):
            x, y = getattr(a, name), getattr(b, name)
            assert (x is None) == (y is None), name
            if x is not None:
                assert np.asarray(x).dtype == np.asarray(y).dtype, name
                np.testing.assert_array_equal(x, y)
        assert a.status == b.status and a.reprojection_rms_px == b.reprojection_rms_px


def test_meshes_stored_as_maps_come_back_to_the_bit_and_others_keep_their_vertices(tmp_path, monkeypatch):
    """Fits whose vertices are their mesh map of the actor's features are stored without the vertices (the
    basis once beside the chunks) and read back equal to the bit, whole or by fields; a chunk with one fit
    whose vertices the map does not give (a blend of two fits, a retargeted mesh) keeps every vertex; a
    chunk that needs a basis that is gone is refused with a one-line error."""
    import zipfile

    import pytest

    from capture.io.errors import CaptureError
    from capture.run.store import MESH_BASIS, load_frame_fits
    from models.mesh_map import map_vertices

    rng = np.random.default_rng(3)
    K, V = 20, 50
    basis = rng.normal(size=(K, V)).astype(np.float32)
    maps = rng.normal(size=(6, 3, K)).astype(np.float32)
    fits = [FrameFit(frame=i, head_R=np.eye(3), head_t=np.zeros(3), jaw_R=np.eye(3), jaw_t=np.zeros(3),
                     code=np.zeros(2), coefficients_landmarks=np.zeros((5, 3)), vertices=map_vertices(m, basis),
                     landmarks_fit=np.zeros((5, 2)), reprojection_rms_px=0.5, status="fitted", mesh_map=m)
            for i, m in enumerate(maps)]
    assert fits[0].vertices.shape == (V, 3) and fits[0].vertices.dtype == np.float32
    np.testing.assert_allclose(fits[2].vertices, (maps[2].astype(np.float64) @ basis).T, rtol=1e-5, atol=1e-5)
    a = tmp_path / "a"
    save_frame_fits(a / "frames_000000.npz", fits[:3], basis)
    save_frame_fits(a / "frames_000003.npz", fits[3:], basis)
    assert (a / MESH_BASIS).is_file()
    assert "vertices.npy" not in zipfile.ZipFile(a / "frames_000000.npz").namelist()
    got = load_frame_fits(a / "frames_000000.npz", FrameFit) + load_frame_fits(a / "frames_000003.npz", FrameFit)
    only = load_frame_fits(a / "frames_000003.npz", FrameFit, ("vertices",))
    for f, g in zip(fits, got):
        np.testing.assert_array_equal(g.vertices, f.vertices)
        np.testing.assert_array_equal(g.mesh_map, f.mesh_map)
    for f, g in zip(fits[3:], only):
        np.testing.assert_array_equal(g.vertices, f.vertices)
        assert g.mesh_map is None and g.head_t is None               # only what was asked for
    # a blended frame: its vertices are not its map's (as a stitched overlap): the chunk keeps them
    blended = list(fits[:3])
    blended[1] = replace(blended[1], vertices=(0.5 * fits[0].vertices + 0.5 * fits[1].vertices))
    save_frame_fits(tmp_path / "b" / "frames_000000.npz", blended, basis)
    assert "vertices.npy" in zipfile.ZipFile(tmp_path / "b" / "frames_000000.npz").namelist()
    for f, g in zip(blended, load_frame_fits(tmp_path / "b" / "frames_000000.npz", FrameFit)):
        np.testing.assert_array_equal(g.vertices, f.vertices)
    # the caller that made the vertices from the maps (a streamed run) says so: stored as maps without making them
    # again (spied), and read back to the bit; a fit without a map keeps the chunk's vertices all the same
    import capture.run.store as store

    made, check = [], store._maps_make_vertices
    monkeypatch.setattr(store, "_maps_make_vertices", lambda f, b: made.append(len(f)) or check(f, b))
    c = tmp_path / "c"
    save_frame_fits(c / "frames_000000.npz", fits, basis, vertices_from_maps=True)
    assert made == [] and "vertices.npy" not in zipfile.ZipFile(c / "frames_000000.npz").namelist()
    for f, g in zip(fits, load_frame_fits(c / "frames_000000.npz", FrameFit)):
        np.testing.assert_array_equal(g.vertices, f.vertices)
    no_map = [fits[0], replace(fits[1], mesh_map=None)]
    save_frame_fits(c / "frames_000006.npz", no_map, basis, vertices_from_maps=True)
    assert "vertices.npy" in zipfile.ZipFile(c / "frames_000006.npz").namelist()
    assert made == [2]                             # checked the usual way, and not all maps
    monkeypatch.undo()
    # another actor's basis into the same folder is a bug, not a silent mix
    other = basis + 1
    assert not (a / "frames_000006.npz").exists()
    save_frame_fits(a / "frames_000006.npz", fits[:1], other)         # not its map of that basis: kept whole
    assert "vertices.npy" in zipfile.ZipFile(a / "frames_000006.npz").namelist()
    with pytest.raises(ValueError, match="another actor"):
        save_frame_fits(a / "frames_000007.npz", [replace(fits[0], vertices=map_vertices(maps[0], other))], other)
    (a / MESH_BASIS).unlink()
    with pytest.raises(CaptureError) as e:
        load_frame_fits(a / "frames_000000.npz", FrameFit)
    assert MESH_BASIS in str(e.value) and "\n" not in str(e.value)
