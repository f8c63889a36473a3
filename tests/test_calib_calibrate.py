"""``capture calibrate`` on synthetic board footage with known intrinsics, and every bad input.

Footage comes from :mod:`tests.calib_synth` (boards rendered through a known distorted 640x480
camera, blurred, with noise). OpenCV's calibration is the reference algorithm; what is tested is
our detection wiring, view selection, outlier rejection, files and error messages.

Tolerances (from the issue) and why they are meaningful here: fx, fy within 0.5 % (3 px), cx, cy
within 2 px, RMS below 0.5 px. The renders' corner noise is ~0.03 px (OpenCV's own corners ~0.1 px),
so a correct pipeline lands far inside them (typically 0.05 % and 0.7 px); a wrong pixel-centre
convention (0.5 px), object points in the wrong units or order, or ignored distortion (k1 = -0.22
bends the corners by several px) fail.
"""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from calib.board import BoardSpec, parse_board
from calib.calibrate import CalibrationOptions, calibrate_views
from calib.camera_io import read_camera
from calib.detect import BoardDetector
from calib.models import DIST_NAMES, model_by_name
from capture.io.errors import CaptureError
from tests.calib_synth import (CHARUCO_SPEC, CHECKER_SPEC, IMAGE_SIZE, TRUE_DIST, TRUE_K, Renderer,
                               random_poses, write_images, write_video)

from capture.cli import main



def run(argv: list[str], capsys) -> tuple[int, str, str]:
    code = main(argv)
    out, err = capsys.readouterr()
    return code, out, err


def assert_one_line_error(code: int, err: str, *fragments: str) -> None:
    assert code != 0
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("capture: error: ")
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def assert_intrinsics_recovered(cam) -> None:
    assert cam.image_size == IMAGE_SIZE
    assert abs(cam.fx / TRUE_K[0, 0] - 1) < 0.005, cam.fx
    assert abs(cam.fy / TRUE_K[1, 1] - 1) < 0.005, cam.fy
    assert abs(cam.cx - TRUE_K[0, 2]) < 2.0, cam.cx
    assert abs(cam.cy - TRUE_K[1, 2]) < 2.0, cam.cy
    assert cam.rms is not None and cam.rms < 0.5
    assert abs(cam.dist[0] - TRUE_DIST[0]) < 0.02  # k1 is well determined by 16 views


# ------------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def charuco():
    renderer = Renderer(CHARUCO_SPEC)
    poses = random_poses(renderer.board, TRUE_K, IMAGE_SIZE, 16, seed=3)
    rng = np.random.default_rng(1)
    return renderer, poses, [renderer.render(p, rng=rng) for p in poses]


@pytest.fixture(scope="module")
def charuco_detections(charuco):
    renderer, _poses, images = charuco
    detector = BoardDetector(renderer.board)
    dets = [detector.detect(img)[0] for img in images]
    return [d.object_points for d in dets], [d.image_points for d in dets]


@pytest.fixture(scope="module")
def charuco_folder(charuco, tmp_path_factory):
    folder = tmp_path_factory.mktemp("charuco_views")
    write_images(folder, charuco[2])
    return folder


# ------------------------------------------------------------------------------------------- board spec
def test_parse_board_specs():
    b = parse_board("charuco:cols=11,rows=8,square=30,marker=22,dict=DICT_5X5_100")
    assert b == BoardSpec("charuco", 11, 8, 30.0, 22.0, "DICT_5X5_100", False)
    assert parse_board(b.text()) == b
    assert parse_board(" ChArUco: cols=11, rows=8, square=30mm, marker=22, dict=5x5_100, legacy=1 ").legacy
    c = parse_board("checker:cols=9,rows=6,square=25")
    assert (c.kind, c.num_corners, c.square_mm) == ("checker", 54, 25.0)
    assert parse_board(c.text()) == c


@pytest.mark.parametrize(
    "spec, message",
    [
        ("", "does not parse"),
        ("charuco", "does not parse"),
        ("circles:cols=4,rows=11,square=20", "board kind 'circles' is unknown"),
        ("checker:cols=9,rows=6", "missing square"),
        ("checker:cols=9,rows=6,square=25,marker=3", "marker unknown for checker"),
        ("checker:cols=nine,rows=6,square=25", "cols='nine' must be a whole number"),
        ("checker:cols=9,rows=6,square=-2", "must be a positive length"),
        ("checker:cols=9,rows=6,square=25,square=20", "gives 'square' twice"),
        ("checker:cols=9,rows,square=25", "is not key=value"),
        ("charuco:cols=11,rows=8,square=30,marker=30,dict=DICT_5X5_100", "must be smaller than the square"),
        ("charuco:cols=11,rows=8,square=30,marker=22,dict=DICT_9X9_1", "ArUco dictionary 'DICT_9X9_1' is unknown"),
        ("charuco:cols=20,rows=20,square=30,marker=22,dict=DICT_4X4_50", "needs 200 markers but DICT_4X4_50 has 50"),
    ],
)
def test_parse_board_rejects(spec, message):
    with pytest.raises(CaptureError, match=message):
        parse_board(spec)


# ------------------------------------------------------------------------------------------ detection
def test_charuco_detection_matches_truth(charuco):
    renderer, poses, images = charuco
    detector = BoardDetector(renderer.board)
    det, reason = detector.detect(images[0])
    assert reason is None and len(det.ids) >= 20
    truth = renderer.project(poses[0])[det.ids]
    # sub-pixel corners on a blurred, noisy render: ~0.1 px RMS; 0.5 px would mean a convention slip
    assert np.sqrt(np.mean(np.sum((det.image_points - truth) ** 2, 1))) < 0.3
    np.testing.assert_array_equal(det.object_points, renderer.board.corner_object_points()[det.ids])
    none, why = detector.detect(np.full((480, 640), 128, np.uint8))
    assert none is None and why == "no board detected"


# -------------------------------------------------------------------------------------- calibration
def test_calibrate_charuco_folder_end_to_end(charuco_folder, tmp_path, capsys):
    out = tmp_path / "cam" / "camera.json"
    code, stdout, err = run(["calibrate", str(charuco_folder), "--board", CHARUCO_SPEC, "--out", str(out),
                             "--no-progress"], capsys)
    assert code == 0, err
    cam = read_camera(out)
    assert_intrinsics_recovered(cam)
    assert not cam.is_default and "capture calibrate" in cam.provenance
    for key in ("fx", "fy", "cx", "cy"):
        # OpenCV's 1-sigma from 16 views of ~45 corners at 0.1 px noise: well under a pixel, not zero
        assert 0 < cam.std_dev[key] < 2.0
    report = json.loads((tmp_path / "cam" / "camera.report.json").read_text())
    assert report["num_views"] == len(report["views"]) == 16
    assert report["rms_px"] == pytest.approx(cam.rms)
    assert all(v["rms_px"] < 0.5 for v in report["views"])
    assert 0.5 < report["coverage"] <= 1.0
    # std of exactly the estimated terms: fx..cy and the chosen model's distortion terms
    model = model_by_name(report["model"])
    assert set(report["std_dev"]) == {"fx", "fy", "cx", "cy"} | {DIST_NAMES[k] for k in model.free_terms}
    assert set(report["model_holdout_rms_px"]) == {"k1-k2", "k1-k2+p", "k1-k3+p", "k1-k6+p"}
    assert report["holdout"]["rms_px"] == report["model_holdout_rms_px"][model.name] < 0.5
    assert report["dropped"] == []  # 16 clean, distinct views: none is unusable
    assert report["settings"]["board"] == CHARUCO_SPEC and report["settings"]["max_views"] == 60
    png = tmp_path / "cam" / "camera.report.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and cv2.imread(str(png)).shape[1] > 800
    assert "RMS" in stdout and "fx" in stdout


def test_calibrate_video_keeps_duplicates_and_usable_blurred_frames_under_the_cap(charuco, tmp_path, capsys):
    renderer, poses, images = charuco
    rng = np.random.default_rng(2)
    frames, kinds = [], []
    for i, (pose, img) in enumerate(zip(poses[:12], images[:12])):
        frames.append(img)
        kinds.append("sharp")
        frames.append(renderer.render(pose, rng=rng))  # the board held still: a near-duplicate
        kinds.append("duplicate")
        if i % 3 == 0:  # motion-blurred, a new pose: blurred but the corners are still usable
            frames.append(renderer.render(poses[12 + i // 3], motion_blur_px=5, blur_sigma=1.2, rng=rng))
            kinds.append("blurred")
    video = write_video(tmp_path / "take.avi", frames)
    out = tmp_path / "camera.yaml"  # OpenCV's format, chosen by the suffix
    code, stdout, err = run(["calibrate", str(video), "--board", CHARUCO_SPEC, "--out", str(out), "--no-progress"],
                            capsys)
    assert code == 0, err
    assert_intrinsics_recovered(read_camera(out))  # MJPG at quality 100 keeps corners sub-pixel
    report = json.loads((tmp_path / "camera.report.json").read_text())
    assert report["input"]["kind"] == "video" and report["input"]["frames"] == len(frames)
    reasons = {d["frame"]: d["reason"] for d in report["dropped"]}
    used = {v["frame"] for v in report["views"]}
    # under the cap only frames the detector could not read are left out: every still twin is used (its
    # corner noise is independent) and so is every blurred frame the detector could read, because
    # sharpness is judged against what the corners need, not against the other views
    assert all(r == "no board detected" or r.startswith("too few corners") for r in reasons.values()), reasons
    assert all(k in used for k, kind in enumerate(kinds) if kind != "blurred")
    blurred = [k for k, kind in enumerate(kinds) if kind == "blurred"]
    assert sum(k in used for k in blurred) >= 2
    edge = {v["frame"]: v["edge_width_px"] for v in report["views"]}
    sharp_edges = [edge[k] for k, kind in enumerate(kinds) if kind == "sharp"]
    assert min(edge[k] for k in blurred if k in used) > max(sharp_edges)
    assert "dropped:" in stdout


def test_max_views_cap_keeps_coverage(charuco_folder, tmp_path, capsys):
    out = tmp_path / "c.json"
    code, _, err = run(["calibrate", str(charuco_folder), "--board", CHARUCO_SPEC, "--out", str(out),
                        "--max-views", "8", "--min-views", "6", "--no-progress"], capsys)
    assert code == 0, err
    report = json.loads((tmp_path / "c.report.json").read_text())
    assert report["num_views"] == 8
    assert sum("over the cap of 8 views" in d["reason"] for d in report["dropped"]) == 8
    assert report["coverage"] > 0.4  # greedy choice spreads the 8 views over the image
    cam = read_camera(out)
    assert abs(cam.fx / TRUE_K[0, 0] - 1) < 0.01  # fewer views: looser, still close


def test_calibration_flags_reach_opencv(charuco_folder, tmp_path, capsys):
    out = tmp_path / "c.json"
    code, _, err = run(["calibrate", str(charuco_folder), "--board", CHARUCO_SPEC, "--out", str(out),
                        "--fix-principal-point", "--fix-aspect-ratio", "--zero-tangent", "--max-views", "10",
                        "--no-progress"], capsys)
    assert code == 0, err
    c = read_camera(out)
    assert (c.cx, c.cy) == ((640 - 1) / 2, (480 - 1) / 2) and c.fx == c.fy
    assert c.dist[2] == c.dist[3] == 0.0 and c.dist[0] != 0.0
    report = json.loads((tmp_path / "c.report.json").read_text())
    assert all(report["flags"][k] for k in ("fix_principal_point", "fix_aspect_ratio", "zero_tangent"))
    assert report["model"] in {"k1-k2", "k1-k3", "k1-k6"}
    assert set(report["model_holdout_rms_px"]) == {"k1-k2", "k1-k3", "k1-k6"}
    assert set(report["std_dev"]) == {"fx", "fy", "k1", "k2"} | ({"k3"} if report["model"] != "k1-k2" else set()) \
        | ({"k4", "k5", "k6"} if report["model"] == "k1-k6" else set())


@pytest.mark.parametrize(
    "options, check",
    [
        (CalibrationOptions(fix_k3=True), lambda r: r.camera.dist[4] == 0.0 and r.model.radial == 2),
        (CalibrationOptions(rational=True), lambda r: r.camera.dist.size == 8 and r.model.radial == 6),
        (CalibrationOptions(model="k1-k3+p"), lambda r: list(r.model_scores) == ["k1-k3+p"]),
    ],
    ids=["fix-k3", "rational", "model"],
)
def test_model_restrictions(charuco_detections, options, check):
    obj, img = charuco_detections
    result = calibrate_views(obj, img, [f"v{i}" for i in range(len(obj))], IMAGE_SIZE, options)
    assert check(result)
    if result.model.radial == 6:  # k4..k6 trade off with fx on 16 views: only the fit is checked
        assert result.rms_px < 0.5 and abs(result.camera.fx / TRUE_K[0, 0] - 1) < 0.02
    else:
        assert_intrinsics_recovered(result.camera)


def test_outlier_view_is_rejected_and_recalibrated(charuco_detections):
    obj, img = charuco_detections
    img = [p.copy() for p in img]
    rng = np.random.default_rng(0)
    img[5] = img[5] + rng.normal(0, 3.0, img[5].shape).astype(np.float32)  # a mis-detected view
    labels = [f"v{i}" for i in range(len(obj))]
    result = calibrate_views(obj, img, labels, IMAGE_SIZE, CalibrationOptions())
    assert [v.label for v in result.rejected] == ["v5"]
    assert result.rejected[0].rms_px > 2.0
    assert "v5" not in [v.label for v in result.views] and len(result.views) == len(obj) - 1
    assert_intrinsics_recovered(result.camera)
    kept = calibrate_views(obj, img, labels, IMAGE_SIZE, CalibrationOptions(outlier_factor=0))
    assert kept.rms_px > 3 * result.rms_px  # without rejection the bad view dominates the RMS


def test_calibrate_checkerboard(tmp_path, capsys):
    renderer = Renderer(CHECKER_SPEC)
    poses = random_poses(renderer.board, TRUE_K, IMAGE_SIZE, 12, seed=5, fully_visible=True)
    rng = np.random.default_rng(3)
    folder = tmp_path / "checker"
    write_images(folder, [renderer.render(p, rng=rng) for p in poses], ".jpg")
    out = tmp_path / "checker.json"
    code, _, err = run(["calibrate", str(folder), "--board", CHECKER_SPEC, "--out", str(out), "--no-progress"],
                       capsys)
    assert code == 0, err
    assert_intrinsics_recovered(read_camera(out))


# ------------------------------------------------------------------------------------------ bad input
def test_error_board_spec_does_not_parse(charuco_folder, tmp_path, capsys):
    code, _, err = run(["calibrate", str(charuco_folder), "--board", "charuco:cols=9", "--out",
                        str(tmp_path / "c.json")], capsys)
    assert_one_line_error(code, err, "board spec for charuco is missing", "dict, marker, rows, square")
    assert not (tmp_path / "c.json").exists()


def test_error_no_board_in_any_frame(tmp_path, capsys):
    rng = np.random.default_rng(0)
    write_images(tmp_path / "noise", [rng.integers(0, 255, (480, 640), dtype=np.uint8) for _ in range(3)])
    code, _, err = run(["calibrate", str(tmp_path / "noise"), "--board", CHARUCO_SPEC, "--out",
                        str(tmp_path / "c.json"), "--no-progress"], capsys)
    assert_one_line_error(code, err, "no board found in any of the 3 frames", "3 no board detected", "check --board",
                          "ArUco dictionary")


def test_error_too_few_views(charuco, tmp_path, capsys):
    write_images(tmp_path / "few", charuco[2][:3])
    code, _, err = run(["calibrate", str(tmp_path / "few"), "--board", CHARUCO_SPEC, "--out",
                        str(tmp_path / "c.json"), "--no-progress"], capsys)
    assert_one_line_error(code, err, "too few usable views: found 3, need at least 4")


def test_error_wrong_board_gives_no_board(charuco_folder, tmp_path, capsys):
    """The footage's own dictionary is named (the smallest of its family that holds the ids seen), and the
    spec it suggests reads the board."""
    code, _, err = run(["calibrate", str(charuco_folder), "--board",
                        "charuco:cols=9,rows=7,square=30,marker=22,dict=DICT_4X4_50", "--out",
                        str(tmp_path / "c.json"), "--no-progress"], capsys)
    suggested = "charuco:cols=9,rows=7,square=30,marker=22,dict=DICT_5X5_50"
    assert_one_line_error(code, err, "no board found in any of the 16 frames", "markers of DICT_5X5_50 are in view",
                          "none of DICT_4X4_50", f"try --board {suggested}")
    image = cv2.imread(str(sorted(charuco_folder.iterdir())[0]), cv2.IMREAD_GRAYSCALE)
    assert BoardDetector(parse_board(suggested)).detect(image)[0] is not None


def _views(spec: str, n: int = 5) -> list[np.ndarray]:
    renderer = Renderer(spec)
    poses = random_poses(renderer.board, TRUE_K, IMAGE_SIZE, n, seed=3, fully_visible=renderer.board.kind == "checker")
    rng = np.random.default_rng(1)
    return [renderer.render(p, rng=rng) for p in poses]


def test_board_hint_names_charuco_markers_seen_as_a_checkerboard():
    """A ChArUco board given as a checkerboard of other dimensions: its markers are named (the CLI finds the
    8x6 chessboard of this ChArUco board's squares in some views and calibrates from those)."""
    from calib.board_hint import board_hint

    hint = board_hint(_views(CHARUCO_SPEC), parse_board("checker:cols=5,rows=4,square=30"))
    assert hint is not None and "ArUco markers of DICT_5X5_50 are in view" in hint and "ChArUco board" in hint


@pytest.mark.parametrize("printed, given, fragments", [
    (CHECKER_SPEC, "checker:cols=9,rows=7,square=30",
     ["a chessboard of 8x6 inner corners is in view", "try --board checker:cols=8,rows=6,square=30"]),
    (CHECKER_SPEC, "charuco:cols=9,rows=7,square=30,marker=22,dict=DICT_5X5_100",
     ["a chessboard without markers is in view", "try --board checker:cols=8,rows=6,square=30"]),
    ("charuco:cols=9,rows=6,square=30,marker=22,dict=DICT_5X5_100,legacy=1",
     "charuco:cols=9,rows=6,square=30,marker=22,dict=DICT_5X5_100",
     ["the board is found as --board charuco:cols=9,rows=6,square=30,marker=22,dict=DICT_5X5_100,legacy=1"]),
], ids=["squares-counted", "checker-given-as-charuco", "legacy-pattern"])
def test_error_names_the_board_in_view(printed, given, fragments, tmp_path, capsys):
    """When no frame has the board given, the error says what the frames show and the --board that reads it
    (the mistakes of real footage: squares counted for inner corners, the wrong kind of board, OpenCV's
    legacy ChArUco pattern); frames of noise keep the general advice (test_error_no_board_in_any_frame)."""
    write_images(tmp_path / "views", _views(printed))
    code, _, err = run(["calibrate", str(tmp_path / "views"), "--board", given, "--out", str(tmp_path / "c.json"),
                        "--no-progress"], capsys)
    assert_one_line_error(code, err, "no board found in any of the 5 frames", *fragments)
    assert not (tmp_path / "c.json").exists()


def test_error_unreadable_video(tmp_path, capsys):
    bad = tmp_path / "take.mp4"
    bad.write_bytes(b"this is not a video" * 100)
    code, _, err = run(["calibrate", str(bad), "--board", CHARUCO_SPEC, "--out", str(tmp_path / "c.json")], capsys)
    assert_one_line_error(code, err, f"cannot read video {bad}")


def test_error_images_of_different_sizes(charuco, tmp_path, capsys):
    folder = tmp_path / "mixed"
    write_images(folder, charuco[2][:6])
    cv2.imwrite(str(folder / "view_100.png"), cv2.resize(charuco[2][6], (800, 600)))
    code, _, err = run(["calibrate", str(folder), "--board", CHARUCO_SPEC, "--out", str(tmp_path / "c.json"),
                        "--no-progress"], capsys)
    assert_one_line_error(code, err, "images have different sizes", "640x480", "view_100.png is 800x600")


def test_error_missing_input_and_empty_folder(tmp_path, capsys):
    code, _, err = run(["calibrate", str(tmp_path / "nope.mp4"), "--board", CHARUCO_SPEC], capsys)
    assert_one_line_error(code, err, "does not exist")
    (tmp_path / "empty").mkdir()
    code, _, err = run(["calibrate", str(tmp_path / "empty"), "--board", CHARUCO_SPEC], capsys)
    assert_one_line_error(code, err, "no images in folder")


def test_error_bad_out_suffix(charuco_folder, tmp_path, capsys):
    code, _, err = run(["calibrate", str(charuco_folder), "--board", CHARUCO_SPEC, "--out",
                        str(tmp_path / "camera.txt")], capsys)
    assert_one_line_error(code, err, "must end in .json")


def test_help_documents_board_grammar(capsys):
    code, out, _ = run(["calibrate", "--help"], capsys)
    assert code == 0
    text = "".join(out.replace("│", " ").split())  # help may be wrapped in a rich panel
    assert "charuco:cols=C,rows=R,square=S,marker=M,dict=NAME" in text
    assert "checker:cols=C,rows=R,square=S" in text
    assert "ArUcodictionary" in text and "innercorners" in text and "INPUT" in text


def test_error_unknown_or_contradictory_model(charuco_folder, tmp_path, capsys):
    code, _, err = run(["calibrate", str(charuco_folder), "--board", CHARUCO_SPEC, "--out", str(tmp_path / "c.json"),
                        "--model", "k1-k9"], capsys)
    assert_one_line_error(code, err, "distortion model 'k1-k9' is unknown", "k1-k3+p")
    code, _, err = run(["calibrate", str(charuco_folder), "--board", CHARUCO_SPEC, "--out", str(tmp_path / "c.json"),
                        "--model", "k1-k3+p", "--fix-k3"], capsys)
    assert_one_line_error(code, err, "contradicts")
    assert not (tmp_path / "c.json").exists()
