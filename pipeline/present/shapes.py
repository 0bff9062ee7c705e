"""What the recording draws, as geometry: detections' rings, methods' crosses, covariance
ellipsoids, and a camera pane's width (which the 2-D sizes are fractions of)."""

from __future__ import annotations

import numpy as np

from pipeline.core.camera import StereoRig
from pipeline.core.chi2 import gammaincinv
from pipeline.core.rig import Rig

_RING = np.stack([np.cos(np.linspace(0, 2 * np.pi, 17)), np.sin(np.linspace(0, 2 * np.pi, 17))], axis=1)  # closed


def ellipsoid_columns(cov: np.ndarray, level: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Half-axes and rotations (quaternions, xyzw) of the ``level`` ellipsoids of 3×3 position
    covariances (``n × 3 × 3``): the axes are the eigenvectors, the half-lengths √(χ²₃(level) λ)."""
    vals, vecs = np.linalg.eigh(cov)
    vecs[np.linalg.det(vecs) < 0, :, 0] *= -1  # a proper rotation
    half = np.sqrt(2 * gammaincinv(1.5, level) * np.clip(vals, 0, None))
    return half, quaternions(vecs)


def quaternions(R: np.ndarray) -> np.ndarray:
    """Unit quaternions (xyzw) of rotation matrices (``n × 3 × 3``, orthonormal): Shepperd's method
    (J. Guidance and Control 1(3), 1978) as ``scipy.spatial.transform.Rotation.from_matrix`` does
    it, the same bits (tested), without its import (about half a second of ``run``'s recording)."""
    R = np.asarray(R, dtype=float)
    d = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], R[:, 0, 0] + R[:, 1, 1] + R[:, 2, 2]], axis=1)
    choice, q = np.argmax(d, axis=1), np.empty((len(R), 4))
    for c in np.unique(choice):  # the largest of the diagonal and the trace: the best-conditioned formula
        m = choice == c
        M, tr = R[m], d[m, 3]
        if c == 3:
            q[m] = np.stack([M[:, 2, 1] - M[:, 1, 2], M[:, 0, 2] - M[:, 2, 0], M[:, 1, 0] - M[:, 0, 1], 1 + tr], axis=1)
            continue
        i, j, k = c, (c + 1) % 3, (c + 2) % 3
        out = np.empty((len(M), 4))
        out[:, i], out[:, 3] = 1 - tr + 2 * M[:, i, i], M[:, k, j] - M[:, j, k]
        out[:, j], out[:, k] = M[:, j, i] + M[:, i, j], M[:, k, i] + M[:, i, k]
        q[m] = out
    return q / np.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3])[:, None]


def pane_width(rig: StereoRig | Rig, c: int) -> float:
    """Camera ``c``'s image width in pixels (640 where the calibration does not say)."""
    w = rig.sizes[c][0] if c < len(rig.sizes) else 0
    return float(w or 640)


def rings(centres: np.ndarray, radius: float) -> np.ndarray:
    """A closed 16-gon of ``radius`` around each centre (n × 2 → n × 17 × 2): a detection drawn as an
    outline leaves the blob it found visible inside it."""
    return centres[:, None, :] + radius * _RING[None]


def crosses(centres: np.ndarray, arm: float) -> np.ndarray:
    """An upright cross at each centre as two 2-point strips (n × 2 → 2n × 2 × 2, the pair of each point
    together): a method's reprojection, told from the rings at a glance."""
    d = np.array([[[-arm, 0.0], [arm, 0.0]], [[0.0, -arm], [0.0, arm]]])
    return (centres[:, None, None, :] + d[None]).reshape(-1, 2, 2)
