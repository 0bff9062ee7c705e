"""The recording's geometry: the covariance ellipsoids' rotations are scipy's, bit for bit, without
importing scipy.spatial (about half a second of `stereotrack run`)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import gammaincinv

from pipeline.present.shapes import ellipsoid_columns, quaternions


def test_quaternions_are_scipy_s_to_the_last_bit():
    """Eigenvector frames of random covariances (every branch of Shepperd's method: the trace and
    each diagonal entry largest), half-turns about each axis and the identity."""
    rng = np.random.default_rng(7)
    A = rng.normal(size=(5000, 3, 3)) * rng.uniform(1e-4, 1.0, size=(5000, 1, 1))
    _, vecs = np.linalg.eigh(A @ A.transpose(0, 2, 1))
    vecs[np.linalg.det(vecs) < 0, :, 0] *= -1
    special = np.stack([np.eye(3), np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])])
    R = np.concatenate([vecs, special])
    d = np.stack([R[:, 0, 0], R[:, 1, 1], R[:, 2, 2], np.trace(R, axis1=1, axis2=2)], axis=1)
    assert set(np.argmax(d, axis=1).tolist()) == {0, 1, 2, 3}
    np.testing.assert_array_equal(quaternions(R), Rotation.from_matrix(R).as_quat())


def test_ellipsoids_half_axes_are_the_chi2_quantile_s():
    cov = np.array([np.diag([4.0, 1.0, 0.25]), [[2.0, 0.5, 0.0], [0.5, 1.0, 0.1], [0.0, 0.1, 0.5]]])
    half, quats = ellipsoid_columns(cov.copy())
    np.testing.assert_array_equal(half, np.sqrt(2 * gammaincinv(1.5, 0.95) * np.linalg.eigvalsh(cov)))
    np.testing.assert_allclose(np.linalg.norm(quats, axis=1), 1.0, atol=1e-15)
