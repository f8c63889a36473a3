"""Video reading, the Haar face finder on real clips, batched vs unbatched runs, the detection cache."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks.assets import GRID_CLIPS
from capture.detector import Detector, LandmarkTrack, TrackOptions, detect_video
from capture.detector import synthetic as S
from capture.detector.finder import HaarFinder
from capture.io.errors import CaptureError
from capture.io.heap import populated
from capture.io.video import VideoReader, open_video, video_identity

GRID = GRID_CLIPS     # $CAPTURE_SHARED_ASSETS or ../shared/assets (benchmarks.assets)
CLIPS = sorted(GRID.glob("*.mpg"))
needs_grid = pytest.mark.skipif(not CLIPS, reason=f"GRID clips not at {GRID} (set CAPTURE_SHARED_ASSETS)")


@needs_grid
def test_reader_reports_count_fps_size():
    with open_video(CLIPS[0]) as r:
        assert (r.info.frame_count, r.info.fps, r.info.width, r.info.height) == (75, 25.0, 360, 288)
        assert r.info.rotation_deg == 0
        seq = dict(r.frames())
        assert sorted(seq) == list(range(75))
        picked = dict(r.frames([3, 40, 41]))  # rewinds and skips
        assert sorted(picked) == [3, 40, 41]
        for i in picked:
            np.testing.assert_array_equal(picked[i], seq[i])
        assert seq[0].dtype == np.uint8 and seq[0].shape == (288, 360, 3)


@needs_grid
def test_frames_decoded_into_a_pool_are_the_frames(monkeypatch):
    """Frames decoded into a FramePool's buffers equal the freshly allocated ones, and the buffers given
    back are written into again (the pool then allocates nothing: every later frame is one of them).
    The pool's own buffers are mapped with their pages in place, one per frame out at once."""
    import capture.io.video as video
    from capture.io.video import FramePool

    made = []

    def counted(shape, dtype=np.uint8):
        made.append(shape)
        return populated(shape, dtype)

    monkeypatch.setattr(video, "populated", counted)
    with open_video(CLIPS[0]) as r:
        ref = {i: f.copy() for i, f in r.frames(range(20))}
    pool, given = FramePool(), []
    with open_video(CLIPS[0]) as r:
        for k in range(0, 20, 5):                    # groups of 5 frames, given back after use
            group = dict(r.frames(range(k, k + 5), pool))
            for i, f in group.items():
                np.testing.assert_array_equal(f, ref[i])
                if k:
                    assert any(np.shares_memory(f, b) for b in given), i
            given = list(group.values())
            pool.give(given)
            assert len(pool) == 5
            assert made == [(288, 360, 3)] * 4          # frame 0 was decoded by the reader's check; 1-4 by the pool
    pool.give([np.zeros((4, 4, 3), np.uint8)[:, ::2]])   # not contiguous: never decoded into
    assert len(pool) == 5


def test_a_capped_pool_waits_for_a_buffer_given_back_and_stops_waiting_on_stop():
    import threading
    import time

    from capture.io.video import FramePool

    stop = threading.Event()
    pool = FramePool(cap=2, stop=stop)
    a, b = pool.take((4, 4, 3)), pool.take((4, 4, 3))
    assert pool.made == 2 and not np.shares_memory(a, b)
    got = []
    t = threading.Thread(target=lambda: got.append(pool.take((4, 4, 3))))
    t.start()
    time.sleep(0.3)
    assert not got and t.is_alive()              # waits: two buffers made and none free
    pool.give([a])
    t.join(2)
    assert got and got[0] is a and pool.made == 2 and pool.waited_s >= 0.25
    t = threading.Thread(target=lambda: got.append(pool.take((4, 4, 3))))
    t.start()
    stop.set()                                   # a stopped run: the decoder is not left waiting
    t.join(2)
    assert not t.is_alive() and got[1] is None and pool.made == 2
    assert FramePool().take() is None            # no shape, nothing free: the reader allocates


def test_populated_buffers_are_zeroed_and_writable():
    a = populated((7, 5, 3), np.uint8)
    assert a.shape == (7, 5, 3) and a.dtype == np.uint8 and a.flags.writeable and a.flags.c_contiguous
    assert not a.any()
    a[...] = 9
    b = populated((3, 4), np.float64)
    b[:] = np.arange(12.0).reshape(3, 4)
    assert a.sum() == 9 * 105 and b[2, 3] == 11.0 and b.sum() == 66.0


def _resident_pages(a: np.ndarray) -> tuple[int, int]:
    """(resident, all) pages of ``a``'s mapping, by mincore(2)."""
    import ctypes
    import mmap

    libc = ctypes.CDLL(None, use_errno=True)
    page = mmap.PAGESIZE
    n = (a.nbytes + page - 1) // page
    vec = (ctypes.c_ubyte * n)()
    assert a.ctypes.data % page == 0
    assert libc.mincore(ctypes.c_void_p(a.ctypes.data), ctypes.c_size_t(a.nbytes), vec) == 0, ctypes.get_errno()
    return sum(v & 1 for v in vec), n


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="mincore and madvise are Linux's")
@pytest.mark.parametrize("madvise", [True, False])
def test_populated_buffers_have_their_pages_in_place_before_the_first_write(monkeypatch, madvise):
    """A frame buffer's pages are mapped when it is made (no fault per 4 KB at the decoder's first write): by
    madvise(MADV_POPULATE_WRITE), which lets go of the GIL, or where the kernel has none by MAP_POPULATE."""
    from capture.io import heap

    if madvise and not _kernel_populates_by_madvise():
        pytest.skip("this kernel has no MADV_POPULATE_WRITE (Linux < 5.14): the fallback case covers it")
    monkeypatch.setattr(heap, "_MADVISE", [] if madvise else [None])
    a = heap.populated((720, 1280, 3), np.uint8)
    assert (heap._MADVISE[0] is not None) == madvise               # the path this case is about was taken
    resident, pages = _resident_pages(a)
    assert pages >= 675 and resident == pages
    assert not a.any()


def _kernel_populates_by_madvise() -> bool:
    """madvise(MADV_POPULATE_WRITE) on a mapping of our own succeeds (asked here, not through capture.io.heap)."""
    import ctypes
    import mmap

    libc = ctypes.CDLL(None, use_errno=True)
    m = mmap.mmap(-1, mmap.PAGESIZE, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
    addr = ctypes.addressof(ctypes.c_char.from_buffer(m))
    ok = libc.madvise(ctypes.c_void_p(addr), ctypes.c_size_t(mmap.PAGESIZE), 23) == 0
    del addr
    m.close()
    return ok


def test_reader_errors(tmp_path):
    with pytest.raises(CaptureError, match="does not exist"):
        VideoReader(tmp_path / "none.mp4")
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(b"this is not a video" * 100)
    with pytest.raises(CaptureError) as e:
        VideoReader(bad)
    assert "bad.mp4" in str(e.value) and "\n" not in str(e.value)
    empty = tmp_path / "empty.avi"
    empty.write_bytes(b"")
    with pytest.raises(CaptureError):
        VideoReader(empty)


@needs_grid
def test_video_identity_ignores_path(tmp_path):
    copy = tmp_path / "copy.mpg"
    shutil.copy(CLIPS[0], copy)
    assert video_identity(copy) == video_identity(CLIPS[0]) != video_identity(CLIPS[1])


@needs_grid
def test_haar_finds_one_face_in_every_clip():
    """The finder on every frame of every clip: exactly one face, of a plausible size."""
    finder = HaarFinder()
    for clip in CLIPS:
        with open_video(clip) as r:
            for i, frame in r.frames():
                boxes = finder.find_all(frame)
                assert len(boxes) == 1, (clip.name, i, boxes)
                x0, y0, x1, y1 = boxes[0]
                assert 60 <= x1 - x0 <= 250 and 0 <= x0 and x1 <= 360 and y1 <= 288, (clip.name, i)


def _conv_detector(tmp_path, segment=16):
    spec = S.detector_spec(name="conv", count=68, size=(96, 96), first_frame="haar", margin=0.1)
    path = S.save_detector(S.conv_model(size=(96, 96), count=68, widths=(8, 16)), spec, tmp_path, "conv")
    return Detector.load(path, options=TrackOptions(segment=segment), threads=1)


@needs_grid
def test_batched_equals_unbatched(tmp_path):
    det = _conv_detector(tmp_path)
    clip = CLIPS[0]
    a = detect_video(clip, det, None, progress=False, batch=1)
    calls_unbatched = det.model_calls
    det.model_calls = 0
    b = detect_video(clip, det, None, progress=False, batch=5)
    assert det.model_calls < calls_unbatched / 3  # 5 segments side by side
    assert a.face_found.all() and len(a) == 75
    np.testing.assert_array_equal(a.frame_index, b.frame_index)
    np.testing.assert_allclose(a.points, b.points, atol=1e-4)
    np.testing.assert_allclose(a.crops, b.crops, atol=1e-4)
    # the track follows the face: crops stay on the Haar face box of the first frame
    x0, y0, x1, y1 = HaarFinder().find(next(open_video(clip).frames([0]))[1])
    assert abs(a.crops[0, 0] - (x0 + x1) / 2) < 0.2 * (x1 - x0)


@needs_grid
def test_cache_rerun_and_resume(tmp_path):
    det = _conv_detector(tmp_path)
    clip = CLIPS[1]
    first = detect_video(clip, det, tmp_path / "out", progress=False)
    assert first.detected_frames == 75 and first.cached_frames == 0 and det.model_calls > 0
    det.model_calls = 0
    again = detect_video(clip, det, tmp_path / "out", progress=False)
    assert det.model_calls == 0 and again.cached_frames == 75
    np.testing.assert_array_equal(again.points, first.points)
    # a partial cache: two segments lost (as after an interrupted run) -> only those are detected
    (key_dir,) = (tmp_path / "out" / "detections").iterdir()
    segs = sorted(key_dir.glob("seg_*.npz"))
    assert [p.name for p in segs] == [f"seg_{s:08d}.npz" for s in (0, 16, 32, 48, 64)]
    segs[1].unlink()
    segs[4].unlink()
    resumed = detect_video(clip, det, tmp_path / "out", progress=False)
    assert resumed.detected_frames == 16 + 11 and resumed.cached_frames == 75 - 27
    assert 0 < det.model_calls
    np.testing.assert_allclose(resumed.points, first.points, atol=1e-9)
    # another detector setting is another key
    det2 = _conv_detector(tmp_path, segment=25)
    detect_video(clip, det2, tmp_path / "out", progress=False, frames=range(10, 20))
    assert len(list((tmp_path / "out" / "detections").iterdir())) == 2


@needs_grid
def test_frame_subset_and_npz_round_trip(tmp_path):
    det = _conv_detector(tmp_path)
    clip = CLIPS[2]
    part = detect_video(clip, det, tmp_path / "out", frames=range(20, 30), progress=True)  # bar: smoke
    assert part.frame_index.tolist() == list(range(20, 30)) and part.points.shape == (10, 68, 2)
    assert part.fps == 25.0 and part.image_size == (360, 288)
    whole = detect_video(clip, det, tmp_path / "out", progress=False)
    np.testing.assert_array_equal(whole.points[20:30], part.points)  # segment-aligned: same result
    p = whole.save_npz(tmp_path / "lm.npz")
    back = LandmarkTrack.load_npz(p)
    np.testing.assert_array_equal(back.points, whole.points)
    assert back.detector == "conv" and back.confidence is None
    with pytest.raises(CaptureError, match="video has frames 0..74"):
        detect_video(clip, det, None, frames=range(70, 80), progress=False)


def _moving_blobs_video(path: Path, n: int = 40):
    """Lossless video of three coloured blobs that move 2 px and turn 1.5 deg per frame; returns truth."""
    import cv2

    from tests.test_detector_crop import _blobs

    base = np.array([[-20.0, -10.0], [20.0, -10.0], [0.0, 25.0]])
    truth = []
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), 25, (320, 240))
    for t in range(n):
        a = np.radians(1.5 * t)
        r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
        c = base @ r.T + [100.0 + 2.0 * t, 110.0 + 0.7 * t]
        truth.append(c)
        w.write(_blobs(240, 320, c, [(0, 0, 255), (0, 255, 0), (255, 0, 0)], sigma=4.0))
    w.release()
    return np.array(truth)


def test_tracking_follows_motion_batched_and_unbatched(tmp_path):
    truth = _moving_blobs_video(tmp_path / "blobs.avi")
    spec = S.detector_spec(size=(96, 96), first_frame="full_frame", margin=0.8, align={"left": 0, "right": 1},
                           presence={"name": "face_score", "threshold": 0.2})
    path = S.save_detector(S.centroid_model(size=(96, 96)), spec, tmp_path, "centroid")
    det = Detector.load(path, options=TrackOptions(segment=16))
    a = detect_video(tmp_path / "blobs.avi", det, None, progress=False, batch=1)
    b = detect_video(tmp_path / "blobs.avi", det, None, progress=False, batch=3)
    assert a.face_found.all() and len(a) == 40
    np.testing.assert_allclose(a.points, truth, atol=0.1)
    np.testing.assert_allclose(a.points, b.points, atol=1e-6)
    # tracked crops keep the blobs well inside and turn with them (angle of landmark 0 -> 1 of the
    # previous frame, smoothed), lagging the motion by about a frame
    from capture.detector.crop import Crop, frame_to_input

    for t in range(40):
        q = frame_to_input(truth[t], Crop(*a.crops[t]), (96, 96))
        assert q.min() > 10 and q.max() < 86, (t, q)
    np.testing.assert_allclose(a.crops[1:16, 3], 1.5 * np.arange(0, 15), atol=2.0)


def test_reader_applies_rotation_metadata(tmp_path):
    """An MP4 whose track matrix says 'rotate 90 degrees' (as phones write) comes out upright."""
    import struct

    import cv2

    src = tmp_path / "plain.mp4"
    w = cv2.VideoWriter(str(src), cv2.VideoWriter_fourcc(*"mp4v"), 25, (160, 120))
    frame = np.zeros((120, 160, 3), np.uint8)
    frame[10:30, 10:50] = 255
    for _ in range(3):
        w.write(frame)
    w.release()
    data = bytearray(src.read_bytes())
    m = data.find(b"tkhd") + 4 + 40  # version-0 track header: the 3x3 matrix follows 40 bytes of fields
    assert struct.unpack(">9i", data[m:m + 36]) == (0x10000, 0, 0, 0, 0x10000, 0, 0, 0, 0x40000000)
    data[m:m + 36] = struct.pack(">9i", 0, 0x10000, 0, -0x10000, 0, 0, 0, 0, 0x40000000)
    rotated = tmp_path / "rotated.mp4"
    rotated.write_bytes(bytes(data))
    with open_video(rotated) as r:
        assert (r.info.rotation_deg, r.info.width, r.info.height, r.info.frame_count) == (90, 120, 160, 3)
        _, f = next(r.frames())
    assert f.shape == (160, 120, 3)
    ys, xs = np.nonzero(f[:, :, 0] > 128)
    # 90 degrees clockwise: row r, column c -> row c, column (120 - 1 - r)
    assert (ys.min(), ys.max(), xs.min(), xs.max()) == (10, 49, 90, 109)


def test_query_detector_on_video_and_cache_key(tmp_path):
    _moving_blobs_video(tmp_path / "blobs.avi", n=6)
    spec = S.detector_spec(name="q", kind="query", query={"name": "points"}, first_frame="full_frame", track=False)
    det = Detector.load(S.save_detector(S.query_model(3), spec, tmp_path, "q"))
    q1 = np.array([[10.0, 20.0, 0.0], [30.0, 40.0, 1.0], [50.0, 60.0, 2.0]])
    a = detect_video(tmp_path / "blobs.avi", det, tmp_path / "out", progress=False, query_points=q1)
    # full frame 320x240 letterboxed into 64x64: 5 frame px per input px, top band of 40 px
    np.testing.assert_allclose(a.points[0], (q1[:, :2] + 0.5) * 5.0 - 0.5 - [0.0, 40.0], atol=1e-4)
    b = detect_video(tmp_path / "blobs.avi", det, tmp_path / "out", progress=False, query_points=q1 + 1.0)
    assert b.cached_frames == 0 and len(list((tmp_path / "out" / "detections").iterdir())) == 2
    np.testing.assert_allclose(b.points - a.points, 5.0, atol=1e-4)
    with pytest.raises(CaptureError, match="needs the actor's template points"):
        detect_video(tmp_path / "blobs.avi", det, None, progress=False)


def _stacked_track(results, count):
    """The readable reference: every array stacked from the list at once (NaN where a frame has none)."""
    def col(name, shape):
        if all(getattr(r, name) is None for r in results):
            return None
        return np.stack([np.full(shape, np.nan) if getattr(r, name) is None else np.asarray(getattr(r, name), float)
                         for r in results])

    return {"frame_index": np.array([r.frame_index for r in results], np.int64),
            "points": np.stack([r.points for r in results]), "face_found": np.array([r.face_found for r in results]),
            "crops": np.array([r.crop for r in results], float), "confidence": col("confidence", (count,)),
            "sigma_px": col("sigma_px", (count,)), "presence": col("presence", ()), "depth": col("depth", (count,))}


@pytest.mark.parametrize("capacity,spill", [(0, False), (5, False), (40, False), (5, True), (40, True)])
def test_track_builder_equals_the_stacked_results(capacity, spill, tmp_path, monkeypatch):
    """A stream fills the track frame by frame (capture.run.stream): the arrays equal those stacked from the
    whole list, whether the room made up front is short (grown by doubling), exact or too large; optional
    arrays that first appear mid-take are NaN before. Spilled (blocks of 3 frames here), the per-landmark
    arrays are the same numbers, mapped read-only from files that leave nothing behind."""
    from capture.detector.pipeline import TrackBuilder
    from capture.detector.runtime import FrameLandmarks
    from capture.io.rows import SpilledRows

    monkeypatch.setattr(SpilledRows, "BLOCK", 3)

    rng = np.random.default_rng(3)
    count, results = 7, []
    for j in range(40):
        found = j % 9 != 4
        results.append(FrameLandmarks(
            frame_index=100 + 2 * j, points=rng.normal(size=(count, 2)) if found else np.full((count, 2), np.nan),
            confidence=rng.uniform(size=count) if j >= 3 else None, sigma_px=None,
            presence=float(rng.uniform()) if j % 5 == 0 else None, face_found=found,
            crop=(float(j), 2.0, 50.0 + j, 0.0), depth=rng.normal(size=count) if j > 30 else None))
    builder = TrackBuilder("det", count, capacity, tmp_path if spill else None)
    for r in results:
        builder.add(r)
    got, want = builder.track(), _stacked_track(results, count)
    if spill:
        assert sorted(builder._rows) == ["confidence", "depth", "points"]        # sigma_px: no frame has it
        for k in builder._rows:
            assert not getattr(got, k).flags.writeable and not getattr(got, k).flags.owndata, k
        assert list(tmp_path.iterdir()) == []
        with pytest.raises(RuntimeError, match="mapped"):
            builder.add(results[0])
    assert len(got) == 40 and got.detector == "det"
    np.testing.assert_array_equal(builder.frames(), want["frame_index"])
    for k, v in want.items():
        if v is None:
            assert getattr(got, k) is None, k
        else:
            assert getattr(got, k).dtype == v.dtype, k
            np.testing.assert_array_equal(getattr(got, k), v, err_msg=k)
    empty = TrackBuilder("det", count, capacity, tmp_path if spill else None).track()
    assert empty.points.shape == (0, count, 2) and empty.crops.shape == (0, 4) and empty.confidence is None
