"""A jaw found in the shapes' motion, for an actor trained without a jaw mesh.

Pure geometry: numpy arrays and a :class:`~models.face_frame.FaceFrame` in, a :class:`JawOpening` out.
Lengths are millimetres.

Without a jaw mesh no skin point is tied to a mandible, so nothing makes the actor's skinning weights
follow a jaw: it opens its mouth by displacements, as a blendshape rig does, and a partly open jaw
moves on straight lines instead of turning. Yet the scans show where the jaw is: in the shape that
opens the mouth, the skin over the mandible turns with it, and the rest of the face stays nearly still.

How :func:`find_jaw_opening` reads it, for each expression shape:

1. **A turn about the pivot.** The skin over a jaw stretches as it turns (on the sample the points over its
   fitted mandible follow the rigid turn that fits them best by 64-106 %, the quartiles), so the skin alone
   cannot say where the axis is: on ICT's identity B the turns about pivots anywhere in a 160 x 130 mm
   region behind the face fit the skin about as well
   (relative residual 0.21-0.40), and a free fit puts the axis 34 mm from the lower teeth's on the
   sample and 64 mm on B. So the axis passes through the given pivot (the anatomical estimate of
   :func:`~models.face_frame.estimate_jaw_pivot`, 17 and 2 mm from the teeth's axes there), and only
   the rotation is fitted: least squares about the pivot
   (:meth:`scipy.spatial.transform.Rotation.align_vectors`), to the points at least ``clearance_mm``
   from the lips that part in this shape (``lips``: they move for their own reasons and outnumber the
   skin over bone). Start from the ``seed_fraction`` of those points that move most, keep the points
   that follow the turn, refit, and repeat until the set stops changing. A point *follows* when the turn
   moves it at least ``min_motion_mm``, it moves at least ``follow_share`` of that along the turn's
   motion, and it ends within ``fit_tolerance`` of the turn's reach from where the turn puts it.
2. **A jaw opening** is a turn of at least ``min_angle_deg`` about an axis within ``max_tilt_deg`` of
   the face's lateral axis that moves the chin down (positive about ``symmetry_normal``, by the frame's
   convention), whose followers lie mostly below the nose tip.
3. The widest such opening wins. Every point that follows its motion (step 1's first two conditions,
   lips included) is jaw.

On the bundled sample and on identity B (``tests/test_jaw_motion.py``, the sample's fitted mandible for
truth): ``jawOpen`` is the only shape that opens the jaw, by 18-20 degrees (its lower teeth turn 24-27:
the skin's share), and most points over the fitted mandible follow it while almost none over the skull
do. The training then learns each shape's jaw transform (rotation and translation) from there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from capture.io.errors import CaptureError

__all__ = ["JawOpening", "find_jaw_opening", "rigid_turn", "following"]


@dataclass(frozen=True)
class JawOpening:
    """The widest jaw opening among the shapes, and the points that follow it.

    shape: index of the opening shape in the ``shapes`` given (0 is the rest pose, never chosen).
    angle_deg: its turn about the pivot. axis: (3,) unit axis of the turn, oriented so that the turn is
    positive about it. share: (M,) how much of the turn's motion each point follows in that shape (1 =
    turns with it).
    follows: (M,) bool, the jaw: points that the turn moves at least ``min_motion_mm`` and that follow
        at least ``follow_share`` of it.
    """

    shape: int
    angle_deg: float
    axis: np.ndarray
    share: np.ndarray
    follows: np.ndarray


def rigid_turn(rest: np.ndarray, moved: np.ndarray, about: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(K,3), (K,3) -> R (3,3), t (3,): the least-squares rigid motion ``moved ~ rest @ R.T + t``; with
    ``about`` (3,), the least-squares rotation about that point (``t = about - R about``)."""
    ca, cb = (rest.mean(0), moved.mean(0)) if about is None else (about, about)
    rot, _ = Rotation.align_vectors(moved - cb, rest - ca)
    R = rot.as_matrix()
    return R, cb - R @ ca


def following(rest: np.ndarray, moved: np.ndarray, R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(M,) share of the turn's motion each point follows, and (M,) how far the turn moves it (mm).

    ``share = (moved - rest) . m / |m|^2`` with ``m = R rest + t - rest``: 1 for a point that turns with
    the jaw, 0 for one that stays, above 1 for one that moves further the same way."""
    m = rest @ R.T + t - rest
    reach = np.linalg.norm(m, axis=1)
    share = np.einsum("mc,mc->m", moved - rest, m) / np.maximum(reach, 1e-9) ** 2
    return share, reach


@dataclass(frozen=True)
class _Turn:
    R: np.ndarray
    t: np.ndarray
    share: np.ndarray
    reach: np.ndarray


def _turn(rest: np.ndarray, moved: np.ndarray, pivot: np.ndarray, usable: np.ndarray, seed_fraction: float,
          follow_share: float, fit_tolerance: float, min_motion_mm: float, max_rounds: int = 50) -> _Turn | None:
    """The turn about ``pivot`` that the most-moving usable points start and their followers settle (module
    docstring, 1)."""
    motion = np.linalg.norm(moved - rest, axis=1)
    if usable.sum() < 3 or motion[usable].max() < min_motion_mm:
        return None
    keep = usable & (motion >= np.quantile(motion[usable], 1.0 - seed_fraction))
    for _ in range(max_rounds):
        if keep.sum() < 3:
            return None
        R, t = rigid_turn(rest[keep], moved[keep], pivot)
        share, reach = following(rest, moved, R, t)
        off = np.linalg.norm(rest @ R.T + t - moved, axis=1)
        new = usable & (share >= follow_share) & (reach >= min_motion_mm) & (off <= fit_tolerance * reach)
        if np.array_equal(new, keep):
            break
        keep = new
    return _Turn(R, t, share, reach) if keep.sum() >= 3 else None


def find_jaw_opening(
    rest: np.ndarray,
    shapes: np.ndarray,
    frame,
    pivot: np.ndarray,
    nose_tip: np.ndarray,
    lips: Sequence[np.ndarray] | None = None,
    *,
    clearance_mm: float = 25.0,
    min_angle_deg: float = 5.0,
    max_tilt_deg: float = 30.0,
    seed_fraction: float = 0.05,
    follow_share: float = 0.5,
    fit_tolerance: float = 0.5,
    min_motion_mm: float = 1.0,
) -> JawOpening | None:
    """The widest jaw opening among ``shapes`` (module docstring), or None when no shape opens the jaw.

    Args:
        rest: (M,3) points on the neutral skin, mm.
        shapes: (N,M,3) the same points in each shape; shape 0 is the rest pose (skipped).
        frame: the face frame (:class:`~models.face_frame.FaceFrame`).
        pivot: (3,) the jaw's centre of rotation (:func:`~models.face_frame.estimate_jaw_pivot`), mm.
        nose_tip: (3,) the nose tip (:func:`~models.face_frame.midline_landmarks`).
        lips: for each shape, (K_i,3) rest positions of the points of the lips that part in it (see
            :func:`models.input_chart.parted_vertices`); None or empty arrays where nothing parts.
    """
    rest = np.asarray(rest, dtype=np.float64)
    shapes = np.asarray(shapes, dtype=np.float64)
    if rest.ndim != 2 or rest.shape[1] != 3 or shapes.ndim != 3 or shapes.shape[1:] != rest.shape:
        raise CaptureError(f"jaw from motion: need rest points (M, 3) and shapes (N, M, 3), got {rest.shape} and "
                           f"{shapes.shape}")
    if lips is not None and len(lips) != len(shapes):
        raise CaptureError(f"jaw from motion: need the lips of each of the {len(shapes)} shapes, got {len(lips)}")
    n, tip = np.asarray(frame.symmetry_normal, dtype=np.float64), np.asarray(nose_tip, dtype=np.float64)
    pivot = np.asarray(pivot, dtype=np.float64)
    best = None
    for i in range(1, len(shapes)):
        usable = np.ones(len(rest), dtype=bool)
        if lips is not None and len(lips[i]):
            usable = cKDTree(np.asarray(lips[i], dtype=np.float64).reshape(-1, 3)).query(rest)[0] >= clearance_mm
        turn = _turn(rest, shapes[i], pivot, usable, seed_fraction, follow_share, fit_tolerance, min_motion_mm)
        if turn is None:
            continue
        rotvec = Rotation.from_matrix(turn.R).as_rotvec()
        angle = float(np.degrees(np.linalg.norm(rotvec)))
        if angle < min_angle_deg:
            continue
        axis = rotvec / np.linalg.norm(rotvec)
        if axis @ n < np.cos(np.radians(max_tilt_deg)):      # not lateral, or it closes the mouth
            continue
        follows = (turn.share >= follow_share) & (turn.reach >= min_motion_mm)
        if np.median((rest[follows] - tip) @ frame.up) >= 0:
            continue
        if best is None or angle > best.angle_deg:
            best = JawOpening(shape=i, angle_deg=angle, axis=axis, share=turn.share, follows=follows)
    return best
