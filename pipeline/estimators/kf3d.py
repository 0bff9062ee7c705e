"""Linear Kalman filter on triangulated 3-D points (Mikić et al.; the baseline the thesis
criticises because triangulation makes the measurement noise non-additive and depth-dependent).

``z_k = [I 0] x_k + v_k`` with ``z_k`` the DLT triangulation of frame k. The measurement
covariance is propagated from the pixel noise at each frame, ``R_k = σ² (Jᵀ J)⁻¹`` with ``J`` the
stereo projection Jacobian at ``z_k`` (first-order error propagation), or a constant
``sigma_3d² I`` when ``measurement_noise: constant``.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from filterpy.kalman import KalmanFilter
from pydantic import Field

from pipeline.estimators.base import NAN3, Estimator, Step, register, transition, white_noise_acceleration
from pipeline.estimators.kalman_common import KalmanConfig, initial_covariance
from pipeline.estimators.triangulation import triangulate


class KF3DConfig(KalmanConfig):
    measurement_noise: Literal["propagated", "constant"] = "propagated"
    sigma_3d: float = Field(0.02, gt=0)


H3 = np.hstack([np.eye(3), np.zeros((3, 3))])


@register
class KF3DEstimator(Estimator):
    """KF with ``H = [I 0]`` on triangulated points."""

    name = "kf3d"
    Config = KF3DConfig

    def reset(self) -> None:
        super().reset()
        cfg: KF3DConfig = self.config  # type: ignore[assignment]
        self.filter = KalmanFilter(dim_x=6, dim_z=3)
        self.filter.F = transition(self.dt)
        self.filter.Q = white_noise_acceleration(self.dt, cfg.process_noise * cfg.q_scale)
        self.filter.H = H3

    def measurement_covariance(self, X: np.ndarray) -> np.ndarray:
        """``R_k`` for triangulated points ``X`` (…×3 → …×3×3)."""
        cfg: KF3DConfig = self.config  # type: ignore[assignment]
        s2 = cfg.pixel_sigma**2 * cfg.r_scale
        if cfg.measurement_noise == "constant":
            return np.broadcast_to(np.eye(3) * cfg.sigma_3d**2 * cfg.r_scale, (*X.shape[:-1], 3, 3)).copy()
        J = self.rig.jacobian(X)
        return s2 * np.linalg.inv(np.swapaxes(J, -1, -2) @ J)

    def _step(self, y: np.ndarray) -> Step:
        f = self.filter
        X = triangulate(self.rig, y[None])[0]
        have = bool(np.all(np.isfinite(X)))
        if not self.initialized:
            x0 = self.initial_state(y)
            if x0 is None:
                return Step(NAN3.copy(), NAN3.copy(), predicted=True)
            f.x = x0.reshape(6, 1)
            f.P = initial_covariance(self.config)  # type: ignore[arg-type]
            self.initialized = True
        else:
            f.predict()
        if have:
            f.update(X.reshape(3, 1), R=self.measurement_covariance(X[None])[0])
        x = f.x.ravel()
        return Step(x[:3].copy(), x[3:].copy(), covariance=f.P.copy(), predicted=not have)

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        """The same filter vectorised over tracks (M × frames × 4 → M × frames × 3)."""
        Y = np.asarray(Y, dtype=float)
        self.reset()
        M, n, _ = Y.shape
        A, Q = self.filter.F, self.filter.Q
        P0 = initial_covariance(self.config)  # type: ignore[arg-type]
        x, P = np.zeros((M, 6)), np.broadcast_to(P0, (M, 6, 6)).copy()
        started = np.zeros(M, dtype=bool)
        out = np.full((M, n, 3), np.nan)
        Z = triangulate(self.rig, Y.reshape(-1, 4)).reshape(M, n, 3)
        eye = np.eye(6)
        for k in range(n):
            z = Z[:, k]
            have = np.all(np.isfinite(z), axis=1)
            x[started] = x[started] @ A.T
            P[started] = A @ P[started] @ A.T + Q
            new = ~started & have
            if self.config.init.mode == "given":
                x[new] = np.array(self.config.init.state)
            else:
                x[new, :3], x[new, 3:] = z[new], 0.0
            P[new] = P0
            started |= new
            upd = have & started
            if upd.any():
                R = self.measurement_covariance(z[upd])
                Ps = P[upd]
                S = Ps[:, :3, :3] + R
                K = np.linalg.solve(S, Ps[:, :3, :]).transpose(0, 2, 1)  # P Hᵀ S⁻¹
                x[upd] += np.einsum("mij,mj->mi", K, z[upd] - x[upd, :3])
                IKH = eye - K @ H3
                P[upd] = IKH @ Ps @ IKH.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)
            out[started, k] = x[started, :3]
        return out
