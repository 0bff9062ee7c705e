"""Linear Kalman filter on triangulated 3-D points (Mikić et al.; the baseline the thesis
criticises because triangulation makes the measurement noise non-additive and depth-dependent).

``z_k = [I 0] x_k + v_k`` with ``z_k = h⁻¹(y_k)`` the triangulation of frame k (the measurement
model's ``inverse_function``). The measurement covariance is propagated from the pixel noise at
each frame, ``R_k = σ² (Jᵀ J)⁻¹`` (the model's ``inverse_covariance``), or a constant
``sigma_3d² I`` when ``measurement_noise: constant``. ``kf3d_rts`` adds the Rauch–Tung–Striebel
backward pass.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from pipeline.estimators.base import Estimator, Step, not_started, transition, white_noise_acceleration
from pipeline.estimators.filters import KalmanFilter
from pipeline.estimators.kalman_common import GatedFilter, KalmanConfig, RTSMixin, filtered_step, gated_step, kalman_batch
from pipeline.estimators.registration import register


class KF3DConfig(KalmanConfig):
    measurement_noise: Literal["propagated", "constant"] = "propagated"
    """'propagated': each triangulated point's covariance from the pixel noise; 'constant': sigma_3d² I"""
    sigma_3d: float = Field(0.02, gt=0)
    """std (m) of a triangulated point when ``measurement_noise`` is 'constant'"""


H3 = np.hstack([np.eye(3), np.zeros((3, 3))])


@register
class KF3DEstimator(GatedFilter, Estimator):
    """Kalman filter with H = [I 0] on triangulated points."""

    name = "kf3d"
    any_cameras = True
    Config = KF3DConfig
    config: KF3DConfig  # the validated settings, of this method's own type

    def reset(self) -> None:
        super().reset()
        cfg = self.config
        self.A = transition(self.dt)
        self.Q = white_noise_acceleration(self.dt, cfg.process_noise * cfg.q_scale)
        self.filter = KalmanFilter(dim_x=6, dim_z=3)
        self.filter.F, self.filter.Q, self.filter.H = self.A, self.Q, H3

    def measurement_covariance(self, X: np.ndarray) -> np.ndarray:
        """``R_k`` for triangulated points ``X`` (…×3 → …×3×3)."""
        cfg = self.config
        if cfg.measurement_noise == "constant":
            return np.broadcast_to(np.eye(3) * cfg.sigma_3d**2 * cfg.r_scale, (*X.shape[:-1], 3, 3)).copy()
        return self.model.inverse_covariance(X) * cfg.r_scale

    def _step(self, y: np.ndarray) -> Step:
        f = self.filter
        if not self.initialized:
            s = self.start(y)
            if s is None:
                return not_started()
            f.x, f.P = s.state.reshape(6, 1), s.covariance.copy()
            self.initialized = True
            return filtered_step(f.x, f.P, False)
        f.predict()
        y, n_gated, restart = self.gate(y, f.x[:, 0], f.P)
        if restart is not None:
            f.x, f.P = restart.state.reshape(6, 1), restart.covariance.copy()
            return gated_step(filtered_step(f.x, f.P, False), n_gated, True)
        X = self.model.inverse_function(y[None])[0]  # a gated camera leaves nothing to triangulate
        have = bool(np.all(np.isfinite(X)))
        if have:
            f.update(X.reshape(3, 1), R=self.measurement_covariance(X[None])[0])
        return gated_step(filtered_step(f.x, f.P, not have, f), n_gated)

    def _linearize(self, p: np.ndarray, y: np.ndarray):
        Z = self.model.inverse_function(y)
        have = np.all(np.isfinite(Z), axis=1)
        H = np.broadcast_to(H3, (len(p), 3, 6))
        R = np.zeros((len(p), 3, 3))
        if have.any():
            R[have] = self.measurement_covariance(Z[have])
        return H, Z - p, R, have

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        """The same filter vectorised over tracks (M × frames × 4 → M × frames × 3)."""
        return kalman_batch(self, np.asarray(Y, dtype=float), self._linearize)


@register
class KF3DRTSEstimator(RTSMixin, KF3DEstimator):
    """kf3d followed by a Rauch–Tung–Striebel backward pass (offline smoothing)."""

    name = "kf3d_rts"
