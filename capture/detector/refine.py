"""Refining a landmark embedding on footage of the actor (``capture actor embed A ... --refine TAKE``).

A published embedding (vertex ids, a canonical mesh projected onto the template) puts a detector's
landmark a few millimetres from where that detector actually fires on this actor's face. On a few
well-spread frames of the actor (:func:`select_frames`), the refinement solves jointly for

* each selected frame's fit: head pose (rotation, translation), jaw (rotation, translation) and one
  blend coefficient per expression (the actor's model, :func:`models.fit.pose_face`), and
* each landmark's position on the template surface: an offset in the tangent plane of its start,

minimising the confidence-weighted squared reprojection error (px; landmarks below ``min_confident``
count as unseen, and a landmark unseen in every frame keeps its start: the report lists those seen in
fewer than 2 frames) plus ``reg`` x the squared
distance (mm) of every landmark from its starting position and small priors on the coefficients and
the jaw. The landmarks' anatomy (neutral, skin weight, expression basis) is re-evaluated by the
actor's networks at the moving template points, so the gradient sees the face change under them.
After each round the points are moved onto the surface (closest point, trimesh) and the tangent
planes re-made. First the frames are fitted with the starting embedding alone, which gives the
"before" reprojection error; the "after" error is that of the final embedding with refitted frames.

Optimisation is Levenberg-Marquardt on the residual vector (Jacobians by vectorised autograd), float64
(the networks in float32), on the CPU.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from capture.detector.embedding import LandmarkEmbedding, embedded_points, embedding_from_points
from capture.io.errors import CaptureError


@dataclass
class RefineSettings:
    frames: int = 8                  # well-spread frames used
    rounds: int = 10                 # joint solves, each followed by a projection onto the surface
    iterations: int = 80             # Levenberg-Marquardt iterations per solve (at most)
    reg: float = 0.005               # weight of |c - c_start|^2 (mm^2) per landmark, vs px^2 per observation
    coeff_weight: float = 0.01       # weight of the squared blend coefficients per frame
    jaw_weight: float = 0.1          # weight of the jaw's distance from rest (axis-angle rad, translation cm)
    min_confident: float = 0.5       # landmarks at or above this confidence count in a frame


@dataclass
class RefineResult:
    embedding: LandmarkEmbedding
    frames: list[int]
    before_rms_px: float
    after_rms_px: float
    moved_mm: np.ndarray             # (L,) distance of each landmark from its start
    rounds: list[dict] = field(default_factory=list)
    seen: np.ndarray | None = None   # (L,) in how many of the frames each landmark was confident

    def report(self) -> dict:
        m = self.moved_mm
        return {"frames": self.frames, "reprojection_before_rms_px": self.before_rms_px,
                "reprojection_after_rms_px": self.after_rms_px,
                "moved_mm": {"median": float(np.median(m)), "p95": float(np.percentile(m, 95)),
                             "max": float(m.max())}, "rounds": self.rounds,
                "landmarks_seen_in_fewer_than_2_frames": (
                    [] if self.seen is None else [int(i) for i in np.flatnonzero(self.seen < 2)])}


def select_frames(points: np.ndarray, weights: np.ndarray, found: np.ndarray, n: int,
                  min_fraction: float = 0.5) -> list[int]:
    """``n`` frames whose landmark configurations differ most (farthest-point sampling on the
    shapes with position and scale removed), among face frames with at least ``min_fraction`` of
    the landmarks confident. Sorted by frame."""
    from capture.fit.take import farthest_point_sample

    p = np.asarray(points, np.float64)
    w = np.nan_to_num(np.asarray(weights, np.float64))
    ok = np.asarray(found, bool) & np.isfinite(p).all(axis=(1, 2)) & ((w > 0).mean(axis=1) >= min_fraction)
    cand = np.flatnonzero(ok)
    if len(cand) < 2:
        raise CaptureError(f"only {len(cand)} frames of the take have the face with most landmarks confident; "
                           f"refining needs at least 2 (better 8 or more, with the head turning)")
    q = p[cand] - p[cand].mean(axis=1, keepdims=True)
    q /= np.sqrt((q ** 2).sum(axis=(1, 2), keepdims=True) / q.shape[1])
    pick = farthest_point_sample(q.reshape(len(cand), -1), min(n, len(cand)))
    return sorted(int(cand[i]) for i in pick)


def _tangent_bases(template, face_index: np.ndarray) -> np.ndarray:
    """(L, 3, 2) orthonormal bases of the planes of the landmarks' triangles."""
    nrm = np.asarray(template.face_normals, np.float64)[face_index]
    a = np.where(np.abs(nrm[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    t1 = np.cross(nrm, a)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(nrm, t1)
    return np.stack([t1, t2], axis=2)


class _Problem:
    """Frame parameters (always) and landmark tangent offsets (when joint), solved by Levenberg-Marquardt.

    The energy is the squared norm of the residual vector: the confidence-weighted reprojection errors
    (px, normalised by the total weight, so the data term is the mean squared error), the blend
    coefficients and the jaw's distance from rest (priors), and for joint solves the landmarks'
    distances from their starting points (``reg``).
    """

    def __init__(self, model, obs: np.ndarray, w: np.ndarray, K: np.ndarray, dist: np.ndarray,
                 R0: np.ndarray, t0: np.ndarray, s: RefineSettings):
        dt = torch.float64
        self.model = model
        self.s = s
        self.obs = torch.as_tensor(obs, dtype=dt)
        self.sw = torch.as_tensor(np.sqrt(w / max(w.sum(), 1e-12)), dtype=dt)   # (J, L)
        self.K = torch.tensor(np.array(K, np.float64), dtype=dt)
        d = np.asarray(dist, np.float64).reshape(-1)
        self.dist = torch.as_tensor(d, dtype=dt) if d.size and np.any(d != 0) else None
        self.J = J = obs.shape[0]
        self.E = E = model.config.n_expressions
        self.head_t0 = torch.as_tensor(t0, dtype=dt)
        self.head_R0 = torch.as_tensor(R0, dtype=dt)
        # rotations are updates R0 exp([w]x) (axis-angle, well conditioned at any step size)
        self.frame = torch.zeros(J * (3 + 3 + 3 + 3 + E), dtype=dt)
        self.base_c = None

    def linearise(self, c: torch.Tensor) -> None:
        """Evaluate the networks at ``c (L, 3)`` and their derivative there (3 forward-mode passes): the
        anatomy at nearby points is then ``A(c) + G (c' - c)`` without running the networks again."""
        m = self.model
        n3, E = 3, self.E

        x = c.detach().float()
        tri = None if m.chart is None else m.chart.locate(x.numpy())[0]   # numpy: outside the jvp

        def f(x):
            a = m(x, chart_triangles=tri)
            return torch.cat([a.neutral, a.skin_weight[:, None], a.expressions.reshape(x.shape[0], E * 3)], dim=1)

        cols = []
        with torch.no_grad():
            for k in range(3):
                t = torch.zeros_like(x)
                t[:, k] = 1.0
                val, d = torch.func.jvp(f, (x,), (t,))
                cols.append(d.double())
        self.base_c = c.detach().double()
        self.base_val = val.double()                      # (L, D)
        self.base_grad = torch.stack(cols, dim=2)         # (L, D, 3)
        self.n_neutral = n3

    def anatomy(self, c: torch.Tensor):
        from models.fit import ActorAtPoints

        v = self.base_val + torch.einsum("ldk,lk->ld", self.base_grad, c - self.base_c)
        m = self.model
        return ActorAtPoints(points=c, neutral=v[:, :3], skin_weight=v[:, 3],
                             expressions=v[:, 4:].reshape(-1, self.E, 3), jaw_pivot=m.jaw_pivot.double(),
                             center=m.center.double(), scale=float(m.config.scale))

    def _unpack(self, th: torch.Tensor):
        J, E = self.J, self.E
        sizes = [J * 3, J * 3, J * 3, J * 3, J * E]
        parts = torch.split(th[:sum(sizes)], sizes)
        return (parts[0].reshape(J, 3), parts[1].reshape(J, 3), parts[2].reshape(J, 3), parts[3].reshape(J, 3),
                parts[4].reshape(J, 1, E))

    def residuals(self, th: torch.Tensor, c: torch.Tensor, c0: torch.Tensor | None = None) -> torch.Tensor:
        """The residual vector for frame parameters ``th`` and template points ``c (L, 3)`` mm."""
        from calib.projection import project_points
        from models.fit import pose_face
        from models.fit_lm import so3_exp

        head_w, dt_cm, jaw_w, jaw_cm, coeff = self._unpack(th)
        actor = self.anatomy(c)
        x = pose_face(actor, self.head_R0 @ so3_exp(head_w), self.head_t0 + 10.0 * dt_cm, so3_exp(jaw_w),
                      10.0 * jaw_cm, coeff)
        uv = project_points(x, self.K, self.dist)
        parts = [((uv - self.obs) * self.sw[..., None]).reshape(-1),
                 np.sqrt(self.s.coeff_weight / self.J) * coeff.reshape(-1),
                 np.sqrt(self.s.jaw_weight / self.J) * jaw_w.reshape(-1),
                 np.sqrt(self.s.jaw_weight / self.J) * jaw_cm.reshape(-1)]
        if c0 is not None:
            parts.append(np.sqrt(self.s.reg / c.shape[0]) * (c - c0).reshape(-1))
        return torch.cat(parts)

    def data_rms_px(self, c: torch.Tensor) -> float:
        self.linearise(c)
        with torch.no_grad():
            r = self.residuals(self.frame, c)[:self.obs.numel()]
        return float(torch.sqrt((r ** 2).sum()))


def _levenberg_marquardt(fn, x0: torch.Tensor, iterations: int, tol: float = 1e-12) -> torch.Tensor:
    """Minimise |fn(x)|^2 from ``x0``: Jacobians by vectorised forward-mode autograd (fewer parameters than
    residuals), damped normal equations."""
    from torch.autograd.functional import jacobian

    x = x0.detach().clone()
    with torch.no_grad():
        r = fn(x)
    e = float((r ** 2).sum())
    lam = 1e-3
    for _ in range(iterations):
        Jm = jacobian(fn, x, vectorize=True, strategy="forward-mode")
        H = Jm.T @ Jm
        g = Jm.T @ r
        diag = torch.diagonal(H).clamp_min(1e-12)
        improved = False
        for _ in range(10):
            A = H + lam * torch.diag(diag)
            try:
                step = -torch.linalg.solve(A, g)
            except RuntimeError:
                lam *= 10
                continue
            with torch.no_grad():
                r_new = fn(x + step)
            e_new = float((r_new ** 2).sum())
            if np.isfinite(e_new) and e_new < e:
                x, r, lam = x + step, r_new, max(lam / 3, 1e-9)
                improved = e - e_new > tol * max(e, 1e-30)
                e = e_new
                break
            lam *= 4
        if not improved:
            break
    return x


def refine_embedding(model, template, emb: LandmarkEmbedding, points2d: np.ndarray, weights: np.ndarray, K: np.ndarray,
                     dist: np.ndarray, settings: RefineSettings = RefineSettings(), frames: list[int] | None = None,
                     say=None) -> RefineResult:
    """Refine ``emb`` on observed landmarks ``points2d (J, L, 2)`` px (NaN: missing) with confidences
    ``weights (J, L)`` of J frames (already selected), camera ``K (3, 3)``, ``dist`` (OpenCV).

    ``model``: the actor's :class:`~models.aim.AnatomicalFaceModel` (frozen). Returns the refined
    embedding (on the template surface) and the reprojection RMS before and after.
    """
    from capture.fit.init import PnPSettings, pnp_frame

    s = settings
    obs = np.asarray(points2d, np.float64)
    J, L = obs.shape[:2]
    w = np.where(np.isfinite(obs).all(axis=2), np.nan_to_num(np.asarray(weights, np.float64)), 0.0)
    w = np.where(w >= s.min_confident, w, 0.0)
    obs = np.nan_to_num(obs)
    c_start = embedded_points(emb, template)
    with torch.no_grad():
        neutral = model(torch.as_tensor(c_start, dtype=torch.float32)).neutral.double().numpy()
    R0, t0, keep = [], [], []
    for j in range(J):
        res = pnp_frame(neutral, np.where(w[j][:, None] > 0, obs[j], np.nan), w[j], np.asarray(K, np.float64),
                        np.asarray(dist, np.float64), PnPSettings(), None)
        if res is not None:
            R0.append(res[0])
            t0.append(np.asarray(res[1]).reshape(3))
            keep.append(j)
    if len(keep) < 2:
        raise CaptureError(f"the head pose was found in {len(keep)} of {J} selected frames; refining needs at "
                           f"least 2: check the camera (--camera) and that the embedding roughly fits")
    obs, w = obs[keep], w[keep]
    prob = _Problem(model, obs, w, K, dist, np.stack(R0), np.stack(t0), s)
    c0 = torch.as_tensor(c_start, dtype=torch.float64)
    nf = prob.frame.numel()

    def frames_only(c):
        prob.linearise(c)
        prob.frame = _levenberg_marquardt(lambda th: prob.residuals(th, c), prob.frame, s.iterations)

    frames_only(c0)
    before = prob.data_rms_px(c0)
    rounds = []
    cur = emb
    c_base = c0
    for r in range(s.rounds):
        basis = torch.as_tensor(_tangent_bases(template, cur.face_index), dtype=torch.float64)

        def points(u):
            return c_base + torch.einsum("lij,lj->li", basis, u.reshape(L, 2))

        prob.linearise(c_base)

        x = _levenberg_marquardt(lambda v: prob.residuals(v[:nf], points(v[nf:]), c0),
                                 torch.cat([prob.frame, torch.zeros(2 * L, dtype=torch.float64)]), s.iterations)
        prob.frame = x[:nf]
        u = x[nf:]
        moved_pts = points(u).detach().numpy()
        cur = embedding_from_points(template, moved_pts, emb.detector, emb.source, max_distance_mm=None)
        c_base = torch.as_tensor(embedded_points(cur, template), dtype=torch.float64)
        rms = prob.data_rms_px(c_base)
        step = float(np.linalg.norm(u.reshape(L, 2).numpy(), axis=1).max())
        rounds.append({"round": r + 1, "rms_px": rms, "largest_step_mm": step})
        if say:
            say(f"refine round {r + 1}: reprojection RMS {rms:.3f} px, largest landmark step {step:.3f} mm")
        if step < 0.05:
            break
    frames_only(c_base)
    after = prob.data_rms_px(c_base)
    moved = np.linalg.norm(c_base.numpy() - c_start, axis=1)
    src = (emb.source + "; " if emb.source else "") + f"refined on {len(keep)} frames"
    out = LandmarkEmbedding(emb.detector, cur.face_index, cur.barycentric, src)
    used = [int(frames[k]) if frames is not None else int(k) for k in keep]
    return RefineResult(out, used, before, after, moved, rounds, (w > 0).sum(axis=0))
