"""Camera values, their adjustments (resize/crop), the default guess and camera files (JSON, OpenCV)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from calib.camera import DEFAULT_FOV_DEG, Camera, default_camera
from calib.camera_io import camera_to_dict, read_camera, write_camera
from capture.io.errors import CaptureError

K4K = np.array([[2950.0, 0.0, 1931.7], [0.0, 2948.5, 1075.2], [0.0, 0.0, 1.0]])
DIST = np.array([-0.11, 0.05, 0.0004, -0.0002, -0.01])


def cam4k(**kw) -> Camera:
    args = dict(K=K4K, dist=DIST, image_size=(3840, 2160), rms=0.21, provenance="test rig",
                std_dev={"fx": 1.5, "fy": 1.4, "cx": 0.9, "cy": 0.8})
    args.update(kw)
    return Camera(**args)


# ------------------------------------------------------------------------------------ Camera values
def test_camera_is_frozen_and_read_only():
    cam = cam4k()
    with pytest.raises(Exception):
        cam.rms = 3.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        cam.K[0, 0] = 1.0


@pytest.mark.parametrize(
    "kw, message",
    [
        (dict(K=np.eye(2)), "must be 3x3"),
        (dict(K=np.diag([-1.0, 1.0, 1.0])), "focal lengths must be positive"),
        (dict(K=[[100, 5, 10], [0, 100, 10], [0, 0, 1]]), "no skew"),
        (dict(dist=np.zeros(6)), "6 distortion coefficients"),
        (dict(image_size=(0, 10)), "two positive integers"),
        (dict(dist=[np.nan] * 5), "NaN"),
    ],
)
def test_camera_rejects_bad_values(kw, message):
    with pytest.raises(CaptureError, match=message):
        cam4k(**kw)


def test_resize_4k_to_1080p_matches_pixel_centre_rule():
    cam = cam4k()
    proxy = cam.resized(1920, 1080)
    # a 2x2 area-average maps full-res pixel centre u to proxy pixel (u + 0.5) / 2 - 0.5; so must K
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-500, 500, (50, 2)), rng.uniform(800, 3000, 50)])
    full = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.dist)[0].reshape(-1, 2)
    small = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), proxy.K, proxy.dist)[0].reshape(-1, 2)
    np.testing.assert_allclose(small, (full + 0.5) / 2 - 0.5, atol=1e-9)
    assert proxy.image_size == (1920, 1080)
    assert proxy.std_dev["fx"] == pytest.approx(0.75)
    assert "resized 3840x2160->1920x1080" in proxy.provenance
    assert cam.for_frame_size(1920, 1080) == proxy
    assert cam.for_frame_size(3840, 2160) is cam


def test_resize_agrees_with_cv2_resize_on_an_image():
    """Render a dot at a known sub-pixel spot, resize with cv2.INTER_AREA, find it again."""
    cam = Camera(np.array([[400.0, 0, 203.3], [0, 400.0, 151.8], [0, 0, 1]]), np.zeros(5), (400, 300))
    yy, xx = np.mgrid[0:300, 0:400].astype(np.float64)
    u0, v0 = 250.3, 101.7
    img = np.exp(-((xx - u0) ** 2 + (yy - v0) ** 2) / (2 * 4.0**2))
    small = cv2.resize(img, (100, 75), interpolation=cv2.INTER_AREA)
    sy, sx = np.mgrid[0:75, 0:100]
    found = np.array([(small * sx).sum(), (small * sy).sum()]) / small.sum()
    expected = (np.array([u0, v0]) + 0.5) * 0.25 - 0.5
    # centroid of a sampled Gaussian (sigma 1 px after resizing): unbiased to ~1e-3 px
    np.testing.assert_allclose(found, expected, atol=5e-3)
    small_cam = cam.resized(100, 75)
    assert small_cam.cx == pytest.approx((cam.cx + 0.5) * 0.25 - 0.5)


def test_crop_then_project():
    cam = cam4k()
    crop = cam.cropped(960, 540, 1920, 1080)
    pts = np.array([[10.0, -30.0, 1500.0], [-200.0, 100.0, 900.0]])
    full = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), cam.K, cam.dist)[0].reshape(-1, 2)
    cut = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), crop.K, crop.dist)[0].reshape(-1, 2)
    np.testing.assert_allclose(cut, full - (960, 540), atol=1e-9)
    with pytest.raises(CaptureError, match="does not fit"):
        cam.cropped(3000, 0, 1920, 1080)


def test_for_frame_size_refuses_other_aspect_ratio():
    with pytest.raises(CaptureError, match="different aspect ratio.*crop the camera"):
        cam4k().for_frame_size(1440, 1080)


def test_default_camera_is_flagged_and_documented():
    cam = default_camera(1920, 1080)
    assert cam.is_default and cam.rms is None
    assert cam.fov_deg()[0] == pytest.approx(DEFAULT_FOV_DEG)
    assert (cam.cx, cam.cy) == (959.5, 539.5)
    assert "DEFAULT GUESS" in cam.describe()
    assert "default guess" in cam.provenance
    assert cam.resized(960, 540).is_default  # the flag survives adjustments
    assert default_camera(1000, 1000, fov_deg=90).fx == pytest.approx(500.0)
    with pytest.raises(CaptureError, match="field of view"):
        default_camera(640, 480, fov_deg=0)


# ------------------------------------------------------------------------------------------- files
@pytest.mark.parametrize("name", ["camera.json", "camera.yaml", "camera.yml", "camera.xml"])
def test_round_trip(tmp_path, name):
    cam = cam4k()
    write_camera(tmp_path / name, cam)
    back = read_camera(tmp_path / name)
    np.testing.assert_array_equal(back.K, cam.K)  # both formats store full float64 precision
    np.testing.assert_array_equal(back.dist, cam.dist)
    assert back.image_size == cam.image_size
    assert back.rms == pytest.approx(cam.rms)
    assert not list(tmp_path.glob(".*"))  # atomic writes leave no temporary files
    if name.endswith(".json"):
        assert back == cam  # every field, exactly
        data = json.loads((tmp_path / name).read_text())
        assert data["image_size"] == [3840, 2160] and data["rms_px"] == 0.21 and data["is_default"] is False


def test_opencv_file_is_readable_by_opencv(tmp_path):
    write_camera(tmp_path / "cam.yaml", cam4k())
    fs = cv2.FileStorage(str(tmp_path / "cam.yaml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_array_equal(fs.getNode("camera_matrix").mat(), K4K)
    assert fs.getNode("image_width").real() == 3840
    assert fs.getNode("distortion_coefficients").mat().size == 5
    fs.release()


def test_read_opencv_calibration_sample_file(tmp_path):
    """The layout OpenCV 4's calibration sample writes (YAML 1.0 header, 1x5 row of coefficients)."""
    text = """%YAML:1.0
---
calibration_time: "Mon Jan  1 10:00:00 2024"
image_width: 1920
image_height: 1080
flags: 0
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 1.4e+03, 0., 9.6e+02, 0., 1.41e+03, 5.4e+02, 0., 0., 1. ]
distortion_coefficients: !!opencv-matrix
   rows: 1
   cols: 5
   dt: d
   data: [ -0.1, 0.02, 0., 0., 0. ]
avg_reprojection_error: 0.35
"""
    (tmp_path / "studio.yml").write_text(text)
    cam = read_camera(tmp_path / "studio.yml")
    assert cam.image_size == (1920, 1080)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (1400.0, 1410.0, 960.0, 540.0)
    np.testing.assert_array_equal(cam.dist, [-0.1, 0.02, 0, 0, 0])
    assert cam.rms == 0.35 and not cam.is_default
    assert "studio.yml" in cam.provenance


def test_default_camera_survives_json(tmp_path):
    write_camera(tmp_path / "guess.json", default_camera(640, 480))
    back = read_camera(tmp_path / "guess.json")
    assert back.is_default and back.rms is None


@pytest.mark.parametrize(
    "name, content, message",
    [
        ("c.json", "{not json", r"c\.json: not valid JSON"),
        ("c.json", json.dumps({"K": np.eye(3).tolist(), "dist": []}), r"c\.json: missing image_size"),
        ("c.json", json.dumps({"K": np.eye(3).tolist(), "dist": [], "image_size": [1, 1], "dst": 1}),
         r"unknown key\(s\) dst"),
        ("c.json", json.dumps({"K": [[1, 0], [0, 1]], "dist": [], "image_size": [10, 10]}), r"c\.json: .*3x3"),
        ("c.json", json.dumps({"K": np.eye(3).tolist(), "dist": [], "image_size": [10.5, 10]}),
         r"image_size must be \[width, height\] integers"),
        ("c.json", json.dumps({"K": np.eye(3).tolist(), "dist": [], "image_size": [10, 10], "version": 9}),
         "version 9 is not supported"),
        ("c.yaml", "%YAML:1.0\n---\nfoo: [1, 2\n", r"c\.yaml: not an OpenCV YAML/XML file"),
        ("c.yaml", "%YAML:1.0\n---\nimage_width: 10\n", r"c\.yaml: missing camera_matrix, distortion_coefficients, image_height"),
        ("c.txt", "K=1", "unknown camera file type"),
    ],
)
def test_bad_files_give_one_line_errors(tmp_path, name, content, message):
    (tmp_path / name).write_text(content)
    with pytest.raises(CaptureError, match=message) as info:
        read_camera(tmp_path / name)
    assert "\n" not in str(info.value)


def test_missing_file_and_directory(tmp_path):
    with pytest.raises(CaptureError, match="does not exist"):
        read_camera(tmp_path / "nope.json")
    (tmp_path / "d.json").mkdir()
    with pytest.raises(CaptureError, match="is a directory"):
        read_camera(tmp_path / "d.json")


def test_json_schema_is_plain_data():
    data = camera_to_dict(cam4k())
    assert json.loads(json.dumps(data, allow_nan=False)) == data
    assert set(data) == {"format", "version", "image_size", "K", "dist", "rms_px", "std_dev", "is_default", "provenance"}
    assert math.isclose(data["K"][0][0], 2950.0)
