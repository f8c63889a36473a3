"""Synthetic calibration footage with known truth: boards rendered through a known distorted camera.

Rendering (all OpenCV or plain numpy, independent of the code under test):

1. A flat board texture: ``CharucoBoard.generateImage`` (ChArUco) or numpy squares (checker), with a
   white quiet zone, at ``px_per_mm`` texture pixels per millimetre.
2. For every pixel of the output (rendered at ``supersample`` times the resolution) the
   *undistorted* pixel is found with ``cv2.undistortPointsIter`` (many iterations, so exact to ~1e-6 px),
   turned into a ray and intersected with the board plane of the view's known pose (the inverse
   homography ``(K [r1 r2 t])^-1``); the texture is sampled there with ``cv2.remap``.
3. The supersampled image is area-averaged down (``INTER_AREA``; with the pixel-centre convention
   ``u_ss = s (u + 0.5) - 0.5`` this is exactly consistent with ``K``), blurred and given noise.

So each view is what a real camera with intrinsics ``K`` and distortion ``dist`` would record of the
board at pose ``(rvec, tvec)`` (board to camera, as OpenCV's calibration returns).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calib.board import BoardSpec, parse_board

CHARUCO_SPEC = "charuco:cols=9,rows=7,square=30,marker=22,dict=DICT_5X5_100"
CHECKER_SPEC = "checker:cols=8,rows=6,square=30"

# A 640x480 camera with a slightly non-square pixel, an off-centre principal point and
# barrel distortion typical of a wide-ish lens (about 0.9 % edge displacement at the corners).
TRUE_K = np.array([[600.0, 0.0, 322.3], [0.0, 604.0, 236.8], [0.0, 0.0, 1.0]])
TRUE_DIST = np.array([-0.22, 0.09, 0.0008, -0.0006, -0.02])
IMAGE_SIZE = (640, 480)


@dataclass(frozen=True)
class Pose:
    rvec: np.ndarray  # (3,) board -> camera rotation, axis-angle
    tvec: np.ndarray  # (3,) mm


def board_texture(board: BoardSpec, px_per_mm: float, margin_mm: float) -> tuple[np.ndarray, float, float]:
    """Texture image and the affine map ``tex_px = a * board_mm + b`` (same for x and y)."""
    w_mm, h_mm = board.size_mm
    margin_px = int(round(margin_mm * px_per_mm))
    W = int(round(w_mm * px_per_mm)) + 2 * margin_px
    H = int(round(h_mm * px_per_mm)) + 2 * margin_px
    if board.kind == "charuco":
        cv_board = cv2.aruco.CharucoBoard(
            (board.cols, board.rows), board.square_mm, board.marker_mm,
            cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, board.dictionary)),
        )
        cv_board.setLegacyPattern(board.legacy)
        tex = cv_board.generateImage((W, H), marginSize=margin_px)
        # OpenCV puts ChArUco object point (0, 0) at the board's outer corner.
        return tex, px_per_mm, margin_px - 0.5
    # checker: (cols + 1) x (rows + 1) squares; object point (0, 0) is the first inner corner.
    ys, xs = np.mgrid[0:H, 0:W]
    X = (xs + 0.5 - margin_px) / px_per_mm
    Y = (ys + 0.5 - margin_px) / px_per_mm
    inside = (X >= 0) & (Y >= 0) & (X < w_mm) & (Y < h_mm)
    black = ((np.floor(X / board.square_mm) + np.floor(Y / board.square_mm)) % 2 == 0) & inside
    tex = np.where(black, 0, 255).astype(np.uint8)
    return tex, px_per_mm, margin_px - 0.5 + board.square_mm * px_per_mm


def random_poses(board: BoardSpec, K: np.ndarray, image_size, n: int, seed: int = 0,
                 distance=(380.0, 560.0), max_tilt_deg: float = 40.0, fully_visible: bool = False) -> list[Pose]:
    """Poses spread over the image and over tilts, keeping the board (mostly) in view."""
    rng = np.random.default_rng(seed)
    w, h = image_size
    obj = board.corner_object_points().astype(np.float64)
    centre = np.array([*np.array(board.size_mm) / 2.0, 0.0])
    if board.kind == "checker":
        centre[:2] -= board.square_mm
    poses: list[Pose] = []
    Kinv = np.linalg.inv(K)
    while len(poses) < n:
        k = len(poses)
        # a 3x3 grid of targets plus random jitter, so the views cover the image
        gx, gy = (k % 3), (k // 3) % 3
        target = np.array([w * (0.25 + 0.25 * gx), h * (0.25 + 0.25 * gy)]) + rng.normal(0, 0.05, 2) * (w, h)
        z = rng.uniform(*distance)
        pos = z * (Kinv @ np.array([target[0], target[1], 1.0]))
        tilt = np.radians(rng.uniform(-max_tilt_deg, max_tilt_deg, 2))
        roll = np.radians(rng.uniform(-20, 20))
        R = cv2.Rodrigues(np.array([tilt[0], 0, 0]))[0] @ cv2.Rodrigues(np.array([0, tilt[1], 0]))[0] \
            @ cv2.Rodrigues(np.array([0, 0, roll]))[0]
        t = pos - R @ centre
        cam = obj @ R.T + t
        if np.any(cam[:, 2] <= 50):
            continue
        uv = cam[:, :2] / cam[:, 2:] * (K[0, 0], K[1, 1]) + K[:2, 2]
        visible = (uv[:, 0] > 8) & (uv[:, 0] < w - 9) & (uv[:, 1] > 8) & (uv[:, 1] < h - 9)
        if (fully_visible and not visible.all()) or visible.mean() < 0.6:
            continue
        poses.append(Pose(cv2.Rodrigues(R)[0].ravel(), t))
    return poses


class Renderer:
    """Renders one board through one camera; the undistortion map is computed once."""

    def __init__(self, board: BoardSpec | str, K=TRUE_K, dist=TRUE_DIST, image_size=IMAGE_SIZE,
                 supersample: int = 2, px_per_mm: float = 6.0, margin_mm: float = 20.0):
        self.board = parse_board(board) if isinstance(board, str) else board
        self.K = np.asarray(K, np.float64)
        self.dist = np.asarray(dist, np.float64)
        self.image_size = tuple(image_size)
        self.s = supersample
        self.tex, self.a, self.b = board_texture(self.board, px_per_mm, margin_mm)
        w, h = self.image_size
        # supersampled camera, by the pixel-centre rule u_ss = s (u + 0.5) - 0.5
        Ks = self.K.copy()
        Ks[:2, :2] *= supersample
        Ks[:2, 2] = supersample * (Ks[:2, 2] + 0.5) - 0.5
        self.K_ss = Ks
        ws, hs = w * supersample, h * supersample
        ys, xs = np.mgrid[0:hs, 0:ws].astype(np.float64)
        pix = np.stack([xs.ravel(), ys.ravel()], 1).reshape(-1, 1, 2)
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)
        und = cv2.undistortPointsIter(pix, Ks, self.dist, np.eye(3), Ks, crit).reshape(-1, 2)
        self._und = und.astype(np.float32).reshape(hs, ws, 2)  # undistorted pixel of each output pixel
        # rays of a 640x480 camera with tilts <= 40 deg always meet the board plane in front of the camera

    def render(self, pose: Pose, blur_sigma: float = 0.5, noise_sigma: float = 2.0,
               motion_blur_px: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
        """A uint8 grayscale view of the board at ``pose``."""
        rng = rng or np.random.default_rng(0)
        R = cv2.Rodrigues(np.asarray(pose.rvec, np.float64))[0]
        H = self.K_ss @ np.column_stack([R[:, 0], R[:, 1], np.asarray(pose.tvec, np.float64)])
        to_tex = np.array([[self.a, 0.0, self.b], [0.0, self.a, self.b], [0.0, 0.0, 1.0]]) @ np.linalg.inv(H)
        maps = cv2.perspectiveTransform(self._und, to_tex)  # texture pixel seen by each output pixel
        mapx, mapy = maps[..., 0], maps[..., 1]
        tex = (self.tex.astype(np.float32) * (190.0 / 255.0) + 35.0)  # no clipping at black/white
        img = cv2.remap(tex, mapx, mapy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=80.0)
        w, h = self.image_size
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA)
        if blur_sigma > 0:
            img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
        if motion_blur_px > 0:
            k = int(round(motion_blur_px)) | 1
            kernel = np.zeros((k, k), np.float32)
            kernel[k // 2, :] = 1.0 / k
            img = cv2.filter2D(img, -1, kernel)
        img = img + rng.normal(0.0, noise_sigma, img.shape)
        return np.clip(np.round(img), 0, 255).astype(np.uint8)

    def project(self, pose: Pose) -> np.ndarray:
        """Ground-truth pixel positions of all corners (cv2.projectPoints), (n, 2)."""
        obj = self.board.corner_object_points().astype(np.float64)
        uv, _ = cv2.projectPoints(obj, np.asarray(pose.rvec, np.float64), np.asarray(pose.tvec, np.float64),
                                  self.K, self.dist)
        return uv.reshape(-1, 2)


def write_images(folder: Path, images: list[np.ndarray], ext: str = ".png") -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, img in enumerate(images):
        p = folder / f"view_{i:03d}{ext}"
        cv2.imwrite(str(p), img)
        paths.append(p)
    return paths


def write_video(path: Path, frames: list[np.ndarray], fps: float = 10.0) -> Path:
    """Write grayscale frames to a lossless-ish video (MJPG at top quality in an AVI container)."""
    h, w = frames[0].shape[:2]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h), True)
    if not writer.isOpened():
        raise RuntimeError("OpenCV cannot write MJPG video in this build")
    writer.set(cv2.VIDEOWRITER_PROP_QUALITY, 100)
    for f in frames:
        writer.write(cv2.cvtColor(f, cv2.COLOR_GRAY2BGR))
    writer.release()
    return path


def operator_poses(board: BoardSpec, K: np.ndarray, image_size, n: int, seed: int = 0,
                   distance=(300.0, 430.0), tilt_deg=(20.0, 45.0), min_visible: float = 0.5) -> list[Pose]:
    """Poses as a careful operator records them: the board taken through the image corners, edges and
    centre in turn (targets cycle through 9 places, with jitter), each view clearly tilted (20-45 deg
    about a random axis in the board plane, random roll), close enough to fill a good part of the image;
    partly outside the frame is allowed (at least ``min_visible`` of the corners inside)."""
    rng = np.random.default_rng(seed)
    w, h = image_size
    obj = board.corner_object_points().astype(np.float64)
    centre = np.array([*np.array(board.size_mm) / 2.0, 0.0])
    if board.kind == "checker":
        centre[:2] -= board.square_mm
    places = [(0.2, 0.2), (0.8, 0.8), (0.8, 0.2), (0.2, 0.8), (0.5, 0.5), (0.5, 0.2), (0.2, 0.5), (0.8, 0.5),
              (0.5, 0.8)]
    order = rng.permutation(len(places))
    Kinv = np.linalg.inv(K)
    poses: list[Pose] = []
    tries = 0
    while len(poses) < n:
        tries += 1
        px, py = places[order[len(poses) % len(places)]]
        target = np.array([px * w, py * h]) + rng.normal(0, 0.03, 2) * (w, h)
        z = rng.uniform(*distance)
        pos = z * (Kinv @ np.array([target[0], target[1], 1.0]))
        axis_ang = rng.uniform(0, 2 * np.pi)
        tilt = np.radians(rng.uniform(*tilt_deg))
        axis = np.array([np.cos(axis_ang), np.sin(axis_ang), 0.0])
        roll = np.radians(rng.uniform(-30, 30))
        R = cv2.Rodrigues(axis * tilt)[0] @ cv2.Rodrigues(np.array([0, 0, roll]))[0]
        t = pos - R @ centre
        cam = obj @ R.T + t
        if np.any(cam[:, 2] <= 50):
            continue
        uv = cam[:, :2] / cam[:, 2:] * (K[0, 0], K[1, 1]) + K[:2, 2]
        visible = (uv[:, 0] > 8) & (uv[:, 0] < w - 9) & (uv[:, 1] > 8) & (uv[:, 1] < h - 9)
        if visible.mean() < min_visible and tries < 1000:
            continue
        poses.append(Pose(cv2.Rodrigues(R)[0].ravel(), t))
    return poses


def corner_poses(board: BoardSpec, K: np.ndarray, image_size, n: int, seed: int = 0, dist=None,
                 distance=(330.0, 520.0), tilt_deg=(15.0, 40.0), inset_px=(5.0, 20.0)) -> list[Pose]:
    """Poses as calibration guides ask for them: four of every five views push the whole board into one of the
    image's corners in turn (its outer edge ``inset_px`` inside the corner, through the lens ``dist``), the
    fifth goes to the centre or an edge's middle; tilts 15-40 deg about a random axis in the board plane,
    random roll; at least 85 % of the inner corners inside the image."""
    rng = np.random.default_rng(seed)
    w, h = image_size
    obj = board.corner_object_points().astype(np.float64)
    bw, bh = board.size_mm
    outline = np.array([[0.0, 0.0, 0.0], [bw, 0.0, 0.0], [0.0, bh, 0.0], [bw, bh, 0.0]])
    if board.kind == "checker":
        outline[:, :2] -= board.square_mm
    centre = outline.mean(0)
    dist = np.zeros(5) if dist is None else np.asarray(dist, np.float64)
    corners = [(0, 0), (1, 1), (1, 0), (0, 1)]
    others = [(0.5, 0.5), (0.5, 0.2), (0.2, 0.5), (0.8, 0.5), (0.5, 0.8)]
    order_c, order_o = rng.permutation(4), rng.permutation(len(others))
    Kinv = np.linalg.inv(K)
    poses: list[Pose] = []
    tries = 0
    while len(poses) < n:
        tries += 1
        k = len(poses)
        axis_ang = rng.uniform(0, 2 * np.pi)
        axis = np.array([np.cos(axis_ang), np.sin(axis_ang), 0.0])
        R = cv2.Rodrigues(axis * np.radians(rng.uniform(*tilt_deg)))[0] \
            @ cv2.Rodrigues(np.array([0, 0, np.radians(rng.uniform(-30, 30))]))[0]
        z = rng.uniform(*distance)
        if k % 5 < 4:
            cx, cy = corners[order_c[(k // 5 * 4 + k % 5) % 4]]
            inset = rng.uniform(*inset_px, 2)
            target = np.array([inset[0] if cx == 0 else w - 1 - inset[0], inset[1] if cy == 0 else h - 1 - inset[1]])
            t = z * (Kinv @ np.array([w / 2, h / 2, 1.0])) - R @ centre
            cam = outline @ R.T + t
            uv = cam[:, :2] / cam[:, 2:]
            i = int(np.argmax((1 if cx else -1) * uv[:, 0] + (1 if cy else -1) * uv[:, 1]))
            ray = cv2.undistortPoints(target.reshape(1, 1, 2), K, dist).reshape(2)
            t = t + cam[i, 2] * np.array([ray[0], ray[1], 1.0]) - cam[i]   # that outline corner onto the target
        else:
            px, py = others[order_o[(k // 5) % len(others)]]
            target = np.array([px * w, py * h]) + rng.normal(0, 0.03, 2) * (w, h)
            t = z * (Kinv @ np.array([target[0], target[1], 1.0])) - R @ centre
        if np.any((obj @ R.T + t)[:, 2] <= 50):
            continue
        uv = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, K, dist)[0].reshape(-1, 2)
        visible = (uv[:, 0] > 8) & (uv[:, 0] < w - 9) & (uv[:, 1] > 8) & (uv[:, 1] < h - 9)
        if visible.mean() < 0.85 and tries < 5000:
            continue
        poses.append(Pose(cv2.Rodrigues(R)[0].ravel(), t))
    return poses
