"""Calibration you can trust (issue 15): views dropped only when unusable, lens model by hold-out,
honest uncertainty, and never worse than plain OpenCV on the same footage.

The comparison with plain OpenCV (``cv2.aruco.CharucoDetector`` + ``cv2.calibrateCamera``, default
flags, on the same images) uses renders with a known lens (tests/calib_synth.py) and the whole-image
model error: for a 4 px grid of pixels, the ray the true camera sees there projected with the
estimated camera (max of the pixel distance). The broad sweep (3 seeds x 6/8/12/20 views x clean /
blur / H.264 x weak / strong lens) is ``benchmarks/bench_calib.py``; a representative subset is here.
"""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

from benchmarks.bench_calib import K, LENSES, SIZE, SPEC, Case, model_error, run_case
from calib.board import parse_board
from calib.calibrate import CalibrationOptions, calibrate_views, solve
from calib.camera import Camera
from calib.checks import check_detection, corner_inconsistency
from calib.diagnostics import diagnose, missed_corners
from calib.detect import BoardDetector, Detection
from calib.models import OPENCV_DEFAULT
from calib.uncertainty import (implied_rotation, intrinsic_covariance, pixel_grid, pixel_uncertainty,
                              projection_difference)
from calib.views import Candidate, measure_edge_width, select_views
from capture.cli import main
from tests.calib_synth import Renderer, operator_poses, write_images


def synthetic_views(dist, n=12, seed=0, noise=0.1, K_true=K):
    """Exact projections of the board corners (cv2.projectPoints) plus Gaussian noise: no rendering."""
    board = parse_board(SPEC)
    poses = operator_poses(board, K_true, SIZE, n, seed=seed)
    rng = np.random.default_rng(seed)
    obj_all = board.corner_object_points().astype(np.float64)
    obj, img = [], []
    for p in poses:
        uv, _ = cv2.projectPoints(obj_all, p.rvec, p.tvec, K_true, dist)
        uv = uv.reshape(-1, 2)
        inside = (uv[:, 0] > 5) & (uv[:, 0] < SIZE[0] - 6) & (uv[:, 1] > 5) & (uv[:, 1] < SIZE[1] - 6)
        obj.append(obj_all[inside].astype(np.float32))
        img.append((uv[inside] + rng.normal(0, noise, uv[inside].shape)).astype(np.float32))
    return obj, img


def _plain(obj, img) -> Camera:
    _rms, Kp, dp, _r, _t = cv2.calibrateCamera(obj, img, SIZE, None, None)
    return Camera(Kp, dp.reshape(-1)[:5], SIZE)


# ------------------------------------------------------------------------------------ uncertainty math
def test_covariance_matches_opencv_standard_deviations():
    """Our Schur-complement covariance has OpenCV's stdDeviationsIntrinsics on its diagonal."""
    obj, img = synthetic_views(LENSES["strong"], n=10, seed=1)
    s = solve(obj, img, SIZE, OPENCV_DEFAULT, CalibrationOptions())
    cam = Camera(s.K, s.dist, SIZE)
    cov = intrinsic_covariance(cam, OPENCV_DEFAULT, obj, img, s.rvecs, s.tvecs)
    ours = cov.std()
    opencv = dict(zip(("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"), s.std_int[:9]))
    for name in cov.names:
        assert ours[name] == pytest.approx(opencv[name], rel=0.03), name
    # at the principal point only cx, cy move the projection: sigma = sqrt(var cx + var cy)
    sigma = pixel_uncertainty(cam, OPENCV_DEFAULT, cov, np.array([[cam.cx, cam.cy]]))
    assert sigma[0] == pytest.approx(np.hypot(ours["cx"], ours["cy"]), rel=1e-6)


def test_predicted_uncertainty_matches_monte_carlo_spread():
    """Re-calibrating with fresh noise scatters the image-corner projection as the covariance predicts."""
    dist = LENSES["weak"]
    corner = np.array([[10.0, 10.0], [320.0, 240.0]])
    truth = Camera(K, dist, SIZE)
    shifts, predicted = [], None
    exact_obj, exact_img = synthetic_views(dist, n=8, seed=3, noise=0.0)
    for trial in range(12):
        rng = np.random.default_rng(50 + trial)
        obj, img = exact_obj, [p + rng.normal(0, 0.2, p.shape).astype(np.float32) for p in exact_img]
        s = solve(obj, img, SIZE, OPENCV_DEFAULT, CalibrationOptions())
        cam = Camera(s.K, s.dist, SIZE)
        if predicted is None:
            cov = intrinsic_covariance(cam, OPENCV_DEFAULT, obj, img, s.rvecs, s.tvecs)
            predicted = pixel_uncertainty(cam, OPENCV_DEFAULT, cov, corner)
        shifts.append(projection_difference(truth, cam, corner))
    observed = np.sqrt(np.mean(np.square(shifts), axis=0))  # RMS over trials = 1-sigma of the 2-D error
    # 12 trials: the RMS is known to about +-20 %; a wrong covariance is off by factors
    assert np.all(observed / predicted > 0.6) and np.all(observed / predicted < 1.6), (observed, predicted)


def test_projection_difference_of_a_focal_change_is_radial_and_exact():
    a = Camera(K, np.zeros(5), SIZE)
    b = Camera(K * [[1.01, 1, 1], [1, 1.01, 1], [1, 1, 1]], np.zeros(5), SIZE)
    grid, _ = pixel_grid(SIZE, 40.0)
    d = projection_difference(a, b, grid)
    np.testing.assert_allclose(d, 0.01 * np.linalg.norm(grid - K[:2, 2], axis=1), atol=1e-6)
    assert projection_difference(a, a, grid).max() < 1e-9


def test_implied_rotation_matches_a_slow_reference():
    """The rotation that best aligns two cameras, against Nelder-Mead on the same sum of squared pixel
    distances written out for pinhole cameras in numpy (no OpenCV)."""
    from scipy.optimize import minimize
    from scipy.spatial.transform import Rotation

    a = Camera(K, np.zeros(5), SIZE)
    Kb = K.copy()
    Kb[0, 2] += 2.5  # a principal point 2.5 px right and 1.5 px up
    Kb[1, 2] -= 1.5
    b = Camera(Kb, np.zeros(5), SIZE)
    grid, _ = pixel_grid(SIZE, 40.0)
    rays = np.column_stack([(grid - K[:2, 2]) / np.diag(K)[:2], np.ones(len(grid))])

    def cost(rvec):
        v = rays @ Rotation.from_rotvec(rvec).as_matrix().T
        uv = v[:, :2] / v[:, 2:] * np.diag(Kb)[:2] + Kb[:2, 2]
        return np.sum((uv - grid) ** 2)

    ref = minimize(cost, np.zeros(3), method="Nelder-Mead",
                   options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 20000}).x
    np.testing.assert_allclose(implied_rotation(a, b, grid), ref, atol=1e-7)
    raw, aligned = projection_difference(a, b, grid), projection_difference(a, b, grid, align=True)
    # the 2.9 px shift is nearly a rotation (0.28 deg): its second-order rest is left, 0.3 px on average
    # and under 1 px in the image corners (about theta x^2 / f there)
    assert raw.min() > 2.9 and aligned.mean() < 0.35 and aligned.max() < 1.0, (raw.min(), aligned.mean(), aligned.max())
    np.testing.assert_allclose(np.sum(aligned ** 2), cost(ref), rtol=1e-6)


def test_predicted_uncertainty_up_to_rotation_matches_monte_carlo_spread():
    """Re-calibrating with fresh noise scatters the model, up to the camera's rotation, as the covariance
    with the rotation taken out predicts; and most of the fixed-frame uncertainty near the centre is that
    rotation (a principal point moving with the board poses)."""
    dist = LENSES["weak"]
    truth = Camera(K, dist, SIZE)
    grid, _ = pixel_grid(SIZE, 40.0)
    centre = int(np.argmin(np.linalg.norm(grid - K[:2, 2], axis=1)))
    exact_obj, exact_img = synthetic_views(dist, n=8, seed=3, noise=0.0)
    shifts, predicted, fixed = [], None, None
    for trial in range(12):
        rng = np.random.default_rng(50 + trial)
        img = [p + rng.normal(0, 0.2, p.shape).astype(np.float32) for p in exact_img]
        s = solve(exact_obj, img, SIZE, OPENCV_DEFAULT, CalibrationOptions())
        cam = Camera(s.K, s.dist, SIZE)
        if predicted is None:
            cov = intrinsic_covariance(cam, OPENCV_DEFAULT, exact_obj, img, s.rvecs, s.tvecs)
            predicted = pixel_uncertainty(cam, OPENCV_DEFAULT, cov, grid, modulo_rotation=True)
            fixed = pixel_uncertainty(cam, OPENCV_DEFAULT, cov, grid)
        shifts.append(projection_difference(truth, cam, grid, align=True))
    observed = np.sqrt(np.mean(np.square(shifts), axis=0))
    worst = int(np.argmax(predicted))
    for i in (worst, 0, len(grid) - 1):  # the image corners, where the model is least known
        assert 0.6 < observed[i] / predicted[i] < 1.6, (i, observed[i], predicted[i])
    assert predicted[centre] < 0.25 * fixed[centre], (predicted[centre], fixed[centre])


# ---------------------------------------------------------------------------------- view selection
def test_geometric_check_removes_misidentified_corners():
    obj, img = synthetic_views(LENSES["strong"], n=1, seed=4, noise=0.05)
    ids = np.arange(len(obj[0]))
    det = Detection(img[0].copy(), obj[0], ids)
    assert np.nanmax(corner_inconsistency(det, 30.0)) < 0.05  # strong distortion, still locally projective
    bad = det.image_points.copy()
    bad[[10, 11]] = bad[[11, 10]]  # two neighbours swapped: each is a square off
    checked, reason = check_detection(Detection(bad, det.object_points, ids), 30.0, min_corners=6)
    assert reason is None and len(checked.ids) == len(ids) - 2 and not {10, 11} & set(checked.ids.tolist())
    shuffled = det.image_points[np.random.default_rng(0).permutation(len(ids))]
    none, why = check_detection(Detection(shuffled, det.object_points, ids), 30.0, min_corners=6)
    assert none is None and why.startswith("fails the geometric check")



def test_geometric_check_keeps_a_partial_view_with_one_corner_off():
    """A view where only 3 corners can be checked (8 corners of a board half out of the image, as the detector
    leaves them at a strongly distorted corner): one of them off its neighbours' grid is removed and the view
    kept (plain OpenCV keeps it too)."""
    obj, img = synthetic_views(LENSES["strong"], n=1, seed=4, noise=0.05)
    grid = [tuple(g) for g in np.round(obj[0][:, :2] / 30.0).astype(int)]
    pattern = [(0, 0), (2, 0), (3, 0), (3, 1), (0, 2), (2, 2), (0, 3), (1, 3)]   # 3 of them have 5 neighbours
    base = next(g for g in sorted(grid) if all((g[0] + dx, g[1] + dy) in grid for dx, dy in pattern + [(1, 0)]))
    idx = np.array([grid.index((base[0] + dx, base[1] + dy)) for dx, dy in pattern])
    det = Detection(img[0][idx].copy(), obj[0][idx], idx)
    checked = np.flatnonzero(np.isfinite(corner_inconsistency(det, 30.0)))
    assert len(checked) == 3                    # one bad corner is a third of them
    square = np.linalg.norm(img[0][grid.index((base[0] + 1, base[1]))] - img[0][grid.index(base)])
    one = det.image_points.copy()
    one[checked[0]] += (0.5 * square, 0.0)      # half a square off
    kept, reason = check_detection(Detection(one, det.object_points, det.ids), 30.0, min_corners=6)
    assert reason is None and len(kept.ids) == 7 and det.ids[checked[0]] not in kept.ids



def test_neighbours_on_one_line_but_one_predict_nothing():
    """Five corners along a partial view's edge and one beside them do not determine a homography (it can turn
    about that edge), so they check no corner. Judged by them, exact corners of a blurred view pushed into the
    image's corner looked 0.21 square off, and the view was dropped, which plain OpenCV kept (7.1 against 2.5 px,
    BENCHMARKS.md). The rule equals the definition, 4 points with no 3 on a line, on every subset of a 3x3 grid
    (a slow reference)."""
    import itertools

    from calib.checks import _determines_a_homography

    def on_line(a, b, c):
        return abs((b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])) < 1e-9

    grid = [(float(i), float(j)) for i in range(3) for j in range(3)]
    for m in range(4, 8):
        for pts in itertools.combinations(grid, m):
            general = any(not any(on_line(*t) for t in itertools.combinations(q, 3))
                          for q in itertools.combinations(pts, 4))
            assert _determines_a_homography(np.array(pts)) == general, pts

    # the exact corners of such a view through the strong lens: row 5 (i = 0..4) and two of row 4
    board = parse_board(SPEC)
    ids = np.array([5 * 8 + i for i in range(5)] + [4 * 8 + 2, 4 * 8 + 3])
    obj = board.corner_object_points()[ids]
    rvec, tvec = np.array([0.3, -0.4, 0.2]), np.array([-170.0, -51.0, 343.0])   # near the bottom-left corner
    img = cv2.projectPoints(obj.astype(np.float64), rvec, tvec, K, LENSES["strong"])[0].reshape(-1, 2)
    assert img.min() > 0 and (img < SIZE).all()
    det = Detection(img.astype(np.float32), obj, ids)
    err = corner_inconsistency(det, board.square_mm)
    assert np.all(np.isfinite(err) == [False, True, True, True, False, False, False]), err
    assert np.nanmax(err) < 0.05, err    # the lens bends the row by 0.01-0.02 square over a few squares
    kept, reason = check_detection(det, board.square_mm, min_corners=6)
    assert reason is None and len(kept.ids) == 7


def test_a_view_of_six_corners_with_one_doubtful_is_kept_and_a_misread_one_judged_by_the_solve():
    """A view of exactly min_corners: removing its one corner that is off would leave too few, so the check keeps the
    view whole (plain OpenCV would use it); a corner a whole square off (a mis-read marker) then makes the view an
    outlier of the first solve, which drops it."""
    obj, img = synthetic_views(LENSES["weak"], n=8, seed=2, noise=0.05)
    grid = [tuple(g) for g in np.round(obj[0][:, :2] / 30.0).astype(int)]
    base = next(g for g in sorted(grid) if all((g[0] + dx, g[1] + dy) in grid for dx in range(3) for dy in range(2)))
    idx = np.array([grid.index((base[0] + dx, base[1] + dy)) for dy in range(2) for dx in range(3)])   # a 3 x 2 block
    square = np.linalg.norm(img[0][idx[1]] - img[0][idx[0]])
    for shift in (0.3, 1.0):
        pts = img[0][idx].copy()
        pts[0] += (shift * square, 0.0)
        assert np.nanmax(corner_inconsistency(Detection(pts, obj[0][idx], idx), 30.0)) > 0.2     # flagged
        det, reason = check_detection(Detection(pts, obj[0][idx], idx), 30.0, min_corners=6)
        assert reason is None and len(det.ids) == 6
    res = calibrate_views([det.object_points] + obj[1:], [det.image_points] + img[1:], [f"v{i}" for i in range(8)],
                          SIZE, CalibrationOptions())
    assert [v.label for v in res.rejected] == ["v0"]

def test_edge_width_measures_gaussian_and_motion_blur():
    renderer = Renderer(SPEC)
    pose = operator_poses(renderer.board, renderer.K, SIZE, 1, seed=2, tilt_deg=(5, 10))[0]
    pts = renderer.project(pose)
    pts = pts[(pts[:, 0] > 0) & (pts[:, 0] < 639) & (pts[:, 1] > 0) & (pts[:, 1] < 479)]
    sharp = measure_edge_width(renderer.render(pose, blur_sigma=0.5), pts)
    gauss = measure_edge_width(renderer.render(pose, blur_sigma=3.0), pts)
    motion = measure_edge_width(renderer.render(pose, blur_sigma=0.5, motion_blur_px=11), pts)
    assert sharp < 3.5
    assert gauss == pytest.approx(np.sqrt(2 * np.pi) * 3.0, rel=0.2)  # step edge: contrast / peak slope
    assert motion > 8.0  # the widest direction counts


def _candidate(label, frame, blur_px, x):
    pts = np.array([[x, 100.0], [x + 40, 100], [x, 140], [x + 40, 140]], np.float32)
    det = Detection(pts, np.zeros((4, 3), np.float32), np.arange(4) + 10 * frame)
    return Candidate(label, frame, det, blur_px, 40.0, (x / 640, 0.25), 0.01, (0.0, 0.0), frozenset({frame}))


def test_blur_rule_does_not_depend_on_the_other_views():
    sharp = [_candidate(f"s{i}", i, 2.0, 20.0 * i) for i in range(20)]
    soft = _candidate("soft", 30, 12.0, 5.0)  # 0.3 of a square: blurred but usable
    mush = _candidate("mush", 31, 20.0, 7.0)  # half a square: corners merge
    chosen, dropped = select_views(sharp + [soft, mush], SIZE, max_views=40)
    assert "soft" in [c.label for c in chosen] and len(chosen) == 21
    assert [d.label for d in dropped] == ["mush"] and dropped[0].reason.startswith("blurred")
    alone, _ = select_views([soft], SIZE)  # no sharper views to compare with: same verdict
    assert [c.label for c in alone] == ["soft"]


def test_near_duplicates_fill_the_cap_last():
    distinct = [_candidate(f"d{i}", i, 2.0, 60.0 * i) for i in range(6)]
    twins = [_candidate(f"t{i}", 10 + i, 2.5, 60.0 * i + 1.0) for i in range(6)]
    for t, d in zip(twins, distinct):  # same corner ids as their twin, moved 1 px
        t.detection.ids[:] = d.detection.ids
    chosen, dropped = select_views(distinct + twins, SIZE, max_views=40)
    assert len(chosen) == 12 and dropped == []  # under the cap: nothing to drop
    chosen, dropped = select_views(distinct + twins, SIZE, max_views=8)
    labels = {c.label for c in chosen}
    assert {f"d{i}" for i in range(6)} <= labels and len(labels) == 8  # distinct views first, then 2 twins
    assert sorted(d.reason for d in dropped) == sorted(f"near-duplicate of d{int(d.label[1:])}" for d in dropped)
    assert len(dropped) == 4


# ------------------------------------------------------------------------------------- model choice
def test_model_choice_keeps_tangential_and_refuses_an_unstable_rational_model():
    dist = np.array([-0.3, 0.12, 0.004, -0.003, -0.02])  # clear tangential terms
    obj, img = synthetic_views(dist, n=12, seed=5)
    res = calibrate_views(obj, img, [f"v{i}" for i in range(12)], SIZE, CalibrationOptions())
    assert res.model.tangential and res.model.radial != 6
    assert set(res.model_scores) == {"k1-k2", "k1-k2+p", "k1-k3+p", "k1-k6+p"}
    assert res.model_scores["k1-k2"] > 1.5 * res.model_scores[res.model.name]  # no p: cannot follow the lens
    truth = Camera(K, dist, SIZE)
    plain = _plain(obj, img)
    assert model_error(truth, res.camera)[0] <= model_error(truth, plain)[0] + 0.1


def test_few_views_missing_the_image_corners_no_worse_than_plain_and_warned():
    """Few views, none in the image corners: k3 is barely determined there. Whatever the model
    choice does, the result is within 0.5 px of plain OpenCV, and a result worse than 1 px warns."""
    dist = np.array([-0.2, 0.08, 0.0, 0.0, 0.0])
    objp = parse_board(SPEC).corner_object_points().astype(np.float64)
    truth = Camera(K, dist, SIZE)
    for seed in range(6):
        poses = operator_poses(parse_board(SPEC), K, SIZE, 6, seed=seed, distance=(420, 520), min_visible=1.0)
        rng = np.random.default_rng(seed)
        obj, img = [], []
        for p in poses:
            uv, _ = cv2.projectPoints(objp, p.rvec, p.tvec, K, dist)
            obj.append(objp.astype(np.float32))
            img.append((uv.reshape(-1, 2) + rng.normal(0, 0.1, (len(objp), 2))).astype(np.float32))
        options = CalibrationOptions()
        res = calibrate_views(obj, img, [f"v{i}" for i in range(6)], SIZE, options)
        ours, plain = model_error(truth, res.camera)[0], model_error(truth, _plain(obj, img))[0]
        assert ours <= plain + 0.5, (seed, ours, plain)
        if ours > 1.0:  # the run must say so, and where
            assert any("not covered" in w for w in diagnose(res, options).warnings), seed


# ---------------------------------------------------------------------------------- against OpenCV
@pytest.mark.parametrize("case", [
    Case(0, 6, "clean", "strong"),
    Case(1, 8, "blur", "weak"),
    Case(2, 6, "h264", "strong"),
    # the three runs of the 72-run sweep that came out more than 0.5 px worse than plain OpenCV when a
    # simpler model was chosen by its hold-out error alone (2.56 vs 1.51, 2.03 vs 1.43, 5.59 vs 5.09 px)
    Case(0, 6, "h264", "strong"),
    Case(2, 20, "blur", "strong"),
    Case(2, 6, "blur", "strong"),
], ids=lambda c: f"{c.lens}-{c.condition}-{c.views}views-seed{c.seed}")
def test_never_worse_than_plain_opencv(case):
    r = run_case(case)
    assert r["ours_max_px"] <= r["plain_max_px"] + 0.5, r
    assert r["ours_max_aligned_px"] <= r["plain_max_aligned_px"] + 0.5, r
    assert r["ours_max_aligned_px"] <= 1.0 or r["warnings"], r  # beyond 1 px the run must say it is unsure


def test_simpler_model_when_opencvs_extra_terms_are_undetermined(tmp_path):
    """The model choice still drops k3 when OpenCV's default cannot determine it at all. On this render
    (8 blurred views, none in the image corners; seed 18 is one of the seeds the thresholds were set
    on) and with OpenCV's own corners (the detector without recovered markers or the saddle step, what
    `capture calibrate` used before stop 55 and plain OpenCV uses), OpenCV's k3 runs away: its predicted
    uncertainty is 7-8 times k1-k2+p's, plain is 6.8 px off and k1-k2+p 1.4 px. (With today's corners
    the same footage determines k3: OpenCV's default model is 0.16 px off, in a scratch run of stop 55.)"""
    from benchmarks.bench_calib import render_case

    _inp, images, truth = render_case(Case(18, 8, "blur", "strong"), tmp_path)
    board = parse_board(SPEC)
    detector = BoardDetector(board, saddle=False, refine_markers=False)
    obj, img = [], []
    for gray in images:
        det, _ = detector.detect(gray)
        if det is not None:
            det, _ = check_detection(det, board.square_mm, detector.min_corners)
        if det is not None:
            obj.append(det.object_points)
            img.append(det.image_points)
    options = CalibrationOptions()
    res = calibrate_views(obj, img, [f"v{i}" for i in range(len(obj))], SIZE, options)
    assert res.model.name == "k1-k2+p"
    ours, plain = model_error(truth, res.camera)[0], model_error(truth, _plain(obj, img))[0]
    assert ours < plain - 3.0, (ours, plain)
    # and it says that OpenCV's default fits these views as well but lands several px elsewhere
    (undecided,) = [w for w in diagnose(res, options).warnings if w.startswith("lens model undecided: k1-k3+p ")]
    assert float(undecided.split("by up to ")[1].split(" px")[0]) > 3.0, undecided


def central_views_of_a_folding_lens(bad=(-0.2, 0.1, 0.0, 0.0, -0.5)):
    """8 views whose corners all lie within 0.55 of the optical axis (normalised), projected through distortion
    ``bad``: a lens there, but its k3 folds the image's corners back (no pixel beyond a radius of about 0.6 has
    a ray). OpenCV's default model fits these corners to 0.07 px and inherits the fold; by default k1-k2 cannot
    express it."""
    from tests.calib_synth import IMAGE_SIZE, TRUE_K, random_poses

    board = parse_board(SPEC)
    bad = np.asarray(bad, np.float64)
    obj0 = board.corner_object_points().astype(np.float64)
    rng = np.random.default_rng(0)
    obj, img = [], []
    for p in random_poses(board, TRUE_K, IMAGE_SIZE, 8, seed=3):
        cam = obj0 @ cv2.Rodrigues(np.asarray(p.rvec))[0].T + p.tvec
        keep = np.linalg.norm(cam[:, :2] / cam[:, 2:], axis=1) < 0.55
        uv = cv2.projectPoints(obj0[keep], p.rvec, p.tvec, TRUE_K, bad)[0].reshape(-1, 2)
        obj.append(obj0[keep].astype(np.float32))
        img.append((uv + rng.normal(0, 0.05, uv.shape)).astype(np.float32))
    return obj, img, IMAGE_SIZE


@pytest.mark.parametrize("seed", [0, 2, 4])
def test_a_strong_lens_seen_in_the_image_corners_is_solved_where_opencvs_start_fails(seed):
    """1920x1080, k1 -0.35: views that push the board into the image's corners (exact projections + 0.1 px noise).
    OpenCV's pinhole start ignores distortion, and from it Levenberg-Marquardt settles far off on seeds 0 and 4
    (fx 2,668 / 2,617 instead of 1,500, RMS 4.8 / 9.0 px, the model over 1,000 px off; 14 of 18 such sets, views
    8-20). The staged start (k1, then k1 and k2, then the model) reaches the noise floor; where OpenCV's start was
    fine (seed 2) both give the same solve."""
    from calib.solve import solve
    from tests.calib_synth import corner_poses

    K_hd = np.array([[1500.0, 0.0, 964.0], [0.0, 1500.0, 538.0], [0.0, 0.0, 1.0]])
    size, dist = (1920, 1080), np.array([-0.35, 0.16, 0.0006, -0.0004, -0.04])
    board = parse_board("charuco:cols=9,rows=6,square=30,marker=22,dict=DICT_5X5_100")
    objp = board.corner_object_points().astype(np.float64)
    rng = np.random.default_rng(seed)
    obj, img = [], []
    for p in corner_poses(board, K_hd, size, 8, seed=seed, dist=dist):
        uv = cv2.projectPoints(objp, p.rvec, p.tvec, K_hd, dist)[0].reshape(-1, 2)
        m = (uv[:, 0] > 10) & (uv[:, 0] < size[0] - 11) & (uv[:, 1] > 10) & (uv[:, 1] < size[1] - 11)
        obj.append(objp[m].astype(np.float32))
        img.append((uv[m] + rng.normal(0, 0.1, uv[m].shape)).astype(np.float32))
    rms, Kp, dp, _r, _t = cv2.calibrateCamera(obj, img, size, None, None)
    s = solve(obj, img, size, OPENCV_DEFAULT, CalibrationOptions())
    truth = Camera(K_hd, dist, size)
    grid, _ = pixel_grid(size, 16.0)
    assert s.rms < 0.16 and abs(s.K[0, 0] - 1500.0) < 5.0, (s.rms, s.K[0, 0])   # 0.1 px noise: RMS 0.13-0.14
    assert projection_difference(truth, Camera(s.K, s.dist, size), grid, align=True).max() < 1.0
    if seed == 2:
        assert rms == pytest.approx(s.rms, abs=1e-6) and np.allclose(Kp, s.K, atol=1e-3)
    else:   # the independent reference fails here: plain OpenCV from its own start
        assert rms > 3.0 and Kp[0, 0] > 2000.0, (rms, Kp[0, 0])


def test_a_lens_model_that_folds_over_inside_the_image_is_never_chosen():
    """Plain OpenCV returns a camera whose distortion does not invert over the image, which every camera
    reader (capture run's) refuses. ``capture calibrate`` sets that model aside, says so, and writes a model
    that is a lens; forced to that model it refuses instead of writing a file nothing can use."""
    from calib.camera_io import camera_problem
    from capture.io.errors import CaptureError

    obj, img, size = central_views_of_a_folding_lens()
    labels = [f"v{i}" for i in range(len(obj))]
    _rms, Kp, dp, _r, _t = cv2.calibrateCamera(obj, img, size, None, None)
    plain_problem = camera_problem(Camera(Kp, dp.reshape(-1)[:5], size))
    assert plain_problem and "do not invert" in plain_problem[0], plain_problem   # the independent reference

    result = calibrate_views(obj, img, labels, size)
    assert result.model.name != OPENCV_DEFAULT.name and camera_problem(result.camera) is None, result.model
    assert set(result.implausible) == {OPENCV_DEFAULT.name}, result.implausible
    assert "do not invert" in result.implausible[OPENCV_DEFAULT.name]
    # the hold-out check would have preferred the folding model: the choice is among the lenses only
    assert result.model_scores[OPENCV_DEFAULT.name] < result.model_scores[result.model.name]
    d = diagnose(result, CalibrationOptions())
    (w,) = [w for w in d.warnings if w.startswith(f"lens model {OPENCV_DEFAULT.name} fitted to these views is not")]
    assert f"{result.model.name} is used instead" in w and "\n" not in w, w
    # a rejected candidate that OpenCV alone would not have returned (the rational model) is only reported
    rational_only = dataclasses.replace(result, implausible={"k1-k6+p": "the distortion coefficients ... fold"})
    assert not any("not a real lens" in w for w in diagnose(rational_only, CalibrationOptions()).warnings)

    with pytest.raises(CaptureError, match=r"^the k1-k3\+p lens model fitted to these 8 views is not a real lens "
                                           r"\(the distortion coefficients .* do not invert .*--model k1-k2\)$"):
        calibrate_views(obj, img, labels, size, CalibrationOptions(model=OPENCV_DEFAULT.name))
    # a fold so strong that k1-k2 folds too (k2 -0.22): no candidate is a lens, and the run is refused
    obj, img, size = central_views_of_a_folding_lens((-0.28, 0.02, 0.0, 0.0, -0.5))
    with pytest.raises(CaptureError, match=r"^no lens model fitted to these 8 views is a real lens \(k1-k3\+p: the "
                                           r"distortion coefficients .* do not invert .*record more views"):
        calibrate_views(obj, img, labels, size)


def test_a_view_no_camera_can_pose_leaves_the_hold_out_check_working(tmp_path, monkeypatch):
    """A kept view that solvePnP (IPPE) cannot pose once made every model's hold-out error inf (no model choice, a
    warning that the check failed) and the report unwritable (JSON has no inf). That view was an H.264 frame with 6
    corners in two rows; the corner detection of stop 55 finds more corners there, so the failure is now simulated:
    the view with the fewest corners cannot be posed by any hold-out camera. It is left out of the pooled error and
    reported as null."""
    import calib.holdout
    from benchmarks.bench_calib import render_case
    from calib.pipeline import CalibrateSettings, run_calibrate

    inp, _images, _truth = render_case(Case(12, 8, "clean", "weak"), tmp_path)
    fewest = []
    real = calib.holdout.pnp_residuals

    def unposable(obj, img, K, dist):
        if len(obj) == min(fewest):
            return np.full(len(obj), np.inf)
        return real(obj, img, K, dist)

    def counting(obj, img, K, dist):
        fewest.append(len(obj))
        return real(obj, img, K, dist)

    monkeypatch.setattr(calib.holdout, "pnp_residuals", counting)
    run_calibrate(CalibrateSettings(input=inp, board=SPEC, out=tmp_path / "first.json", progress=False))
    monkeypatch.setattr(calib.holdout, "pnp_residuals", unposable)
    out = run_calibrate(CalibrateSettings(input=inp, board=SPEC, out=tmp_path / "cam.json", progress=False))
    report = json.loads(out.report.read_text())
    assert all(np.isfinite(v) for v in report["model_holdout_rms_px"].values()), report["model_holdout_rms_px"]
    unposed = [v for v in report["views"] if v["holdout_rms_px"] is None]
    assert len(unposed) == 1 and unposed[0]["corners"] == min(fewest), unposed
    assert not any("hold-out check failed" in w for w in report["warnings"])


def test_twenty_clean_views_none_dropped():
    r = run_case(Case(0, 20, "clean", "weak"))
    assert r["dropped"] == [] and r["ours_views"] == 20 == r["plain_views"]
    assert r["ours_max_px"] <= r["plain_max_px"] + 0.5, r
    assert r["ours_max_aligned_px"] <= 1.0 or r["warnings"], r  # seed 0 renders leave the image corners uncovered


# ------------------------------------------------------------------------- corners the detector missed
def _truly_in_view(renderer, pose) -> np.ndarray:
    """(N,) bool, the readable rule: each board corner and the points one square away along the board's axes,
    projected by the *true* camera and pose, all inside the image."""
    board = renderer.board.corner_object_points().astype(np.float64)
    ok = np.ones(len(board), bool)
    for d in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1)):
        pts = board + np.array([d[0], d[1], 0.0]) * renderer.board.square_mm
        uv = cv2.projectPoints(pts, np.asarray(pose.rvec, float), np.asarray(pose.tvec, float), renderer.K,
                               renderer.dist)[0].reshape(-1, 2)
        ok &= (uv[:, 0] >= 0) & (uv[:, 0] <= SIZE[0] - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= SIZE[1] - 1)
    return ok


def test_missed_corners_counts_what_the_true_camera_had_in_view():
    """Given the true camera and poses, the corners in view are exactly the readable rule's, the detected ones
    are those passed in, and every missed one is put where the true camera sees it."""
    renderer = Renderer(SPEC, K, LENSES["strong"], SIZE)
    poses = operator_poses(renderer.board, K, SIZE, 8, seed=4)
    board = renderer.board.corner_object_points()
    rng = np.random.default_rng(4)
    truth = Camera(K, LENSES["strong"], SIZE)
    obj, keep = [], []
    for p in poses:
        k = _truly_in_view(renderer, p) & (rng.random(len(board)) < 0.6)    # a detector that finds 60 % of them
        obj.append(board[k])
        keep.append(k)
    m = missed_corners(truth, board, obj, [p.rvec for p in poses], [p.tvec for p in poses], renderer.board.square_mm)
    for v, (p, k) in enumerate(zip(poses, keep)):
        in_view = _truly_in_view(renderer, p)
        assert m.in_view[v] == in_view.sum() > 0 and m.detected[v] == k.sum()
        assert np.allclose(np.sort(m.missed_px[m.missed_view == v], axis=0),
                           np.sort(renderer.project(p)[in_view & ~k], axis=0), atol=1e-6)
    assert m.fraction == pytest.approx(sum(k.sum() for k in keep) / sum(_truly_in_view(renderer, p).sum()
                                                                         for p in poses))


def test_blurred_board_corners_the_detector_missed_are_reported_and_warned(tmp_path):
    """On blurred renders the ChArUco detector misses many of the corners in view, on clean ones nearly none
    (98 %); the counts in view equal the true camera's, view by view; only the blurred footage is warned (below
    70 %), and told that the board came near the bare image corners without being detected. At a 1.8 px blur
    OpenCV's defaults found 46 %; with the missed markers recovered from the board's layout (stop 55) 72 %, so the
    blur here is 2.2 px (61 %)."""
    renderer = Renderer(SPEC, K, LENSES["strong"], SIZE)
    poses = operator_poses(renderer.board, K, SIZE, 10, seed=3)
    reports = {}
    looks = {"clean": dict(blur_sigma=0.5, noise_sigma=2.0), "blur": dict(blur_sigma=2.2, noise_sigma=3.0)}
    for name, look in looks.items():
        rng = np.random.default_rng(3)
        write_images(tmp_path / name, [renderer.render(p, rng=rng, **look) for p in poses])
        out = tmp_path / f"{name}.json"
        assert main(["calibrate", str(tmp_path / name), "--board", SPEC, "--out", str(out), "--no-progress"]) == 0
        reports[name] = json.loads((tmp_path / f"{name}.report.json").read_text())
        truth = {f"view_{k:03d}.png": int(_truly_in_view(renderer, p).sum()) for k, p in enumerate(poses)}
        for v in reports[name]["views"]:
            assert v["corners_in_view"] == truth[v["label"]], (name, v["label"])
    clean, blur = reports["clean"], reports["blur"]
    assert clean["corners_detected_fraction"] > 0.9 and blur["corners_detected_fraction"] < 0.7
    assert blur["corners_in_view"] == clean["corners_in_view"]
    assert not any("the detector found only" in w for w in clean["warnings"])
    assert any(w.startswith("the detector found only") for w in blur["warnings"])
    assert any("not covered" in w and "not detected" in w for w in blur["warnings"])
    assert any("not covered" in w and w.endswith("record the board in the image corners") for w in clean["warnings"])
    # the coverage map marks the missed corners in pure red, a colour its heat map (inferno) never takes
    red = {}
    for name in looks:
        png = cv2.imread(str(tmp_path / f"{name}.coverage.png"))
        red[name] = int(np.sum((png[..., 2] > 220) & (png[..., 1] < 40) & (png[..., 0] < 40)))
    assert red["blur"] > 5 * max(red["clean"], 1)


# ------------------------------------------------------------------------------- warnings, --strict
def test_strict_fails_when_the_image_corners_are_not_covered(tmp_path, capsys):
    renderer = Renderer(SPEC, K, LENSES["strong"], SIZE)
    poses = operator_poses(renderer.board, K, SIZE, 6, seed=8, distance=(700, 800), min_visible=1.0)
    rng = np.random.default_rng(0)
    folder = tmp_path / "centre"
    write_images(folder, [renderer.render(p, rng=rng) for p in poses])
    out = tmp_path / "cam.json"
    code = main(["calibrate", str(folder), "--board", SPEC, "--out", str(out), "--no-progress", "--strict"])
    stdout, err = capsys.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith("capture: error: calibration not trusted")
    assert "image corners top-left, top-right, bottom-left, bottom-right not covered" in lines[0]
    assert "warning: image corner" in stdout  # the summary still says what was found
    assert not out.exists()
    report = json.loads((tmp_path / "cam.report.json").read_text())
    assert report["camera_written"] is False and any("not covered" in w for w in report["warnings"])
    assert report["uncertainty"]["max_px"] > report["uncertainty"]["median_px"] > 0
    png = tmp_path / "cam.coverage.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and cv2.imread(str(png)).shape[1] > 1000
