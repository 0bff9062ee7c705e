"""Linear Kalman filter on triangulated 3-D points (Mikić et al.; the baseline the thesis
criticises because triangulation makes the measurement noise non-additive and depth-dependent).

``z_k = [I 0] x_k + v_k`` with ``z_k = h⁻¹(y_k)`` the triangulation of frame k (the measurement
model's ``inverse_function``). The measurement covariance is propagated from the pixel noise at
each frame, ``R_k = σ² (Jᵀ J)⁻¹`` (the model's ``inverse_covariance``), or a constant
``sigma_3d² I`` when ``measurement_noise: constant``. A frame with one camera kept (the other
gated or missing) triangulates nothing: that camera's pixel updates the state through the
measurement model instead, linearised at the prediction (the EKF's update on 2 rows), so the track
follows the camera it keeps. ``kf3d_rts`` adds the Rauch–Tung–Striebel backward pass.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from pipeline.estimators.base import Estimator, Step, not_started, transition, white_noise_acceleration
from pipeline.estimators.filters import KalmanFilter
from pipeline.estimators.kalman_common import (
    GatedFilter,
    KalmanConfig,
    RTSMixin,
    available_rows,
    filtered_step,
    gated_step,
    joseph_update,
    kalman_batch,
)
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
    joint_check = True
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
        x = f.x[:, 0]
        h, H = self.model.linearize(x)
        S = H @ f.P @ H.T + self.gate_covariance()
        y, n_gated, restart = self.gate(y, x, f.P, h, H, S)
        if restart is not None:
            f.x, f.P = restart.state.reshape(6, 1), restart.covariance.copy()
            return gated_step(filtered_step(f.x, f.P, False), n_gated, True)
        rows = available_rows(y)
        if len(rows) == 2:  # one camera kept: its pixel through the measurement model, linearised at x
            r, Hc, R = y[rows] - h[rows], H[rows], self.gate_covariance()[np.ix_(rows, rows)]
            xn, Pn = joseph_update(x[None], f.P[None], Hc[None], r[None], R[None])
            f.x, f.P = xn[0].reshape(6, 1), Pn[0]
            return gated_step(filtered_step(f.x, f.P, False, innovation=r, innovation_covariance=S[np.ix_(rows, rows)]),
                              n_gated)
        X = self.model.inverse_function(y[None])[0] if len(rows) else np.full(3, np.nan)
        have = bool(np.all(np.isfinite(X)))
        if have:
            f.update(X.reshape(3, 1), R=self.measurement_covariance(X[None])[0])
        return gated_step(filtered_step(f.x, f.P, not have, f), n_gated)

    def _linearize(self, x: np.ndarray, y: np.ndarray):
        """The update of each of M tracks: on its triangulated point (H = [I 0], 3 rows), or where
        one camera is kept on that camera's pixel linearised at ``x`` (2 rows; the rows are then
        padded to 4 with rows that carry nothing: H = 0, residual 0, unit variance)."""
        p = x[:, :3]
        Z = self.model.inverse_function(y)
        have = np.all(np.isfinite(Z), axis=1)
        one = np.isfinite(y).sum(axis=1) == 2
        m = 4 if one.any() else 3
        H = np.zeros((len(p), m, 6))
        H[:, :3, :3] = np.eye(3)
        r = np.zeros((len(p), m))
        r[have, :3] = Z[have] - p[have]
        R = np.broadcast_to(np.eye(m), (len(p), m, m)).copy()
        if have.any():
            R[have, :3, :3] = self.measurement_covariance(Z[have])
        if one.any():
            H[one] = 0.0
            Hs, hs = self.model.jacobian(x[one]), self.model.function(x[one])
            for i, m_ in enumerate(np.flatnonzero(one)):
                rows = np.flatnonzero(np.isfinite(y[m_]))
                H[m_, :2], r[m_, :2] = Hs[i][rows], y[m_, rows] - hs[i][rows]
                R[m_, :2, :2] = self.gate_covariance()[np.ix_(rows, rows)]
        return H, r, R, have | one

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        """The same filter vectorised over tracks (M × frames × 4 → M × frames × 3)."""
        return kalman_batch(self, np.asarray(Y, dtype=float), self._linearize)


@register
class KF3DRTSEstimator(RTSMixin, KF3DEstimator):
    """kf3d followed by a Rauch–Tung–Striebel backward pass (offline smoothing)."""

    name = "kf3d_rts"
