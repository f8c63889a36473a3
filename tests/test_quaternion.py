"""models.quaternion against scipy.spatial.transform and scipy.ndimage (the independent reference), and the
fit's start (interpolated and smoothed PnP poses, the actor's jaw rotation vectors) without scipy."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation, Slerp

from models.quaternion import gaussian_smooth, matrix_from_quat, quat_from_matrix, rotvec_from_matrix, slerp_keys


def _rotations(n: int = 400, seed: int = 0) -> np.ndarray:
    """Random rotations plus the hard cases: identity, half turns about axes and near them, tiny angles."""
    R = Rotation.random(n, random_state=seed).as_matrix()
    special = [np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]
    for ang in (np.pi - 1e-9, np.pi - 1e-4, 1e-9, 1e-5):
        for axis in (np.array([1.0, 2, 3]) / np.sqrt(14), np.array([0, 0, 1.0])):
            special.append(Rotation.from_rotvec(ang * axis).as_matrix())
    return np.concatenate([R, np.stack(special)])


def test_quaternions_and_rotation_vectors_equal_scipys():
    R = _rotations()
    q = quat_from_matrix(R)
    ref = Rotation.from_matrix(R).as_quat()
    ref = np.where(ref[:, 3:] < 0, -ref, ref)
    # a half turn has w = 0: q and -q are the same rotation, compare the matrices there
    np.testing.assert_allclose(matrix_from_quat(q), R, atol=1e-12)
    far = ref[:, 3] > 1e-6
    np.testing.assert_allclose(q[far], ref[far], atol=1e-12)
    rv = rotvec_from_matrix(R)
    np.testing.assert_allclose(Rotation.from_rotvec(rv).as_matrix(), R, atol=1e-12)
    small = np.linalg.norm(Rotation.from_matrix(R).as_rotvec(), axis=1) < np.pi - 1e-3
    np.testing.assert_allclose(rv[small], Rotation.from_matrix(R[small]).as_rotvec(), atol=1e-12)


def test_slerp_and_gaussian_smoothing_equal_scipys():
    rng = np.random.default_rng(1)
    times = np.sort(rng.choice(60, 9, replace=False)).astype(float)
    keys = Rotation.random(9, random_state=2).as_matrix()
    at = np.linspace(times[0], times[-1], 200)
    np.testing.assert_allclose(slerp_keys(times, keys, at), Slerp(times, Rotation.from_matrix(keys))(at).as_matrix(),
                               atol=1e-12)
    x = rng.normal(size=(50, 4))
    for sigma in (0.6, 1.0, 2.5):
        np.testing.assert_allclose(gaussian_smooth(x, sigma), gaussian_filter1d(x, sigma, axis=0, mode="nearest"),
                                   atol=1e-13)
    np.testing.assert_allclose(gaussian_smooth(x[:2], 3.0), gaussian_filter1d(x[:2], 3.0, axis=0, mode="nearest"),
                               atol=1e-13)   # fewer samples than the kernel's radius


STREAM_SCRIPT = """
import sys
import numpy as np, cv2
from calib.camera import default_camera
from capture.actor.package import load_actor
from capture.fit.stream import fit_take_stream, pnp_model_points
from capture.fit.take import WindowedFit
actor = load_actor("capture/data/demo_actor")
tv = np.asarray(actor.template_vertices)
tp = tv[np.linspace(0, len(tv) - 1, 300).astype(int)]
cam = default_camera(640, 480)
mp = pnp_model_points(actor, tp)
rows = []
for j in range(12):
    R = np.diag([1.0, -1.0, -1.0]) @ cv2.Rodrigues(np.array([0.0, 0.02 * j, 0.0]))[0]
    t = -R @ tv.mean(0) + np.array([0.0, 0.0, 700.0])
    uv = cv2.projectPoints(mp, cv2.Rodrigues(R)[0], t, cam.K, cam.dist)[0][:, 0]
    uv[j % 5 == 4] = np.nan                       # a frame without a face: poses interpolated over it
    rows.append((uv, np.ones(len(uv)), j % 5 != 4))
fits = list(fit_take_stream(actor, iter(rows), tp, cam, WindowedFit("default", window=5, overlap=2)))
assert [f.frame for f in fits] == list(range(12))
print(" ".join(sorted({m.split(".")[0] for m in sys.modules if m.split(".")[0] == "scipy"})))
"""


@pytest.mark.slow
def test_a_streamed_2d_fit_does_not_import_scipy():
    """The fit process's path from rows to frame fits (PnP, poses interpolated over a gap and smoothed, the
    actor queried with its jaw rotations, the default LM solve) imports no scipy: its import cost the fit
    process 0.3-0.4 s before its first window."""
    repo = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", STREAM_SCRIPT], cwd=repo, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "", f"imported by a streamed fit: {out.stdout.strip()}"
