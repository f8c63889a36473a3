"""The take-level fit on a synthetic take of the tiny actor: accuracy, seams, robustness, bridging, resume, fit3d.

The take (48 frames, 320x240, preset ``talk``, 200 landmarks) is rendered from the actor itself, so
the truth is exactly representable; the fit sees the true landmarks plus 0.5 px Gaussian noise.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import capture.fit.take as fit_take_mod
from calib.camera_io import read_camera
from capture.actor.package import load_actor
from capture.fit.take import (FrameFit, TakeLandmarks, WindowedFit, fit_meshes, fit_take, resolved_settings_dict,
                              window_plan)
from models.fit import FIT_PRESETS
from tests.tiny_actor import synth_tiny_take, train_tiny_actor

WINDOW, OVERLAP = 16, 4  # windows [0,16) [12,28) [24,40) [36,48): three borders in 48 frames
SETTINGS = replace(FIT_PRESETS["default"], iterations=300, warm_iterations=100)
NO_FACE = [20, 21, 22]


@pytest.fixture(scope="module")
def take(tmp_path_factory):
    root = tmp_path_factory.mktemp("fit_take")
    actor_path = train_tiny_actor(root)
    out = synth_tiny_take(actor_path, root / "take", frames=48)
    actor = load_actor(str(actor_path))
    lm = np.load(out / "truth_landmarks.npz")
    tv, tf = np.asarray(actor.template.vertices), np.asarray(actor.template.faces)
    template_points = np.einsum("lk,lkc->lc", lm["barycentric"], tv[tf[lm["face_index"]]])
    rng = np.random.default_rng(0)
    points = lm["points_2d"] + rng.normal(0.0, 0.5, lm["points_2d"].shape)
    weights = lm["visible"].astype(np.float64)
    found = np.ones(len(points), bool)
    found[NO_FACE] = False
    points[NO_FACE] = np.nan
    return dict(actor=actor, camera=read_camera(out / "camera.json"), points=points, weights=weights, found=found,
                template_points=template_points, truth=np.load(out / "truth_meshes.npz")["vertices"], root=root)


def run(take, points=None, cache_dir=None, **kw) -> list[FrameFit]:
    lm = TakeLandmarks(take["points"] if points is None else points, take["weights"], take["found"],
                       take["template_points"])
    return list(fit_take(take["actor"], lm, take["camera"],
                         WindowedFit(SETTINGS, WINDOW, OVERLAP, cache_dir=cache_dir, threads=1), **kw))


@pytest.fixture(scope="module")
def clean(take):
    return run(take)


def vertex_errors(fits, truth):
    V = np.stack([f.vertices for f in fits])
    return np.linalg.norm(V - truth, axis=2)  # (T, V) mm


def test_window_plan():
    assert window_plan(48, 16, 4) == [(0, 16), (12, 28), (24, 40), (36, 48)]
    assert window_plan(10, 30, 6) == [(0, 10)]
    with pytest.raises(ValueError, match="overlap"):
        window_plan(10, 4, 4)


def test_accuracy_and_reprojection(take, clean):
    assert [f.frame for f in clean] == list(range(48))
    f0 = clean[0]
    assert f0.vertices.shape == take["truth"].shape[1:] and f0.vertices.dtype == np.float32
    assert f0.landmarks_fit.shape == (200, 2) and f0.coefficients_landmarks.shape[0] == 200
    np.testing.assert_allclose(f0.head_R @ f0.head_R.T, np.eye(3), atol=1e-5)
    fitted = np.array([f.status == "fitted" for f in clean])
    err = vertex_errors(clean, take["truth"])
    rms = np.array([f.reprojection_rms_px for f in clean])[fitted]
    # 0.5 px noise per axis gives residuals of 0.5 * sqrt(2) = 0.71 px RMS at the truth.
    assert rms.mean() <= 1.0, rms
    # The face spans ~100 px, so 1 px is ~1.5 mm across the image and ~10 mm in depth: monocular
    # depth is the weak direction. Measured 0.4-0.5 mm mean (mostly per-frame depth); bound 0.8 mm.
    assert err[fitted].mean() < 0.8, err[fitted].mean()


def test_bridged_frames(take, clean):
    status = [f.status for f in clean]
    assert [j for j, s in enumerate(status) if s == "bridged"] == NO_FACE
    assert all(np.isnan(clean[j].reprojection_rms_px) for j in NO_FACE)
    err = vertex_errors(clean, take["truth"]).mean(1)
    # Three frames (0.12 s) bridged by the temporal prior: the face stays near the truth.
    assert err[NO_FACE].max() < 2.0, err[NO_FACE]


def test_no_seam_at_window_borders(take, clean):
    """Vertex velocity error (fit minus truth) at the window borders is no larger than inside windows."""
    V = np.stack([f.vertices for f in clean]).astype(np.float64)
    dv = np.linalg.norm(np.diff(V, axis=0) - np.diff(take["truth"], axis=0), axis=2).mean(1)  # (T-1,) mm/frame
    border = set()
    for (s, e), (s2, _) in zip(window_plan(48, WINDOW, OVERLAP)[:-1], window_plan(48, WINDOW, OVERLAP)[1:]):
        border |= set(range(s2 - 1, e))  # steps into, across and out of the blended overlap
    bridging = {j for j in range(47) if j in NO_FACE or j + 1 in NO_FACE}
    inside = [j for j in range(47) if j not in border and j not in bridging]
    at = [j for j in sorted(border) if j not in bridging]
    # Both are dominated by the per-frame noise of a 0.5 px monocular fit (~0.4 mm/frame); a seam would
    # add a step of the size of the two windows' disagreement (~1-3 mm) at one frame.
    assert np.mean(dv[at]) <= 1.25 * np.mean(dv[inside]), (dv[at], dv[inside])
    assert dv[at].max() <= 1.5 * dv[inside].max(), (dv[at], dv[inside])


def test_robust_to_wild_landmarks(take, clean):
    rng = np.random.default_rng(1)
    bad = take["points"].copy()
    T, L = bad.shape[:2]
    mask = rng.random((T, L)) < 0.05
    ang = rng.uniform(0, 2 * np.pi, (T, L))
    bad[mask] += 50.0 * np.stack([np.cos(ang), np.sin(ang)], -1)[mask]
    fits = run(take, points=bad)
    fitted = np.array([f.status == "fitted" for f in clean])
    e_clean = vertex_errors(clean, take["truth"])[fitted].mean()
    e_bad = vertex_errors(fits, take["truth"])[fitted].mean()
    # 5 % of the landmarks 50 px off would move a squared-loss fit by millimetres; the pseudo-Huber
    # loss (1 px in the default preset) and the RANSAC PnP keep it within 0.15 mm of the clean fit.
    assert e_bad < e_clean + 0.15, (e_clean, e_bad)


def test_resume_gives_the_same_outputs(take, clean, tmp_path, monkeypatch):
    cache = tmp_path / "cache"

    class Stop(Exception):
        pass

    def stop_after_window_2(done, total):
        if done == 30:  # frames 0-29 out: windows 0, 1 and 2 are solved and cached
            raise Stop

    with pytest.raises(Stop):
        run(take, cache_dir=cache, progress=stop_after_window_2)
    assert sorted(p.name for p in cache.glob("win_*.npz")) == ["win_000000.npz", "win_000012.npz", "win_000024.npz"]
    solves = []
    real = fit_take_mod.fit_sequence
    monkeypatch.setattr(fit_take_mod, "fit_sequence", lambda *a, **k: solves.append(1) or real(*a, **k))
    resumed = run(take, cache_dir=cache)
    assert len(solves) == 1  # only the last window was solved again
    for a, b in zip(clean, resumed):
        assert a.frame == b.frame and a.status == b.status
        for name in ("vertices", "head_R", "head_t", "jaw_R", "code", "coefficients_landmarks", "landmarks_fit"):
            np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=1e-5, err_msg=name)
    # the 2D default (F_W zero): each window's coefficients are stored as one row per frame, the fit's rows
    with np.load(cache / "win_000000.npz", allow_pickle=False) as z:
        assert "coefficients_landmarks" not in z.files
        rows, counts = z["coefficients_landmarks@row"], z["coefficients_landmarks@rows"]
    assert rows.shape == (WINDOW, clean[0].coefficients_landmarks.shape[1]) and (counts == len(take["template_points"])).all()
    for f in clean[:WINDOW - OVERLAP]:                 # frames of the first window that no blend touches
        np.testing.assert_array_equal(np.asarray(f.coefficients_landmarks), np.tile(rows[f.frame], (counts[0], 1)))


def test_fit_meshes_known_answer(take):
    truth = take["truth"][:20]
    fits = list(fit_meshes(take["actor"], iter(truth), WindowedFit(SETTINGS, WINDOW, OVERLAP, threads=1),
                           n_samples=300))
    assert [f.frame for f in fits] == list(range(20))
    err = np.array([f.error3d_mm for f in fits])
    np.testing.assert_allclose(err, vertex_errors(fits, truth).mean(1), rtol=1e-5)
    # The meshes are the actor's own shapes, fitted with 300 of 1,785 vertices: sub-0.2 mm everywhere.
    assert err.mean() < 0.2, err


def test_bad_inputs(take):
    with pytest.raises(ValueError, match="weights"):
        fit_take(take["actor"], TakeLandmarks(take["points"], take["weights"][:, :10], None, take["template_points"]),
                 take["camera"])
    with pytest.raises(ValueError, match="unknown fit preset"):
        fit_take(take["actor"], TakeLandmarks(take["points"], take["weights"], None, take["template_points"]),
                 take["camera"], WindowedFit("fast"))
    d = resolved_settings_dict("paper", 30, 6)
    assert d["preset"] == "paper" and d["fit"]["iterations"] == 10_000 and d["window"] == 30


def test_warm_state_carries_the_base_of_the_overlap_frames():
    """A warm start keeps the solved base (head, jaw, coefficient offsets) of the overlap frames."""
    import torch

    from capture.fit.take import _warm_state

    J, E, f = 6, 3, 4
    prev = {"codes": torch.arange(J * f, dtype=torch.float32).reshape(J, f),
            "head_R0": torch.eye(3).expand(J, 3, 3) * torch.arange(1, J + 1)[:, None, None],
            "head_t0": torch.arange(J * 3, dtype=torch.float32).reshape(J, 3),
            "jaw_R0": torch.eye(3).expand(J, 3, 3) * -torch.arange(1, J + 1)[:, None, None],
            "jaw_t0": -torch.arange(J * 3, dtype=torch.float32).reshape(J, 3),
            "coeff0": torch.arange(J * E, dtype=torch.float32).reshape(J, E),
            "field": torch.arange(J * 2 * E, dtype=torch.float32).reshape(J, 2, E)}
    R_new, t_new = torch.full((5, 3, 3), 7.0), torch.full((5, 3), 9.0)
    st = _warm_state(prev, 10, 16, 14, 5, R_new, t_new)  # frames 14, 15 overlap; 16-18 are new
    for k in ("codes", "jaw_R0", "jaw_t0", "coeff0", "field"):
        torch.testing.assert_close(st[k][:2], prev[k][4:6], msg=k)
        torch.testing.assert_close(st[k][2:], prev[k][5:6].expand_as(st[k][2:]), msg=k)
    torch.testing.assert_close(st["head_R0"][:2], prev["head_R0"][4:6])
    torch.testing.assert_close(st["head_t0"][:2], prev["head_t0"][4:6])


def test_warm_state_moves_the_new_frames_by_the_last_overlap_frames_correction():
    """New frames start at their initial pose moved by the rigid correction the solve made at the last
    overlap frame: if the solve moved every initial pose by one rigid transform, the new frames get it;
    without overlap they start at their initial poses."""
    import torch
    from scipy.spatial.transform import Rotation

    from capture.fit.take import _warm_state

    g = torch.Generator().manual_seed(0)
    R_init = torch.tensor(Rotation.random(9, random_state=1).as_matrix(), dtype=torch.float64)  # frames 10-18
    t_init = 600.0 + 20 * torch.randn(9, 3, generator=g, dtype=torch.float64)
    C = torch.tensor(Rotation.from_rotvec([0.05, -0.1, 0.02]).as_matrix(), dtype=torch.float64)
    d = torch.tensor([3.0, -2.0, 15.0], dtype=torch.float64)
    solved_R, solved_t = C @ R_init, t_init @ C.T + d
    prev = {"head_R0": solved_R[:6].clone(), "head_t0": solved_t[:6].clone(), "coeff0": torch.zeros(6, 2)}
    st = _warm_state(prev, 10, 16, 14, 5, R_init[4:], t_init[4:])   # frames 14, 15 overlap; 16-18 are new
    torch.testing.assert_close(st["head_R0"], solved_R[4:])
    torch.testing.assert_close(st["head_t0"], solved_t[4:])
    # a correction that differs from frame to frame: the new frames take the last overlap frame's (frame 15)
    prev["head_R0"][4] = R_init[4]
    st = _warm_state(prev, 10, 16, 14, 5, R_init[4:], t_init[4:])
    torch.testing.assert_close(st["head_R0"][2:], solved_R[6:])
    st = _warm_state(prev, 10, 16, 16, 3, R_init[6:], t_init[6:])   # no overlap: the initial poses
    torch.testing.assert_close(st["head_R0"], R_init[6:])
    torch.testing.assert_close(st["head_t0"], t_init[6:])


def _fit(take, settings, points=None, timings=None) -> list[FrameFit]:
    lm = TakeLandmarks(take["points"] if points is None else points, take["weights"], take["found"],
                       take["template_points"])
    return list(fit_take(take["actor"], lm, take["camera"], WindowedFit(settings, WINDOW, OVERLAP, threads=1),
                         timings=timings))


def test_noise_adaptive_smoothing_reads_the_noise_and_is_the_tuned_prior_at_scale_1(take, clean):
    """The default reads the landmarks' noise from its residuals (0.5 px added here; the tiny actor explains
    its own take, so the residuals are that noise) and scales the coefficients' temporal prior by
    models.fit_noise's rule; where the rule gives 1 the fit is the fixed prior's, to the bit (no second
    solve, the same settings)."""
    from models.fit_noise import temporal_prior_scale

    assert SETTINGS.adaptive_ref_px > 0
    tm: dict = {}
    fits = _fit(take, SETTINGS, timings=tm)
    np.testing.assert_array_equal(np.stack([f.vertices for f in fits]), np.stack([f.vertices for f in clean]))
    assert 0.45 < tm["landmark_noise_px"] < 0.6
    assert 140 < tm["landmarks_per_frame"] < 200 and 0 < tm["face_px_per_mm"] < SETTINGS.adaptive_ref_px_per_mm
    k = temporal_prior_scale(tm["landmark_noise_px"], tm["landmarks_per_frame"], SETTINGS.adaptive_ref_px,
                             SETTINGS.adaptive_ref_landmarks, SETTINGS.adaptive_max, tm["face_px_per_mm"],
                             SETTINGS.adaptive_ref_px_per_mm)
    # a fifth of the tuning's landmarks on a face half its size in the image: 5 x 0.5^2, a little above 1
    assert 1 < tm["temporal_prior_scale_min"] <= tm["temporal_prior_scale_max"] < 2
    assert 0.95 * tm["temporal_prior_scale_min"] <= k <= 1.05 * tm["temporal_prior_scale_max"]
    fixed = _fit(take, replace(SETTINGS, adaptive_ref_px=0.0))
    at_one = _fit(take, replace(SETTINGS, adaptive_ref_landmarks=1.0))     # the rule's k < 1: clamped to 1
    np.testing.assert_array_equal(np.stack([f.vertices for f in at_one]), np.stack([f.vertices for f in fixed]))
    assert np.abs(np.stack([f.vertices for f in fits]) - np.stack([f.vertices for f in fixed])).max() > 1e-3


def test_noise_adaptive_smoothing_resumes_from_the_cache_to_the_same_fit(take, clean, tmp_path):
    """The scale of each window comes from the one before: a fit resumed from cached windows (each read back,
    not solved) carries the same scales and gives the same frames as the fit in one go."""
    lm = TakeLandmarks(take["points"], take["weights"], take["found"], take["template_points"])
    how = WindowedFit(SETTINGS, WINDOW, OVERLAP, cache_dir=tmp_path / "cache", threads=1)
    first: dict = {}
    list(fit_take(take["actor"], lm, take["camera"], how, timings=first))
    again: dict = {}
    fits = list(fit_take(take["actor"], lm, take["camera"], how, timings=again))
    assert again["windows_solved"] == 0 and again["windows_cached"] == first["windows_solved"] > 1
    assert again["temporal_prior_scale_max"] == first["temporal_prior_scale_max"] > 1
    np.testing.assert_array_equal(np.stack([f.vertices for f in fits]), np.stack([f.vertices for f in clean]))
