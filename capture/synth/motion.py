"""Performance-like motion: per-frame head angles and offset, jaw opening and expression weights.

Pure functions of (preset, frame count, frame rate, the actor's shape names, seed). The head pose is
returned as angles in the *template* frame (yaw about the template's up axis y, positive turns the
face toward the actor's left; pitch about x, positive tilts the face up; roll about the forward
axis z) and an offset in mm in camera coordinates; :mod:`capture.synth.scene` turns them into the
head transform. The jaw opening is a fraction 0..1 of the actor's learned jawOpen-like transform.

Signals are smooth: keyframes at random times interpolated with monotone cubic (PCHIP) curves,
raised-cosine envelopes for expressions that come and go, short blinks.

Example:
    >>> m = generate_motion(PRESETS["talk"], 50, 25.0, ["jawOpen", "smile"], seed=0)
    >>> m.coefficients.shape, float(m.jaw_open.max()) <= 1.0
    ((50, 2), True)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
from scipy.interpolate import PchipInterpolator


@dataclass(frozen=True)
class MotionPreset:
    """How a take moves. Angles in degrees, lengths in mm, rates per second."""

    name: str
    yaw_deg: float = 15.0           # amplitude of the yaw wander
    pitch_deg: float = 8.0
    roll_deg: float = 3.0
    hold_yaw_deg: float = 0.0       # constant yaw added to the wander
    turn_alternate: bool = False    # yaw keyframes alternate sides (deliberate head turns)
    head_keys_per_s: float = 0.7    # keyframes per second of the head wander
    translate_mm: tuple[float, float, float] = (15.0, 10.0, 30.0)
    talk: float = 0.7               # fraction of the time spent talking
    jaw_max: float = 0.6            # largest jaw opening (fraction of the learned jawOpen)
    expressions_per_s: float = 0.35
    expression_max: float = 0.7
    blinks: bool = True


PRESETS: dict[str, MotionPreset] = {
    "talk": MotionPreset("talk"),
    "turns": MotionPreset("turns", yaw_deg=30.0, pitch_deg=20.0, roll_deg=5.0, turn_alternate=True,
                          head_keys_per_s=0.6, translate_mm=(25.0, 15.0, 40.0), talk=0.4),
    "calm": MotionPreset("calm", yaw_deg=5.0, pitch_deg=3.0, roll_deg=1.0, head_keys_per_s=0.4,
                         translate_mm=(5.0, 5.0, 10.0), talk=0.3, jaw_max=0.35, expressions_per_s=0.15,
                         expression_max=0.5),
    "frontal": MotionPreset("frontal", yaw_deg=0.0, pitch_deg=0.0, roll_deg=0.0, translate_mm=(0.0, 0.0, 0.0)),
    "yaw30": MotionPreset("yaw30", yaw_deg=0.0, pitch_deg=0.0, roll_deg=0.0, hold_yaw_deg=30.0,
                          translate_mm=(0.0, 0.0, 0.0)),
}


@dataclass
class Motion:
    """Per-frame parameters of a take (T frames, N-1 expression shapes)."""

    yaw_deg: np.ndarray         # (T,)
    pitch_deg: np.ndarray       # (T,)
    roll_deg: np.ndarray        # (T,)
    offset_mm: np.ndarray       # (T, 3) head offset in camera coordinates
    jaw_open: np.ndarray        # (T,) fraction of the jawOpen-like transform, 0..1
    coefficients: np.ndarray    # (T, N-1) expression weights, 0..1
    jaw_shape: int | None       # index of the jawOpen-like shape (None: the actor has none)


def jaw_shape_index(shape_names: list[str], jaw_angles_deg: np.ndarray | None = None) -> int | None:
    """The jawOpen-like shape: named ``jawOpen`` (any case), else the largest learned jaw rotation."""
    for i, n in enumerate(shape_names):
        if n.lower().replace("_", "") in ("jawopen", "mouthopen"):
            return i
    if jaw_angles_deg is not None and len(jaw_angles_deg) and float(np.max(jaw_angles_deg)) > 2.0:
        return int(np.argmax(jaw_angles_deg))
    return None


def _keys(rng: np.random.Generator, T: int, fps: float, keys_per_s: float, alternate: bool = False) -> np.ndarray:
    """A smooth signal in [-1, 1] over T frames: random keyframes joined by PCHIP curves."""
    if T == 1:
        return np.zeros(1)
    dur = (T - 1) / fps
    n = max(2, int(np.ceil(dur * keys_per_s)) + 2)
    # Evenly spaced keyframes with +-30 % jitter: never two keyframes close together (no jerks).
    t = np.linspace(0.0, dur, n)
    t[1:-1] += rng.uniform(-0.3, 0.3, n - 2) * (dur / (n - 1))
    if alternate:
        sign = np.where(np.arange(len(t)) % 2 == 0, 1.0, -1.0) * rng.choice([-1.0, 1.0])
        v = sign * rng.uniform(0.6, 1.0, len(t))
        v[0] *= 0.3
    else:
        v = rng.uniform(-1.0, 1.0, len(t))
    return np.clip(PchipInterpolator(t, v)(np.arange(T) / fps), -1.0, 1.0)


def _bump(T: int, fps: float, start: float, duration: float, attack: float) -> np.ndarray:
    """Raised-cosine envelope: rises over ``attack`` s, holds, falls over ``attack`` s."""
    t = np.arange(T) / fps - start
    a = max(attack, 1e-3)
    up = 0.5 - 0.5 * np.cos(np.pi * np.clip(t / a, 0, 1))
    down = 0.5 - 0.5 * np.cos(np.pi * np.clip((duration - t) / a, 0, 1))
    return np.minimum(up, down) * ((t >= 0) & (t <= duration))


def _talking(rng: np.random.Generator, T: int, fps: float, talk: float, jaw_max: float) -> np.ndarray:
    """Jaw opening: syllables at about 4 Hz inside phrases separated by pauses."""
    if talk <= 0 or jaw_max <= 0:
        return np.zeros(T)
    dur = T / fps
    env = np.zeros(T)
    t = rng.uniform(0.0, 0.5)
    while t < dur:
        length = rng.uniform(1.5, 4.0)
        env = np.maximum(env, _bump(T, fps, t, length, 0.15))
        t += length + rng.uniform(0.3, 1.2) * (1.0 - talk) / max(talk, 0.1) * 2.0 + 0.2
    # Syllables: alternate closed / open keyframes every 0.12-0.3 s.
    times, vals, s, k = [], [], 0.0, 0
    while s <= dur + 0.3:
        times.append(s)
        vals.append(rng.uniform(0.0, 0.1) if k % 2 == 0 else rng.uniform(0.35, 1.0))
        s += rng.uniform(0.12, 0.3)
        k += 1
    syl = np.clip(PchipInterpolator(times, vals)(np.arange(T) / fps), 0.0, 1.0)
    return jaw_max * env * syl


def generate_motion(preset: MotionPreset, n_frames: int, fps: float, shape_names: list[str], seed: int = 0,
                    jaw_angles_deg: np.ndarray | None = None) -> Motion:
    """Per-frame head angles, offset, jaw opening and expression weights (see the module docstring).

    Args:
        preset: one of :data:`PRESETS` (or a variant made with ``dataclasses.replace``).
        n_frames, fps: length and rate of the take.
        shape_names: the actor's N-1 expression shape names (they choose jaw, blink and expression
            channels); ``jaw_angles_deg (N-1,)`` the learned jaw rotation angles, used to find a
            jawOpen-like shape when none is named so.
        seed: the random seed; the same inputs give the same motion.
    """
    if n_frames < 1 or fps <= 0:
        raise ValueError(f"need n_frames >= 1 and fps > 0, got {n_frames}, {fps}")
    rng = np.random.default_rng(seed)
    T, E = n_frames, len(shape_names)
    p = preset
    yaw = p.hold_yaw_deg + p.yaw_deg * _keys(rng, T, fps, p.head_keys_per_s, p.turn_alternate)
    pitch = p.pitch_deg * _keys(rng, T, fps, p.head_keys_per_s)
    roll = p.roll_deg * _keys(rng, T, fps, p.head_keys_per_s * 0.7)
    offset = np.stack([a * _keys(rng, T, fps, 0.4) for a in p.translate_mm], 1)

    jaw_idx = jaw_shape_index(shape_names, jaw_angles_deg)
    jaw = _talking(rng, T, fps, p.talk, p.jaw_max) if jaw_idx is not None else np.zeros(T)
    coeff = np.zeros((T, E))
    if jaw_idx is not None:
        coeff[:, jaw_idx] = jaw
    lower = [n.lower() for n in shape_names]
    blink = [i for i, n in enumerate(lower) if "blink" in n]
    pool = [i for i, n in enumerate(lower) if i != jaw_idx and i not in blink and not n.startswith("jaw")]
    dur = T / fps
    if pool and p.expressions_per_s > 0:
        n_events = rng.poisson(p.expressions_per_s * dur) + 1
        for _ in range(n_events):
            start = rng.uniform(-0.5, dur)
            length = rng.uniform(0.8, 3.0)
            env = _bump(T, fps, start, length, min(0.4, length / 3))
            for i in rng.choice(pool, size=min(len(pool), rng.integers(1, 3)), replace=False):
                coeff[:, i] += env * rng.uniform(0.3, 1.0) * p.expression_max
    if blink and p.blinks:
        t = rng.uniform(0.5, 3.0)
        while t < dur:
            env = _bump(T, fps, t, rng.uniform(0.15, 0.25), 0.07)
            coeff[:, blink] = np.maximum(coeff[:, blink], env[:, None])
            t += rng.uniform(2.0, 6.0)
    coeff = np.clip(coeff, 0.0, 1.0)
    return Motion(yaw, pitch, roll, offset, jaw, coeff, jaw_idx)


def preset_dict(preset: MotionPreset) -> dict:
    """The preset as plain data (for truth.json)."""
    d = asdict(preset)
    d["translate_mm"] = list(d["translate_mm"])
    return d


__all__ = ["MotionPreset", "PRESETS", "Motion", "generate_motion", "jaw_shape_index", "preset_dict", "replace"]
