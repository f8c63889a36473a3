"""Held-out 3D performances of the bundled ICT sample actor (pure data generation, no fitting).

The sample actor (``capture/data/sample_actor``) is one ICT FaceKit identity with a neutral and 19
training expressions. A held-out performance animates the SAME identity (``sample_identity_coeffs``
on the 100 identity modes of the Light model; face region, vertices 0..9408) with

* expressions the actor never saw (``held_out_expressions`` of ``sample.json``, ``mouthClose``
  excluded: it is a corrective shape that only makes sense on top of ``jawOpen``), several per
  sequence, each on a smooth random weight curve at PARTIAL weights (peaks 0.3 .. 0.8 by default),
* jaw motion from the ICT jaw shapes (``jawOpen`` talking curve 0 .. 0.45, ``jawLeft`` /
  ``jawRight`` 0 .. 0.3): these four are TRAINING shapes, used here only at partial weights and mixed
  with the held-out shapes,
* a smooth rigid head motion (yaw +-20 deg, pitch +-10, roll +-6, translation +-15 mm about the
  face's bounding-box centre).

The ICT model is linear: ``X = R (N + sum_k w_k D_k - c) + c + t`` with ``N`` the identity's
neutral and ``D_k`` the expression deltas (all in mm, ICT frame: x = actor's left, y up, z towards the
face front).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.interpolate import PchipInterpolator
from scipy.spatial.transform import Rotation

from benchmarks.assets import ICT_LIGHT_NPZ

FACE_NV = 9409                 # ICT face region: vertices 0..9408
NARROW_FACE_NV = 6706          # ICT narrow face (no scalp, ears, neck): vertices 0..6705
N_IDENTITY = 100               # the Light model's identity modes
CM_TO_MM = 10.0
DEFAULT_ICT = ICT_LIGHT_NPZ    # benchmarks.assets: $CAPTURE_SHARED_ASSETS or ../shared/assets
JAW_RANGES = {"jawOpen": 0.45, "jawLeft": 0.3, "jawRight": 0.3}
LOWER_TEETH = slice(19247, 21451)   # ICT's lower teeth (derived/jaw_rigid_from_lower_teeth.json): rigid in every shape
EXCLUDED = ("mouthClose",)
IDENTITIES = ("sample", "b", "c")


@dataclass
class ICTIdentity:
    """The sample identity's face region and expression deltas (mm)."""

    neutral: np.ndarray                 # (V, 3) mm
    deltas: dict[str, np.ndarray]       # name -> (V, 3) mm, all 53 ICT expressions
    jaws: dict[str, "RigidJaw"] = field(default_factory=dict)   # the jaw shapes as turns of the lower teeth


@dataclass
class RigidJaw:
    """A jaw shape as a real jaw makes it: a rigid motion of the lower teeth, which the skin follows in part.

    ``log (4, 4)`` is the matrix logarithm of the teeth's rigid motion at full weight; at weight ``w`` they move by
    ``expm(w log)``, the screw motion that turns and slides them by ``w`` times as much (pure rotation about a
    fixed axis for a pure turn, a straight slide for a pure shift). ``follow (V,)`` in [0, 1] is the share of each
    face vertex's full-weight motion along that rigid motion and ``rest (V, 3)`` the motion beyond it (mm), so
    that at weight 1 the shape is ICT's own delta exactly."""

    log: np.ndarray
    follow: np.ndarray
    rest: np.ndarray

    def displacement(self, neutral: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``(T, V, 3)`` mm at weights ``w (T,)``: the skin's share of the teeth's rigid motion by ``w``, plus ``w``
        times the rest. ICT's linear blend instead moves every vertex on a straight line, which bends the teeth
        at partial weights."""
        from scipy.linalg import expm

        M = np.stack([expm(x * self.log) for x in np.asarray(w, np.float64)])              # (T, 4, 4)
        moved = np.einsum("tij,vj->tvi", M[:, :3, :3], neutral) + M[:, None, :3, 3]
        return self.follow[None, :, None] * (moved - neutral) + np.asarray(w)[:, None, None] * self.rest


def make_rigid_jaw(neutral: np.ndarray, delta: np.ndarray, teeth: np.ndarray, teeth_delta: np.ndarray) -> RigidJaw:
    """:class:`RigidJaw` of a jaw shape from the lower teeth's positions ``teeth (M, 3)`` and motion ``(M, 3)``
    (Kabsch), for the face ``neutral (V, 3)`` and its delta ``(V, 3)``, mm."""
    from scipy.linalg import logm

    a, b = teeth, teeth + teeth_delta
    ca, cb = a.mean(0), b.mean(0)
    U, _, Vt = np.linalg.svd((a - ca).T @ (b - cb))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, cb - R @ ca
    r = neutral @ R.T + T[:3, 3] - neutral                            # each vertex's motion if it were bone
    follow = np.clip((delta * r).sum(1) / np.maximum((r * r).sum(1), 1e-12), 0.0, 1.0)
    return RigidJaw(np.real(logm(T)), follow, delta - follow[:, None] * r)


def identity_coeffs(name: str, npz: Path = DEFAULT_ICT) -> np.ndarray:
    """The ICT identity coefficients of a named identity: ``sample`` (the bundled sample actor's,
    ``sample_identity_coeffs``), ``b`` (their negation: the second identity of the retargeting test,
    ``benchmarks/bench_retarget.py`` and ``tests/data/ict_b_actor``) or ``c`` (the sample's coefficients with
    random signs, seed 2026: each mode as far from the mean face as the sample's, in a direction drawn once; a
    third identity, held out from every setting chosen on the other two)."""
    if name not in IDENTITIES:
        raise ValueError(f"unknown identity {name!r}; expected one of {', '.join(IDENTITIES)}")
    with np.load(Path(npz), allow_pickle=False) as d:
        c = np.asarray(d["sample_identity_coeffs"], np.float64)[:N_IDENTITY]
    if name == "c":
        return c * np.random.default_rng(2026).choice([-1.0, 1.0], size=c.shape)
    return c if name == "sample" else -c


def write_identity_shapes(name: str, shapes: Path, out: Path, npz: Path = DEFAULT_ICT) -> Path:
    """The sample actor's training shapes (``shapes``: a folder of PLY in ICT's topology, mm) moved to identity
    ``name`` (ICT is linear, so each shape moves by the difference of the identities), written to ``out``."""
    import trimesh

    with np.load(Path(npz), allow_pickle=False) as d:
        deltas = d["identity_deltas"][:N_IDENTITY].astype(np.float64)
    offset = CM_TO_MM * np.tensordot(identity_coeffs(name, npz) - identity_coeffs("sample", npz), deltas, axes=1)
    out.mkdir(parents=True, exist_ok=True)
    for p in sorted(Path(shapes).glob("*.ply")):
        m = trimesh.load(p, process=False, maintain_order=True)
        v = np.asarray(m.vertices)
        trimesh.Trimesh(v + offset[:len(v)], m.faces, process=False).export(out / p.name)
    return out


def load_ict_identity(npz: Path = DEFAULT_ICT, identity_coeffs: np.ndarray | None = None) -> ICTIdentity:
    """The ICT Light model at ``identity_coeffs`` (default: the npz's ``sample_identity_coeffs``), face region, mm."""
    npz = Path(npz)
    if not npz.is_file():
        raise FileNotFoundError(f"ICT FaceKit arrays not found at {npz}; pass --ict")
    with np.load(npz, allow_pickle=False) as d:
        c = d["sample_identity_coeffs"] if identity_coeffs is None else identity_coeffs
        c = np.asarray(c, np.float64)[:N_IDENTITY]
        ident = np.tensordot(c, d["identity_deltas"][:N_IDENTITY, :FACE_NV].astype(np.float64), axes=1)
        neutral = (d["neutral"][:FACE_NV] + ident) * CM_TO_MM
        names = [str(n) for n in d["expression_names"]]
        deltas = {n: d["expression_deltas"][i, :FACE_NV].astype(np.float64) * CM_TO_MM for i, n in enumerate(names)}
        teeth = (d["neutral"][LOWER_TEETH] + np.tensordot(c, d["identity_deltas"][:N_IDENTITY, LOWER_TEETH].astype(
            np.float64), axes=1)) * CM_TO_MM
        jaws = {n: make_rigid_jaw(neutral, deltas[n], teeth,
                                  d["expression_deltas"][names.index(n), LOWER_TEETH].astype(np.float64) * CM_TO_MM)
                for n in JAW_RANGES if n in names}
    return ICTIdentity(neutral, deltas, jaws)


@dataclass
class Performance:
    """A held-out performance: ``vertices[j] = R_j (neutral + weights[j] @ deltas - centre) + centre + t_j``."""

    vertices: np.ndarray        # (T, V, 3) mm
    names: list[str]            # expression names of the weight columns
    weights: np.ndarray         # (T, K) in [0, 1]
    head_R: np.ndarray          # (T, 3, 3)
    head_t: np.ndarray          # (T, 3) mm
    sequence: np.ndarray        # (T,) sequence index of each frame
    fps: float

    def describe(self) -> dict:
        active = {n: float(self.weights[:, k].max()) for k, n in enumerate(self.names) if self.weights[:, k].max() > 0}
        rot = Rotation.from_matrix(self.head_R).as_euler("yxz", degrees=True)
        return {"frames": int(len(self.vertices)), "sequences": int(self.sequence.max() + 1), "fps": self.fps,
                "max_weight": active, "head_rotation_deg_absmax_yaw_pitch_roll": np.abs(rot).max(0).round(1).tolist(),
                "head_translation_mm_absmax": np.abs(self.head_t).max(0).round(1).tolist()}


def _curve(rng: np.random.Generator, T: int, fps: float, keys_per_s: float, lo: float, hi: float) -> np.ndarray:
    """A smooth random curve in [lo, hi]: random keys every 1/keys_per_s s, monotone cubic between them."""
    n = max(2, int(np.ceil(T / fps * keys_per_s)) + 1)
    kt = np.linspace(0, T - 1, n)
    kv = rng.uniform(lo, hi, n)
    return PchipInterpolator(kt, kv)(np.arange(T))


def _bumps(rng: np.random.Generator, T: int, fps: float, peak: float) -> np.ndarray:
    """An expression curve: 0 at rest with 1-3 smooth activations (attack/release ~0.3 s) up to ``peak``."""
    out = np.zeros(T)
    t = np.arange(T) / fps
    for _ in range(rng.integers(1, 4)):
        c, width, amp = rng.uniform(0, T / fps), rng.uniform(0.4, 1.5), rng.uniform(0.5, 1.0) * peak
        out = np.maximum(out, amp * np.exp(-0.5 * ((t - c) / (width / 2)) ** 2))
    return out


def make_performance(ident: ICTIdentity, held_out: list[str], sequences: int = 4, frames: int = 90,
                     fps: float = 30.0, per_sequence: int = 5, seed: int = 0,
                     peak: tuple[float, float] = (0.3, 0.8), jaw: bool = True, rigid_jaw: bool = False
                     ) -> Performance:
    """``sequences`` x ``frames`` frames of held-out expressions + partial jaw shapes + rigid head motion.

    Each sequence animates ``per_sequence`` expressions drawn from ``held_out``, each with 1-3 smooth
    activations whose peak weight is drawn uniformly from ``peak`` (times 0.5 .. 1 per activation).
    ``jaw`` False: the jaw shapes stay at 0 (the same draws otherwise, so the same expressions and head motion).
    ICT blends a jaw shape linearly: at partial weights its lower teeth, which are rigid, are bent by 0.24 -
    0.39 mm on average (jawOpen at 0.2 - 0.5), where a real jaw turns them rigidly. ``rigid_jaw``: the jaw shapes
    turn as a jaw does instead (:class:`RigidJaw`; the same shapes at weight 0 and 1, the same draws).
    """
    pool = [n for n in held_out if n not in EXCLUDED and n in ident.deltas]
    if not pool:
        raise ValueError("no held-out expression available in the ICT model")
    names = pool + list(JAW_RANGES)
    D = np.stack([ident.deltas[n] for n in names])                      # (K, V, 3)
    centre = (ident.neutral.min(0) + ident.neutral.max(0)) / 2
    W, R, tr, seq = [], [], [], []
    for s in range(sequences):
        rng = np.random.default_rng([seed, s])
        w = np.zeros((frames, len(names)))
        for k in rng.choice(len(pool), size=min(per_sequence, len(pool)), replace=False):
            w[:, k] = _bumps(rng, frames, fps, rng.uniform(*peak))
        jo = names.index("jawOpen")
        w[:, jo] = np.clip(_curve(rng, frames, fps, 4.0, -0.1, JAW_RANGES["jawOpen"]), 0, None)
        side = names.index("jawLeft" if s % 2 == 0 else "jawRight")
        w[:, side] = np.clip(_curve(rng, frames, fps, 1.0, -0.15, JAW_RANGES["jawLeft"]), 0, None)
        eul = np.stack([_curve(rng, frames, fps, 1.0, -a, a) for a in (20.0, 10.0, 6.0)], 1)
        if not jaw:
            w[:, [jo, side]] = 0.0
        W.append(np.clip(w, 0, 1))
        R.append(Rotation.from_euler("yxz", eul, degrees=True).as_matrix())
        tr.append(np.stack([_curve(rng, frames, fps, 1.0, -15.0, 15.0) for _ in range(3)], 1))
        seq.append(np.full(frames, s))
    W, R, tr = np.concatenate(W), np.concatenate(R), np.concatenate(tr)
    jaw_cols = [k for k, n in enumerate(names) if n in JAW_RANGES]
    linear = W.copy()
    if rigid_jaw:
        linear[:, jaw_cols] = 0.0
    local = ident.neutral + np.einsum("tk,kvc->tvc", linear, D) - centre
    if rigid_jaw:
        for k in jaw_cols:
            local += ident.jaws[names[k]].displacement(ident.neutral, W[:, k])
    verts = np.einsum("tij,tvj->tvi", R, local) + centre + tr[:, None]
    return Performance(verts, names, W, R, tr, np.concatenate(seq), fps)


def sample_actor_split(sample_json: Path) -> tuple[list[str], list[str]]:
    """(training shapes, held-out expressions) of the bundled sample actor's ``sample.json``."""
    info = json.loads(Path(sample_json).read_text(encoding="utf-8"))
    return list(info["training_shapes"]), list(info["held_out_expressions"])
