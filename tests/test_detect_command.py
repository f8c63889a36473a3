"""``capture detect``: landmarks, overlay and summary of a detector alone; the cache shared with ``capture run``."""

from __future__ import annotations

import json

import numpy as np

from capture.cli import main
from capture.detector import LandmarkTrack
from capture.detector import synthetic as S
from capture.detector.summary import landmark_jitter
from capture.io.video import VideoReader
from capture.run.store import claim_run_dir
from tests.test_detector_crop import _blobs

CENTRES = np.array([[150.3, 120.8], [190.6, 140.2], [165.1, 165.7]])
COLOURS = [(0, 0, 255), (0, 255, 0), (255, 0, 0)]


def _reference_jitter(p, valid):
    """Slow reference: loops over landmarks and frames; valid (T, L)."""
    t, n = p.shape[:2]
    step, noise = [], []
    for l in range(n):
        ok = valid[:, l]
        d2 = [np.sum((p[i, l] - p[i - 1, l]) ** 2) for i in range(1, t) if ok[i] and ok[i - 1]]
        a2 = [np.sum((p[i + 1, l] - 2 * p[i, l] + p[i - 1, l]) ** 2) for i in range(1, t - 1)
              if ok[i - 1] and ok[i] and ok[i + 1]]
        step.append(np.sqrt(np.mean(d2)))
        noise.append(np.sqrt(np.mean(a2) / 6))
    return np.array(step), np.array(noise)


def test_jitter_matches_a_loop_reference_and_measures_noise():
    rng = np.random.default_rng(1)
    t, n = 400, 4
    motion = np.linspace(0, 40, t)[:, None, None] * np.array([1.0, 0.5])   # steady: no second difference
    sigma = rng.uniform(0.2, 2.0, n)                                         # per-axis noise per landmark
    p = 100 + motion + rng.standard_normal((t, n, 2)) * sigma[None, :, None]
    face = np.ones(t, bool)
    face[[50, 51, 200]] = False
    p[~face] = np.nan
    valid = face[:, None] & (rng.uniform(size=(t, n)) > 0.05)   # a few unconfident landmark-frames
    j = landmark_jitter(p, valid)
    ref_step, ref_noise = _reference_jitter(p, valid)
    np.testing.assert_allclose(j["step_rms"], ref_step, rtol=1e-12)
    np.testing.assert_allclose(j["noise_rms"], ref_noise, rtol=1e-12)
    # 2D noise RMS = sqrt(2) sigma; 390-odd triples give it to a few per cent
    np.testing.assert_allclose(j["noise_rms"], np.sqrt(2) * sigma, rtol=0.15)


def _video(path, t=12):
    import cv2

    rng = np.random.default_rng(0)
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (360, 288))
    shake = rng.standard_normal((t, 2)) * 1.5
    for i in range(t):
        frame = _blobs(288, 360, CENTRES + [1.0 * i, 0.5 * i] + shake[i], COLOURS) if i != 5 else \
            np.zeros((288, 360, 3), np.uint8)
        w.write(frame)
    w.release()
    return path


def test_detect_command_writes_landmarks_overlay_summary_and_shares_the_cache(tmp_path, capsys):
    video = _video(tmp_path / "take.avi")
    spec = S.detector_spec(name="blobs", size=(96, 96), first_frame="full_frame", margin=0.6,
                           presence={"name": "face_score", "threshold": 0.2})
    onnx = S.save_detector(S.centroid_model(size=(96, 96)), spec, tmp_path / "det", "blobs")
    out = tmp_path / "out"
    args = ["detect", str(video), "--detector", str(onnx), "--out", str(out), "--no-progress"]
    assert main(args) == 0
    d = out / "detect" / "blobs"
    summary = json.loads((d / "summary.json").read_text())
    track = LandmarkTrack.load_npz(d / "landmarks.npz")
    assert summary["frames"] == 12 and summary["frames_with_face"] == 11 and summary["longest_gap_frames"] == 1
    assert list(np.flatnonzero(~track.face_found)) == [5]
    step, noise = _reference_jitter(track.points, np.repeat(track.face_found[:, None], 3, axis=1))
    np.testing.assert_allclose(summary["per_landmark"]["step_rms_px"], step, atol=1e-5)
    np.testing.assert_allclose(summary["per_landmark"]["noise_rms_px"], noise, atol=1e-5)
    assert summary["run"]["detected_frames"] == 12 and summary["run"]["cached_frames"] == 0
    assert all(b["threads"] == 1 for b in summary["run"]["thread_pools"]["blas"])   # capture.io.threads
    with VideoReader(d / "overlay.mp4") as r:
        assert (r.info.frame_count, r.info.width, r.info.height) == (12, 360, 288)
        frames = dict(r.frames([0]))
    assert np.abs(frames[0].astype(int) - _blobs(288, 360, CENTRES, COLOURS).astype(int)).max() > 100  # drawn on
    printed = capsys.readouterr().out
    assert "face in 11 of 12 frames" in printed
    # a second call and capture run's folder check reuse the cache folder
    assert main(args) == 0
    again = json.loads((d / "summary.json").read_text())
    assert again["run"]["detected_frames"] == 0 and again["run"]["cached_frames"] > 0
    claim_run_dir(out, "some take", "take.avi", overwrite=False)   # a folder of detect outputs is claimable


def test_detect_command_errors_are_one_line(tmp_path, capsys):
    assert main(["detect", str(tmp_path / "none.mp4"), "--detector", str(tmp_path / "x.onnx")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("capture: error: video") and err.count("\n") == 1
