"""Extended Kalman filter on the stereo reprojection (thesis App. I; SPEC §4.5).

Model of :mod:`pipeline.estimators.base`; with ``H_k = ∂h/∂x`` at the prediction (the analytic
Jacobian of :func:`pipeline.camera.project_jacobian`, zeros for the velocity)::

    x⁻ = A x,            P⁻ = A P Aᵀ + Q
    S = H P⁻ Hᵀ + R,      K = P⁻ Hᵀ S⁻¹
    x = x⁻ + K (y − h(x⁻)),  P = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ   (Joseph form, as filterpy)

Single tracks run through ``filterpy.kalman.ExtendedKalmanFilter`` (measurements passed as column
vectors: filterpy 2.0.0 reshapes the state when ``z`` is 1-D). ``run_batch`` runs the same
equations vectorised over many tracks. A camera without a detection drops its two rows.
"""

from __future__ import annotations

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from pipeline.estimators.base import NAN3, Estimator, Step, register, transition, white_noise_acceleration
from pipeline.estimators.kalman_common import KalmanConfig, available_rows, initial_covariance


def measurement_jacobian(rig, p: np.ndarray) -> np.ndarray:
    """``H = [∂h/∂p, 0]`` (…×4×6) at positions ``p`` (…×3)."""
    J = rig.jacobian(p)
    return np.concatenate([J, np.zeros_like(J)], axis=-1)


@register
class EKFEstimator(Estimator):
    """EKF with white-noise-acceleration ``Q`` and ``R = σ² I`` on the 4-D stereo observation."""

    name = "ekf"
    Config = KalmanConfig

    def reset(self) -> None:
        super().reset()
        cfg: KalmanConfig = self.config  # type: ignore[assignment]
        self.A = transition(self.dt)
        self.Q = white_noise_acceleration(self.dt, cfg.process_noise * cfg.q_scale)
        self.R = np.eye(4) * (cfg.pixel_sigma**2 * cfg.r_scale)
        self.filter = ExtendedKalmanFilter(dim_x=6, dim_z=4)
        self.filter.F, self.filter.Q, self.filter.R = self.A, self.Q, self.R

    @property
    def x(self) -> np.ndarray:
        return self.filter.x.ravel()

    @property
    def P(self) -> np.ndarray:
        return self.filter.P

    def _step(self, y: np.ndarray) -> Step:
        if not self.initialized:
            x0 = self.initial_state(y)
            if x0 is None:
                return Step(NAN3.copy(), NAN3.copy(), predicted=True)
            self.filter.x = x0.reshape(6, 1)
            self.filter.P = initial_covariance(self.config)  # type: ignore[arg-type]
            self.initialized = True
        else:
            self.filter.predict()
        rows = available_rows(y)
        if len(rows):
            self.filter.update(
                y[rows].reshape(-1, 1),
                lambda x: measurement_jacobian(self.rig, x[:3, 0])[rows],
                lambda x: self.rig.project(x[:3, 0])[rows].reshape(-1, 1),
                R=self.R[np.ix_(rows, rows)],
            )
        x = self.x
        return Step(x[:3].copy(), x[3:].copy(), covariance=self.P.copy(), predicted=not len(rows))

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        return batch_ekf(self, np.asarray(Y, dtype=float))


def batch_ekf(est: EKFEstimator, Y: np.ndarray) -> np.ndarray:
    """The EKF of :class:`EKFEstimator` over M tracks at once (M × frames × 4 → M × frames × 3).

    Missing rows get ``H = 0``, residual 0 and unit variance: their gain column is exactly zero,
    so the update equals the reduced one.
    """
    from pipeline.estimators.triangulation import triangulate

    est.reset()
    M, n, _ = Y.shape
    A, Q, R = est.A, est.Q, est.R
    P0 = initial_covariance(est.config)  # type: ignore[arg-type]
    x = np.zeros((M, 6))
    P = np.broadcast_to(P0, (M, 6, 6)).copy()
    started = np.zeros(M, dtype=bool)
    out = np.full((M, n, 3), np.nan)
    eye = np.eye(6)
    for k in range(n):
        y = Y[:, k]
        new = ~started & np.all(np.isfinite(y), axis=1)
        # predict the running tracks
        x[started] = x[started] @ A.T
        P[started] = A @ P[started] @ A.T + Q
        if new.any():
            if est.config.init.mode == "given":
                x[new] = np.array(est.config.init.state)
            else:
                x[new, :3] = triangulate(est.rig, y[new])
                x[new, 3:] = 0.0
            P[new] = P0
            started |= new
        ok = np.isfinite(y)
        ok[:, :2] &= ok[:, :2].all(axis=1, keepdims=True)
        ok[:, 2:] &= ok[:, 2:].all(axis=1, keepdims=True)
        ok &= started[:, None]
        upd = ok.any(axis=1)
        if upd.any():
            xs, Ps, oks = x[upd], P[upd], ok[upd]
            H = measurement_jacobian(est.rig, xs[:, :3]) * oks[:, :, None]
            r = np.where(oks, np.nan_to_num(y[upd]) - est.rig.project(xs[:, :3]), 0.0)
            Rk = np.where(oks[:, :, None] & oks[:, None, :], R, 0.0) + np.eye(4) * ~oks[:, :, None]
            PHt = Ps @ H.transpose(0, 2, 1)
            S = H @ PHt + Rk
            K = np.linalg.solve(S, PHt.transpose(0, 2, 1)).transpose(0, 2, 1)  # P Hᵀ S⁻¹ (S symmetric)
            xs = xs + np.einsum("mij,mj->mi", K, r)
            IKH = eye - K @ H
            Ps = IKH @ Ps @ IKH.transpose(0, 2, 1) + K @ Rk @ K.transpose(0, 2, 1)
            x[upd], P[upd] = xs, Ps
        out[started, k] = x[started, :3]
    return out
