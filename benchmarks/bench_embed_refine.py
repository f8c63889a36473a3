"""Landmark-embedding refinement: how close to the truth a start perturbed by 3 mm comes back, and how long it takes.

The take is made by the actor's own model (known embedding, random head poses within +-yaw / +-yaw/2.3
pitch, random expressions and jaw, 1000 px focal length at 550 mm, Gaussian detector noise), so it is
inside the model's span: it measures the refinement's conditioning and optimiser, not the model's
fidelity. The plain baseline in the same run is the unrefined start. End-to-end on a rendered take
with the synthetic detector, see BENCHMARKS.md.

    python benchmarks/bench_embed_refine.py [--landmarks 60] [--frames 8] [--noise 0.1] [--quick]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch
from scipy.spatial.transform import Rotation


def make_case(actor, landmarks: int, frames: int, noise_px: float, yaw_deg: float, perturb_mm: float, seed: int):
    from calib.projection import project_points
    from capture.detector.embedding import LandmarkEmbedding, embedded_points, embedding_from_points
    from models.fit import ActorAtPoints, pose_face

    tm = actor.template
    rng = np.random.default_rng(seed)
    front = np.flatnonzero(tm.triangles_center[:, 2] > 60)
    true = LandmarkEmbedding("t", rng.choice(front, landmarks, replace=False), rng.dirichlet([3, 3, 3], landmarks))
    c_true = embedded_points(true, tm)
    flip = np.diag([1.0, -1, -1])
    R = np.stack([Rotation.from_euler("yxz", [rng.uniform(-yaw_deg, yaw_deg), rng.uniform(-yaw_deg / 2.3, yaw_deg / 2.3),
                                              rng.uniform(-5, 5)], degrees=True).as_matrix() @ flip for _ in range(frames)])
    t = np.stack([[rng.uniform(-20, 20), rng.uniform(-20, 20), 550.0] for _ in range(frames)])
    E = actor.model.config.n_expressions
    coeff = rng.uniform(0, 0.3, (frames, 1, E))
    jaw = np.stack([Rotation.from_euler("x", rng.uniform(0, 8), degrees=True).as_matrix() for _ in range(frames)])
    K = np.array([[1000.0, 0, 320], [0, 1000, 240], [0, 0, 1]])
    with torch.no_grad():
        a = actor.model(torch.as_tensor(c_true, dtype=torch.float32))
        at = ActorAtPoints(points=None, neutral=a.neutral.double(), skin_weight=a.skin_weight.double(),
                           expressions=a.expressions.double(), jaw_pivot=actor.model.jaw_pivot.double(),
                           center=None, scale=1.0)
        x = pose_face(at, torch.as_tensor(R), torch.as_tensor(t), torch.as_tensor(jaw),
                      torch.zeros(frames, 3, dtype=torch.float64), torch.as_tensor(coeff))
        obs = project_points(x, torch.as_tensor(K)).numpy()
    obs = obs + rng.normal(0, noise_px, obs.shape)
    nrm = tm.face_normals[true.face_index]
    d = rng.standard_normal((landmarks, 3))
    d -= (d * nrm).sum(1, keepdims=True) * nrm
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    start = embedding_from_points(tm, c_true + perturb_mm * d, "t", "start", max_distance_mm=None)
    return c_true, start, obs, K


def main(argv=None) -> dict:
    from capture.actor.package import load_actor
    from capture.detector.embedding import embedded_points
    from capture.detector.refine import RefineSettings, refine_embedding

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--actor", default="demo")
    ap.add_argument("--landmarks", type=int, default=60)
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--noise", type=float, default=0.1, help="detector noise, px (1 sigma per axis)")
    ap.add_argument("--yaw", type=float, default=35.0, help="head yaw range +-deg")
    ap.add_argument("--perturb", type=float, default=3.0, help="start offset along the surface, mm")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rounds", type=int, default=RefineSettings.rounds)
    ap.add_argument("--iterations", type=int, default=RefineSettings.iterations)
    ap.add_argument("--reg", type=float, default=RefineSettings.reg)
    ap.add_argument("--quick", action="store_true", help="a small case (CI)")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    settings = RefineSettings(rounds=a.rounds, iterations=a.iterations, reg=a.reg)
    if a.quick:
        # 12 landmarks over 4 frames underdetermine the embeddings (fitted to 0.04 px, 3.5 mm off on one actor,
        # 2.5 on another); 24 over 6 reduce the error on both, on every seed tried (0-2)
        a.landmarks, a.frames = 24, 6
        settings = RefineSettings(rounds=2, iterations=10)
    actor = load_actor(a.actor)
    c_true, start, obs, K = make_case(actor, a.landmarks, a.frames, a.noise, a.yaw, a.perturb, a.seed)
    t0 = time.perf_counter()
    res = refine_embedding(actor.model, actor.template, start, obs, np.ones(obs.shape[:2]), K, np.zeros(0), settings)
    secs = time.perf_counter() - t0
    e0 = np.linalg.norm(embedded_points(start, actor.template) - c_true, axis=1)
    e1 = np.linalg.norm(embedded_points(res.embedding, actor.template) - c_true, axis=1)
    out = {"settings": {"rounds": settings.rounds, "iterations": settings.iterations, "reg": settings.reg},
           "landmarks": a.landmarks, "frames": a.frames, "noise_px": a.noise, "yaw_deg": a.yaw,
           "start_error_mm": {"mean": float(e0.mean()), "max": float(e0.max())},
           "refined_error_mm": {"mean": float(e1.mean()), "median": float(np.median(e1)),
                                "p90": float(np.percentile(e1, 90)), "max": float(e1.max()),
                                "within_0.5mm": float(np.mean(e1 <= 0.5))},
           "reprojection_rms_px": {"before": res.before_rms_px, "after": res.after_rms_px},
           "rounds": len(res.rounds), "seconds": secs}
    print(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
