"""Reading a finished fit's chunks partly: only some fields (the report's summaries skip the meshes), only
the chunks that hold some frames (the report's worst-frame thumbnails). Against the whole read."""

from __future__ import annotations

import json

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
