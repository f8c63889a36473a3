"""Crop geometry: hand-computed cases, exact round trips, agreement with cv2.warpAffine, full pipeline."""

from __future__ import annotations

import numpy as np
import pytest

from capture.detector import Detector
from capture.detector import synthetic as S
from capture.detector.crop import (Crop, crop_from_box, crop_from_landmarks, crop_matrix, frame_to_input,
                                   full_frame_crop, input_px_to_output, input_to_frame, output_to_input_px,
                                   warp_crop)

SIZE = (64, 64)


def test_hand_computed_mapping():
    # centre (100, 80), 128 frame px -> 64 input px: k = 0.5; input centre (31.5, 31.5)
    c = Crop(100.0, 80.0, 128.0, 0.0)
    np.testing.assert_allclose(input_to_frame([[31.5, 31.5], [0.0, 0.0], [-0.5, -0.5]], c, SIZE),
                               [[100.0, 80.0], [37.0, 17.0], [36.0, 16.0]], atol=1e-12)
    # -0.5 (outer edge of the input) maps to the outer edge of the crop: cx - size / 2
    assert input_to_frame([[-0.5, 63.5]], c, SIZE)[0, 0] == pytest.approx(100 - 64)
    # rotated 90 deg: the crop x axis points along frame +y
    c90 = Crop(100.0, 80.0, 128.0, 90.0)
    np.testing.assert_allclose(input_to_frame([[0.0, 31.5]], c90, SIZE), [[100.0, 17.0]], atol=1e-9)


def test_output_frames_hand_computed():
    q = output_to_input_px([[0.0, 1.0], [0.5, 0.5]], "crop_unit", (64, 32))
    np.testing.assert_allclose(q, [[-0.5, 31.5], [31.5, 15.5]])
    q = output_to_input_px([[-1.0, 1.0], [0.0, 0.0]], "crop_signed", (64, 32))
    np.testing.assert_allclose(q, [[-0.5, 31.5], [31.5, 15.5]])


@pytest.mark.parametrize("frame", ["crop_pixels", "crop_unit", "crop_signed"])
@pytest.mark.parametrize("angle", [0.0, 17.0, -90.0, 180.0])
def test_round_trip_exact(frame, angle):
    rng = np.random.default_rng(0)
    size = (96, 64)
    crop = Crop(412.3, 288.7, 231.9, angle)
    p = rng.uniform(0, 800, (200, 2))
    q = frame_to_input(p, crop, size)
    o = input_px_to_output(q, frame, size)
    back = input_to_frame(output_to_input_px(o, frame, size), crop, size)
    np.testing.assert_allclose(back, p, atol=1e-6, rtol=0)


def test_warp_agrees_with_matrix():
    """A blob at frame p lands at input px frame_to_input(p) in the warped image (rotation too).

    (OpenCV interpolates with 1/32-pixel fixed-point weights, so agreement is to a few hundredths.)
    """
    p = np.array([150.3, 110.6])
    frame = _blobs(240, 320, [p], [(255, 255, 255)], sigma=2.0)
    for angle in (0.0, 30.0, -75.0):
        crop = Crop(160.0, 120.0, 64.0, angle)  # magnification 2
        img = warp_crop(frame, crop, SIZE)[:, :, 0].astype(np.float64)
        ys, xs = np.mgrid[0:64, 0:64]
        centroid = np.array([(img * xs).sum(), (img * ys).sum()]) / img.sum()
        np.testing.assert_allclose(centroid, frame_to_input(p, crop, SIZE), atol=0.03)


def test_warp_antialias_keeps_geometry():
    """Strong downscaling pre-reduces the frame; a blob's centroid still maps exactly."""
    import cv2

    frame = np.zeros((1000, 1200, 3), np.uint8)
    cv2.circle(frame, (700, 400), 40, (255, 255, 255), -1, lineType=cv2.LINE_AA)
    crop = Crop(650.0, 420.0, 640.0, 20.0)  # 10x reduction
    img = warp_crop(frame, crop, SIZE)[:, :, 0].astype(np.float64)
    ys, xs = np.mgrid[0:64, 0:64]
    centroid = np.array([(img * xs).sum(), (img * ys).sum()]) / img.sum()
    np.testing.assert_allclose(centroid, frame_to_input([700.0, 400.0], crop, SIZE), atol=0.05)


@pytest.mark.parametrize("crop", [Crop(640.0, 360.0, 300.0, 0.0), Crop(600.0, 300.0, 420.0, 25.0),
                                  Crop(60.0, 700.0, 330.0, -40.0), Crop(640.0, 360.0, 1500.0, 0.0)],
                         ids=["inside", "rotated", "over-the-corner", "larger-than-the-frame"])
def test_warp_reduces_only_what_the_crop_covers(crop):
    """The anti-aliased warp reduces only the region the crop covers, at the right place: on a linear ramp
    (which area averaging and bilinear sampling both reproduce exactly, whatever the blocks' phase; 16-bit,
    20-30 levels per px) every input pixel whose neighbourhood lies in the frame has the ramp's value at its
    frame position (input_to_frame) within 0.05 input px (OpenCV's area reduction by a non-integer factor
    and its 1/32 px sampling; at the 4.7x reduction of a 300 px crop that is 8 levels, where a shift by
    one frame pixel is 20-30); pixels off the frame are black."""
    from capture.detector.crop import input_to_frame

    h, w = 720, 1280
    ys, xs = np.mgrid[0:h, 0:w]
    ramp = lambda x, y: 20.0 * x + 30.0 * y + 100.0
    frame = np.repeat(np.round(ramp(xs, ys)).astype(np.uint16)[:, :, None], 3, axis=2)
    size = (64, 64)
    img = warp_crop(frame, crop, size)[:, :, 0].astype(np.float64)
    qy, qx = np.mgrid[0:64, 0:64]
    p = input_to_frame(np.stack([qx.ravel(), qy.ravel()], 1).astype(np.float64), crop, size)
    f = int(crop.size // 64)
    margin = 2 * f + 1                     # a reduced pixel and the bilinear neighbour, in frame px
    inside = ((p[:, 0] > margin) & (p[:, 0] < w - 1 - margin) & (p[:, 1] > margin) & (p[:, 1] < h - 1 - margin))
    outside = (p[:, 0] < -margin) | (p[:, 0] > w - 1 + margin) | (p[:, 1] < -margin) | (p[:, 1] > h - 1 + margin)
    assert inside.sum() > 500
    err = np.abs(img.ravel()[inside] - ramp(p[inside, 0], p[inside, 1]))
    tol = np.hypot(20.0, 30.0) * 0.05 * crop.size / size[0]        # 0.05 input px, in levels
    assert err.max() <= tol, (err.max(), tol)
    assert not img.ravel()[outside].any()
    off = warp_crop(frame, Crop(-900.0, -900.0, 300.0, 0.0), size)
    assert off.shape == (64, 64, 3) and not off.any()


def test_warp_reduces_by_an_exact_factor(monkeypatch):
    """The region handed to OpenCV's area reduction lies on the frame's grid of f x f blocks (its exact-factor
    path: 3.6 -> 0.2 ms for a 600 px region halved) and covers what the crop needs: the warp equals the warp
    of the whole frame reduced block by block here in float64, within 1.5 levels (0.9 seen; OpenCV rounds the
    block means to 8 bits and the bilinear weights to 1/32 px); a region shifted by one block fails it."""
    import cv2

    from capture.detector import crop as C

    calls = []
    resize = cv2.resize
    monkeypatch.setattr(cv2, "resize",
                        lambda a, dsize, **kw: calls.append((a.shape[:2], dsize)) or resize(a, dsize, **kw))
    frame = np.zeros((720, 1280, 3), np.uint8)
    cv2.circle(frame, (641, 363), 90, (200, 120, 40), -1, lineType=cv2.LINE_AA)
    for crop in [Crop(640.3, 360.7, 301.0, 0.0), Crop(611.0, 333.0, 437.0, 17.0), Crop(30.0, 700.0, 380.0, -30.0),
                 Crop(640.0, 360.0, 1500.0, 0.0)]:
        calls.clear()
        img = warp_crop(frame, crop, SIZE)
        (rh, rw), (dw, dh) = calls[0]
        f = int(np.floor(crop.size / SIZE[0]))
        assert (rw, rh) == (dw * f, dh * f), (crop, rw, rh, dw, dh, f)
        # reference: reduce the whole frame by the same blocks, in float64, and warp that
        m = C.crop_matrix(crop, SIZE)
        a = m[:, :2]
        x0 = y0 = 0
        blocks = frame[:720 // f * f, :1280 // f * f].astype(np.float64)
        red = blocks.reshape(720 // f, f, 1280 // f, f, 3).mean((1, 3))
        mm = np.hstack([a * f, (m[:, 2] + a @ (0.5 * f - 0.5 + np.array([x0, y0])))[:, None]])
        ref = cv2.warpAffine(red, mm, SIZE, flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        inside = cv2.warpAffine(np.ones_like(red[:, :, 0]), mm, SIZE, flags=cv2.INTER_LINEAR) > 0.999
        assert np.abs(img.astype(np.float64) - ref)[inside].max() <= 1.5, crop


def test_crop_from_box_and_landmarks():
    c = crop_from_box(10.0, 20.0, 110.0, 100.0, 0.25, SIZE)
    assert (c.cx, c.cy, c.size) == (60.0, 60.0, 150.0)
    pts = np.array([[0.0, 0.0], [99.0, 0.0], [0.0, 39.0]])
    c = crop_from_landmarks(pts, 0.0, SIZE)
    assert (c.cx, c.cy, c.size) == pytest.approx((49.5, 19.5, 100.0))
    # rotated points: the box is taken in the rotated axes, so the size is the same
    a = np.radians(30)
    r = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]])
    c30 = crop_from_landmarks(pts @ r.T + 5.0, 0.0, SIZE, 30.0)
    assert c30.size == pytest.approx(100.0)
    np.testing.assert_allclose([c30.cx, c30.cy], r @ [49.5, 19.5] + 5.0, atol=1e-9)
    f = full_frame_crop(640, 480, SIZE)
    assert (f.cx, f.cy, f.size) == (319.5, 239.5, 640.0)
    m = crop_matrix(f, SIZE)
    np.testing.assert_allclose(m @ [-0.5, -0.5, 1.0], [-0.5, -0.5 + 8.0])  # letterbox: 8 px black band


@pytest.mark.parametrize("frame", ["crop_pixels", "crop_unit", "crop_signed"])
def test_detector_maps_constant_landmarks_exactly(tmp_path, frame):
    """A model with constant outputs in each coordinate frame: full-frame points equal the inverse affine."""
    q = np.array([[5.0, 7.0], [50.25, 12.5], [31.5, 60.0]])  # input px
    out = input_px_to_output(q, frame, SIZE)
    path = S.save_detector(S.constant_model(out), S.detector_spec(frame=frame), tmp_path)
    det = Detector.load(path)
    crops = [Crop(200.0, 150.0, 123.0, 0.0), Crop(180.5, 160.25, 99.0, 33.0)]
    frames = [np.zeros((300, 400, 3), np.uint8)] * 2
    res = det.run_crops(frames, crops, [0, 1])
    for r, c in zip(res, crops):
        np.testing.assert_allclose(r.points, input_to_frame(q, c, SIZE), atol=1e-4)  # float32 model outputs
        assert r.crop == c.as_tuple()
    # hand value: input centre -> crop centre
    path = S.save_detector(S.constant_model(input_px_to_output([[31.5, 31.5]], frame, SIZE)),
                           S.detector_spec(frame=frame, count=1), tmp_path, "one")
    r = Detector.load(path).run_crops(frames[:1], [Crop(180.5, 160.25, 99.0, 33.0)], [0])[0]
    np.testing.assert_allclose(r.points, [[180.5, 160.25]], atol=1e-5)


def _blobs(h, w, centres, colours, sigma=3.0):
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    img = np.zeros((h, w, 3))
    for (x, y), col in zip(centres, colours):
        g = np.exp(-((xs - x) ** 2 + (ys - y) ** 2) / (2 * sigma ** 2))
        img += g[:, :, None] * np.asarray(col, np.float64)[None, None]
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("layout", ["NCHW", "NHWC"])
def test_centroid_detector_end_to_end_with_alignment(tmp_path, layout):
    """Red/green/blue blobs at known frame positions come back at those positions (colour order, rotation)."""
    centres = np.array([[150.3, 120.8], [190.6, 140.2], [165.1, 165.7]])  # R, G, B
    frame = _blobs(288, 360, centres, [(0, 0, 255), (0, 255, 0), (255, 0, 0)])  # BGR tuples
    spec = S.detector_spec(size=(96, 96), layout=layout, first_frame="full_frame", margin=0.6,
                           align={"left": 0, "right": 1},
                           presence={"name": "face_score", "threshold": 0.2})
    det = Detector.load(S.save_detector(S.centroid_model(size=(96, 96), layout=layout), spec, tmp_path))
    res = det.detect([frame, frame, frame])
    angle = np.degrees(np.arctan2(*(centres[1] - centres[0])[::-1]))
    for r in res:
        assert r.face_found
        np.testing.assert_allclose(r.points, centres, atol=0.05)
    # the crop of the second frame is aligned with the R -> G direction
    assert res[1].crop[3] == pytest.approx(angle, abs=0.1)
    # BGR colour order swaps the red and blue landmarks
    spec["input"]["color"] = "BGR"
    det = Detector.load(S.save_detector(S.centroid_model(size=(96, 96), layout=layout), spec, tmp_path, "bgr"))
    r = det.detect([frame])[0]
    np.testing.assert_allclose(r.points, centres[[2, 1, 0]], atol=0.05)


def test_preprocess_in_kept_buffers_gives_the_same_batches():
    """preprocess with buffers kept between calls gives, value for value, the batch of the readable formula
    ((x * scale - mean) / std, then the layout), for every colour, layout and dtype; the float batch is
    computed in the same arrays call after call (same shape), and a new shape gets new ones. A float16 batch is
    the float32 one rounded once (normalising in float16 would round at every operation)."""
    from dataclasses import replace

    from capture.detector.crop import Crop
    from capture.detector.preprocess import preprocess
    from capture.detector.spec import InputSpec

    rng = np.random.default_rng(0)
    frames = [rng.integers(0, 256, (120, 160, 3), dtype=np.uint8) for _ in range(3)]
    crops = [Crop(80.0 + 5 * i, 60.0 - 3 * i, 90.0 + 10 * i, 7.0 * i) for i in range(3)]
    for color, layout, dtype in [("RGB", "NCHW", "float32"), ("BGR", "NHWC", "float32"), ("GRAY", "NCHW", "float32"),
                                 ("RGB", "NCHW", "uint8"), ("BGR", "NCHW", "float16"), ("RGB", "NHWC", "float16")]:
        C = 1 if color == "GRAY" else 3
        inp = InputSpec("image", layout, (48, 40), color, dtype, 1 / 255, (0.485, 0.456, 0.406)[:C],
                        (0.229, 0.224, 0.225)[:C])
        buffers: dict = {}
        first = None
        for n in (3, 3, 2):
            got = preprocess(frames[:n], crops[:n], inp, buffers)
            u8 = preprocess(frames[:n], crops[:n], replace(inp, dtype="uint8", layout="NHWC"))
            ref = u8
            if dtype != "uint8":    # float16: normalised in float32, then rounded once
                ref = ((u8.astype(np.float32) * np.float32(inp.scale) - np.asarray(inp.mean, np.float32))
                       / np.asarray(inp.std, np.float32)).astype(dtype)
            if layout == "NCHW":
                ref = ref.transpose(0, 3, 1, 2)
            assert got.dtype == ref.dtype and got.flags.c_contiguous
            np.testing.assert_array_equal(got, ref)
            if n == 3 and first is not None:
                assert np.shares_memory(got, first)        # the same arrays, written again
            first = got if first is None else first
