"""What the recording draws, as geometry: detections' rings, methods' crosses, covariance
ellipsoids, and a camera pane's width (which the 2-D sizes are fractions of)."""

from __future__ import annotations

import numpy as np

from pipeline.core.camera import StereoRig
from pipeline.core.rig import Rig

_RING = np.stack([np.cos(np.linspace(0, 2 * np.pi, 17)), np.sin(np.linspace(0, 2 * np.pi, 17))], axis=1)  # closed


def ellipsoid_columns(cov: np.ndarray, level: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """Half-axes and rotations (quaternions, xyzw) of the ``level`` ellipsoids of 3×3 position
    covariances (``n × 3 × 3``): the axes are the eigenvectors, the half-lengths √(χ²₃(level) λ)."""
    from scipy.spatial.transform import Rotation
    from scipy.special import gammaincinv  # χ²'s quantile without scipy.stats' ~1 s import

    vals, vecs = np.linalg.eigh(cov)
    vecs[np.linalg.det(vecs) < 0, :, 0] *= -1  # a proper rotation
    half = np.sqrt(2 * gammaincinv(1.5, level) * np.clip(vals, 0, None))
    return half, Rotation.from_matrix(vecs).as_quat()


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
