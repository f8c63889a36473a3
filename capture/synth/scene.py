"""Head-to-camera convention of synthetic takes (the one place it is defined) and the framing.

Frames:

* **Template / head frame** (the actor's template, mm): x = the actor's left, y = up, z = out of the
  face (forward, toward someone looking at the actor).
* **Camera frame** (OpenCV): x right, y down, z forward (into the scene).

A camera looking straight at the face sees the actor's left on the image's right, the actor's up as
image up and the face pointing back at the camera, so the frontal head rotation is
``R_FRONT = diag(1, -1, -1)`` (a proper rotation: 180 degrees about x). A head pose with angles
(yaw, pitch, roll) in the template frame (see :mod:`capture.synth.motion`) is

    R_g = R_FRONT @ Rz(roll) @ Ry(yaw) @ Rx(-pitch)
    t_g = placement - R_g @ pivot

and a head-frame point maps to camera coordinates as ``x_cam = R_g @ x + t_g`` (column vectors). The
pivot is the template's bounding-box centre, so ``placement`` (mm, camera frame) is where that centre
is seen: straight ahead at the framing distance plus the motion's offset.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from calib.camera import Camera
from calib.projection import project_points

#: The head rotation of a frontal view (template frame -> camera frame).
R_FRONT = np.diag([1.0, -1.0, -1.0])


def head_rotation(yaw_deg: np.ndarray, pitch_deg: np.ndarray, roll_deg: np.ndarray) -> np.ndarray:
    """Head rotations ``(T, 3, 3)`` (template frame -> camera frame) from angles ``(T,)`` in degrees.

    Positive yaw turns the face toward the actor's left (the image's right), positive pitch tilts
    the face up.
    """
    yaw, pitch, roll = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (yaw_deg, pitch_deg, roll_deg))
    local = Rotation.from_euler("ZYX", np.stack([roll, yaw, -pitch], 1), degrees=True).as_matrix()
    return R_FRONT[None] @ local


def framing_distance(camera: Camera, template_vertices: np.ndarray, fill: float = 0.75) -> float:
    """Distance (mm) at which the template's height fills ``fill`` of the image height."""
    v = np.asarray(template_vertices)
    height = float(v[:, 1].max() - v[:, 1].min())
    return camera.fy * height / (fill * camera.height)


def head_transforms(camera: Camera, template_vertices: np.ndarray, yaw_deg, pitch_deg, roll_deg,
                    offset_mm: np.ndarray, fill: float = 0.75) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame head transforms ``R_g (T, 3, 3)``, ``t_g (T, 3)`` mm (see the module docstring)."""
    v = np.asarray(template_vertices, dtype=np.float64)
    pivot = 0.5 * (v.min(0) + v.max(0))
    R = head_rotation(yaw_deg, pitch_deg, roll_deg)
    # Aim at the principal point: the pivot is seen at the image centre when the offset is zero.
    placement = np.array([0.0, 0.0, framing_distance(camera, v, fill)]) + np.asarray(offset_mm, dtype=np.float64)
    t = placement - np.einsum("tij,j->ti", R, pivot)
    return R, t


def to_camera(points: np.ndarray, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Head-frame points ``(*, P, 3)`` to camera coordinates with ``R (*, 3, 3)``, ``t (*, 3)``."""
    return np.einsum("...ij,...pj->...pi", R, points) + np.asarray(t)[..., None, :]


def project(camera: Camera, points_cam: np.ndarray) -> np.ndarray:
    """Pixels ``(*, P, 2)`` of camera-frame points ``(*, P, 3)`` through K and the OpenCV distortion
    (float64, through :func:`calib.projection.project_points`)."""
    p = torch.as_tensor(np.asarray(points_cam), dtype=torch.float64)
    K = torch.tensor(np.array(camera.K), dtype=torch.float64)
    dist = torch.tensor(np.array(camera.dist), dtype=torch.float64) if camera.dist.size else None
    return project_points(p, K, dist).numpy()
