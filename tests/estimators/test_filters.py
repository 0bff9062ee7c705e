"""The numpy filters the built-in methods build equal filterpy's own classes, driven side by side."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.common import Q_continuous_white_noise
from filterpy.kalman import KalmanFilter as FilterpyKF
from filterpy.kalman import MerweScaledSigmaPoints
from filterpy.kalman import UnscentedKalmanFilter as FilterpyUKF

from pipeline.estimators.base import transition, white_noise_acceleration
from pipeline.estimators.filters import KalmanFilter, MerweSigmaPoints, UnscentedKalmanFilter


@pytest.mark.parametrize(("dt", "q", "dim"), [(1 / 30, 0.5, 3), (0.01, 3.0, 3), (0.2, 1e-4, 2)])
def test_white_noise_acceleration_is_filterpys(dt: float, q: float, dim: int) -> None:
    ref = Q_continuous_white_noise(2, dt, q, block_size=dim, order_by_dim=False)
    np.testing.assert_array_equal(white_noise_acceleration(dt, q, dim), ref)


def test_kalman_filter_and_smoother_are_filterpys() -> None:
    """Predict/update with a varying R and skipped updates, then the RTS pass, equal to the last bit."""
    rng = np.random.default_rng(4)
    dt = 1 / 30
    ours, ref = KalmanFilter(6, 3), FilterpyKF(dim_x=6, dim_z=3)
    for f in (ours, ref):
        f.F, f.Q, f.H = transition(dt), white_noise_acceleration(dt, 0.5), np.hstack([np.eye(3), np.zeros((3, 3))])
    x0 = rng.normal(size=(6, 1))
    ours.x, ours.P, ref.x, ref.P = x0.copy(), np.eye(6) * 0.1, x0.copy(), np.eye(6) * 0.1
    xs, Ps = [], []
    for k in range(60):
        z, R = rng.normal(size=(3, 1)), np.diag(rng.uniform(1e-4, 1e-2, 3))
        for f in (ours, ref):
            f.predict()
            if k % 7:
                f.update(z, R=R)
        np.testing.assert_array_equal(ours.x, ref.x)
        np.testing.assert_array_equal(ours.P, ref.P)
        if k % 7:
            np.testing.assert_array_equal(ours.y, ref.y)
            np.testing.assert_array_equal(ours.S, ref.S)
        xs.append(ours.x[:, 0])
        Ps.append(ours.P)
    got, want = ours.rts_smoother(np.array(xs), np.array(Ps)), ref.rts_smoother(np.array(xs), np.array(Ps))
    np.testing.assert_allclose(got[0], want[0], rtol=0, atol=1e-12)
    np.testing.assert_allclose(got[1], want[1], rtol=0, atol=1e-12)
    assert np.abs(got[0] - np.array(xs)).max() > 1e-3  # the pass moved the means


def test_unscented_filter_is_filterpys_on_a_nonlinear_model() -> None:
    """A range-bearing-like model (nonlinear h, column-sliced sigma points), several steps, to the last bit."""
    rng = np.random.default_rng(9)
    A = transition(0.1, dim=2)

    def h(s: np.ndarray) -> np.ndarray:
        s = np.atleast_2d(s)
        return np.stack([np.hypot(s[:, 0], s[:, 1]), np.arctan2(s[:, 1], s[:, 0]), s[:, 2]], axis=1)

    ours = UnscentedKalmanFilter(4, MerweSigmaPoints(4, 0.3, 2.0, -1.0), fx=lambda S: np.array([A @ s for s in S]))
    ref = FilterpyUKF(dim_x=4, dim_z=3, dt=0.1, hx=None, fx=lambda x, dt: A @ x,
                      points=MerweScaledSigmaPoints(4, alpha=0.3, beta=2.0, kappa=-1.0))
    x0, P0, Q = np.array([5.0, 2.0, 0.3, -0.1]), np.eye(4) * 0.2, white_noise_acceleration(0.1, 0.3, 2)
    for f in (ours, ref):
        f.x, f.P, f.Q = x0.copy(), P0.copy(), Q
    R = np.diag([0.01, 1e-4, 0.02])
    for _ in range(25):
        z = h(ours.x)[0] + rng.normal(0, [0.1, 0.01, 0.1])
        ours.predict()
        ref.predict()
        sig = h(ours.sigmas_f)[:, [0, 1, 2]]  # column-indexed, as the UKF's reduced update (not C-ordered)
        ours.update(z, R, sig)
        rows = iter(sig)
        ref.update(z, R=R, hx=lambda _x, rows=rows: next(rows))
        for a, b in ((ours.x, ref.x), (ours.P, ref.P), (ours.S, ref.S), (ours.y, ref.y)):
            np.testing.assert_array_equal(a, b)


def test_the_sigma_points_factor_is_scipys_cholesky_bit_for_bit() -> None:
    """numpy's upper Cholesky factor (no scipy.linalg import) equals ``scipy.linalg.cholesky``, which
    filterpy's sigma points take, to the last bit, over covariances spanning eight decades."""
    from scipy.linalg import cholesky

    rng = np.random.default_rng(3)
    for _ in range(2000):
        n = int(rng.integers(2, 10))
        M = rng.normal(size=(n, n)) * 10.0 ** rng.uniform(-4, 4)
        A = M @ M.T + 1e-3 * np.eye(n)
        np.testing.assert_array_equal(MerweSigmaPoints.cholesky(A), cholesky(A))
    with pytest.raises(np.linalg.LinAlgError):
        MerweSigmaPoints.cholesky(-np.eye(3))
    with pytest.raises(ValueError, match="NaN"):
        MerweSigmaPoints.cholesky(np.full((3, 3), np.nan))
