"""A synthetic open face mask with known axes, shared by tests."""

import numpy as np


def synthetic_face(n_th: int = 91, n_ph: int = 121, noise: float = 0.0, seed: int = 0):
    """Open face mask in mm, symmetric about x = 0: x = the face's left, y = up, z = forward.

    Half an ellipsoid (150 x 220 x 190 mm), narrowing toward the chin like a face, with a nose (tip at
    y = 0; gentle 45 mm bridge above, steep 12 mm drop below), eye sockets, a brow ridge at y = 55 (so
    there is a nasion dip near y = 45) and a chin.
    """
    th = np.radians(np.linspace(-80, 80, n_th))
    ph = np.radians(np.linspace(-65, 70, n_ph))
    t, p = np.meshgrid(th, ph, indexing="ij")
    x = 75.0 * np.sin(t) * np.cos(p)
    y = 110.0 * np.sin(p)
    z = 95.0 * np.cos(t) * np.cos(p)
    x = x * (1.0 - 0.3 * np.clip(-y / 110.0, 0.0, 1.0))  # the jaw is narrower than the temples
    nose = np.where(y >= 0, 22.0 * np.clip(1 - y / 45.0, 0, 1), 22.0 * np.clip(1 + y / 12.0, 0, 1))
    z = z + nose * np.exp(-(x**2) / 200.0)
    z = z + 7.0 * np.exp(-(((y - 55.0) / 10.0) ** 2)) * np.exp(-(x**2) / 2450.0)
    z = z + 8.0 * np.exp(-(((y + 85.0) / 12.0) ** 2)) * np.exp(-(x**2) / 800.0)
    for side in (-1.0, 1.0):
        z = z - 6.0 * np.exp(-((x - side * 32.0) ** 2 + (y - 35.0) ** 2) / 200.0)
    v = np.stack([x, y, z], -1).reshape(-1, 3)
    if noise:
        v = v + np.random.default_rng(seed).normal(scale=noise, size=v.shape)
    idx = np.arange(n_th * n_ph).reshape(n_th, n_ph)
    a0, a1, a2, a3 = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a0, a1, a2], 1), np.stack([a0, a2, a3], 1)])
    return v, f
