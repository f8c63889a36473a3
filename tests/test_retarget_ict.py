"""``capture retarget`` between two ICT FaceKit identities (issue 7).

A is the bundled demo actor (the ICT sample identity, 9,409 vertices, 19 expressions + 5 mirrored, default preset);
B is a second ICT identity with the same expressions (the sample's identity coefficients negated on
the 100 ICT identity modes), learnt once by scripts/make_ict_b_actor.py (width 64, 600 iterations,
estimated bones) and committed as tests/data/ict_b_actor (no ICT source data or training needed here).
A 6-frame take of A posed with known parameters (head transform, jaw opening, expression coefficients at
partial weights) is fitted by ``capture fit3d`` and played on B by ``capture retarget``; B's meshes must
equal B posed with the same parameters, within A's own fit error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import trimesh
from scipy.spatial.transform import Rotation

from capture.cli import main

A_DIR = Path(__file__).resolve().parents[1] / "capture" / "data" / "demo_actor"
B_DIR = Path(__file__).resolve().parent / "data" / "ict_b_actor"
T = 6
FIT = ["--iterations", "150", "--window", "8", "--threads", "1", "--no-progress"]
CURVES = {  # expression: weights over the take (partial, overlapping)
    "jawOpen": np.linspace(0.0, 0.6, T),
    "mouthSmile_L": 0.7 * np.sin(np.linspace(0.0, 3.0, T)),
    "browInnerUp_R": np.linspace(0.8, 0.1, T),
    "eyeBlink_L": np.linspace(0.0, 0.5, T),
}


def _known_params(names: list[str]):
    """Head (R (T,3,3), t (T,3) mm), jaw rot6d (T,6) 0..12 deg about x, jaw t (T,3), coefficients (T, E)."""
    head_R = Rotation.from_euler("yx", np.stack([np.linspace(-8, 8, T), np.linspace(3, -3, T)], 1),
                                 degrees=True).as_matrix()
    head_t = np.stack([np.linspace(-5, 5, T), np.linspace(2, -2, T), np.full(T, 600.0)], 1)
    J = Rotation.from_euler("x", np.linspace(0.0, 12.0, T)[:, None], degrees=True).as_matrix()
    r6 = torch.tensor(np.concatenate([J[:, :, 0], J[:, :, 1]], 1), dtype=torch.float32)
    co = np.zeros((T, len(names)))
    for name, w in CURVES.items():
        co[:, names.index(name)] = w
    return (head_R, head_t), (r6, torch.zeros(T, 3), torch.tensor(co, dtype=torch.float32))


def _posed(actor_dir: Path, head, local) -> tuple[np.ndarray, np.ndarray]:
    """The actor posed with the known parameters, camera frame (T, V, 3) mm; and its faces."""
    from capture.actor.package import load_actor

    act = load_actor(str(actor_dir))
    v = torch.tensor(np.asarray(act.template.vertices), dtype=torch.float32)
    with torch.no_grad():
        x = act.model.shape(act.model(v), *local).numpy().astype(np.float64)
    return np.einsum("tij,tvj->tvi", head[0], x) + head[1][:, None], np.asarray(act.template.faces)


def _meshes(folder: Path) -> np.ndarray:
    return np.stack([trimesh.load(p, process=False, maintain_order=True).vertices
                     for p in sorted(folder.glob("frame_*.obj"))])


def test_ict_retarget_plays_known_parameters_on_b(tmp_path):
    from capture.actor.package import read_metadata

    names = read_metadata(str(A_DIR))["shape_names"][1:]
    assert read_metadata(str(B_DIR))["shape_names"][1:] == names
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # shared cores
    try:
        head, local = _known_params(names)
        truth_a, faces = _posed(A_DIR, head, local)
        truth_b, _ = _posed(B_DIR, head, local)
        scans = tmp_path / "scans"
        scans.mkdir()
        for i in range(T):
            trimesh.Trimesh(truth_a[i], faces, process=False).export(scans / f"scan_{i:03d}.ply")
        run, out = tmp_path / "run_a", tmp_path / "on_b"
        assert main(["fit3d", str(scans), "--actor", str(A_DIR), "--out", str(run), "--formats", "obj,npz",
                     *FIT]) == 0
        assert main(["retarget", str(run), "--to", str(B_DIR), "--out", str(out), "--formats", "obj",
                     "--no-progress"]) == 0
    finally:
        torch.set_num_threads(threads)
    fit_a, got_b = _meshes(run / "meshes"), _meshes(out / "meshes")
    still_b, _ = _posed(B_DIR, head, (_identity6().expand(T, -1), local[1], 0 * local[2]))
    err_a = np.linalg.norm(fit_a - truth_a, axis=-1).mean(1)
    err_b = np.linalg.norm(got_b - truth_b, axis=-1).mean(1)
    copy_a = np.linalg.norm(fit_a - truth_b, axis=-1).mean(1)        # A's meshes taken as B's
    still = np.linalg.norm(still_b - truth_b, axis=-1).mean(1)      # B's head motion only, no jaw/expressions
    print(f"A fit {err_a.round(3)}, B retargeted {err_b.round(3)}, copy of A {copy_a.round(2)}, "
          f"B still {still.round(2)} (mean vertex error per frame, mm)")
    # Measured (2 shared CPU cores, fixture as committed, 150 fit3d iterations), mean vertex error per frame:
    # A's fit 0.029-0.034 mm; B retargeted 0.048-0.057 mm; a copy of A's meshes 7.2-7.9 mm from B's truth;
    # B with the head motion but no jaw or expressions 0.37-3.4 mm. Test ~8-13 s.
    # Tolerance: retargeting adds no error of its own, so B's error is A's fit error carried over through
    # the same parameters onto a different face (B's fields respond to a parameter error a little more
    # than A's, hence 1.5x) plus 0.1 mm for OBJ rounding and float32 sums: per frame 1.5x A's + 0.1 mm.
    assert np.all(err_b <= 1.5 * err_a + 0.1), (err_a, err_b)
    # ... far below the identity difference (a copy of A's meshes) and the face's own motion.
    assert copy_a.mean() > 10 * err_b.mean(), (copy_a, err_b)
    assert still.max() > 10 * err_b.max(), (still, err_b)


def _identity6() -> torch.Tensor:
    """rot6d of the identity rotation (1, 6)."""
    return torch.tensor([[1.0, 0.0, 0.0, 0.0, 1.0, 0.0]])
