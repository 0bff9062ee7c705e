"""Marker paths without images, for the estimators' tests and benchmarks: a marker that cruises and
now and then turns hard (what one process noise cannot serve), and smooth sinusoids beside it."""

from __future__ import annotations

import numpy as np

#: where both paths are centred: 2.2 m in front of the first camera
CENTRE = np.array([0.0, 0.0, 2.2])


def turning(n: int, seed: int, dt: float = 1 / 30) -> tuple[np.ndarray, np.ndarray]:
    """(positions n × 3, turn flags n): a marker cruising about :data:`CENTRE` (pulled back to it at
    6 s⁻², its speed damped at 1.5 s⁻¹) that, at random (4 % of frames), turns hard for 3–8 frames
    at 8–14 m/s² (peaks of 11–15 m/s² with the pull back); it stays in view of a rig at the origin."""
    rng = np.random.default_rng(seed)
    x, v = np.array([-0.3, 0.0, 2.2]), rng.normal(0, 0.3, 3) * [1, 1, 0.5]
    out, turns, left, a = [], [], 0, np.zeros(3)
    for _ in range(n):
        if left == 0 and rng.random() < 0.04:
            left, a = int(rng.integers(3, 9)), rng.normal(0, 1, 3)
            a *= rng.uniform(8, 14) / np.linalg.norm(a)
        acc = (a if left else 0.0) - 6.0 * (x - CENTRE) - 1.5 * v
        turns.append(left > 0)
        left = max(0, left - 1)
        v = v + acc * dt
        x = x + v * dt
        out.append(x.copy())
    return np.array(out), np.array(turns)


def sinusoid(n: int, seed: int, dt: float = 1 / 30) -> np.ndarray:
    """n × 3 positions: a sinusoid per axis (0.2–0.6 Hz, amplitudes 0.3, 0.15 and 0.4 m) about
    :data:`CENTRE`: smooth motion, accelerations under 5 m/s²."""
    t, rng = np.arange(n) * dt, np.random.default_rng(seed)
    f, ph = rng.uniform(0.2, 0.6, 3), rng.uniform(0, 6, 3)
    return CENTRE + np.c_[0.3 * np.sin(2 * np.pi * f[0] * t + ph[0]), 0.15 * np.sin(2 * np.pi * f[1] * t + ph[1]),
                          0.4 * np.sin(2 * np.pi * f[2] * t + ph[2])]


def observed(rig, X: np.ndarray, seed: int, sigma: float = 1.0) -> np.ndarray:
    """What a detector would report of positions ``X`` (n × 3) through a stereo ``rig``: the
    projections with Gaussian noise ``sigma`` (px; drawn from ``seed + 50``), NaN where a camera's
    image does not hold the marker."""
    Y = rig.project(X) + np.random.default_rng(seed + 50).normal(0, sigma, (len(X), 4))
    w, h = rig.image_size
    for c in range(2):
        u, v = Y[:, 2 * c], Y[:, 2 * c + 1]
        Y[~((u >= 0) & (u < w) & (v >= 0) & (v < h)), 2 * c : 2 * c + 2] = np.nan
    return Y
