"""Extended Kalman filter on the stereo reprojection (thesis App. I; SPEC §4.5).

Model of :mod:`pipeline.estimators.base`; with ``H_k = ∂h/∂x`` at the prediction (the measurement
model's analytic ``jacobian``, zeros for the velocity)::

    x⁻ = A x,            P⁻ = A P Aᵀ + Q
    S = H P⁻ Hᵀ + R,      K = P⁻ Hᵀ S⁻¹
    x = x⁻ + K (y − h(x⁻)),  P = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ   (Joseph form, as filterpy)

Single tracks run through ``filterpy.kalman.ExtendedKalmanFilter`` (measurements passed as column
vectors: filterpy 2.0.0 reshapes the state when ``z`` is 1-D). ``run_batch`` runs the same
equations vectorised over many tracks. A camera without a detection drops its two rows.
``ekf_rts`` adds the Rauch–Tung–Striebel backward pass (the transition is linear, so filterpy's
smoother applies as it is).
"""

from __future__ import annotations

import numpy as np

from pipeline.estimators.base import Estimator, Step, not_started, register, transition, white_noise_acceleration
from pipeline.estimators.kalman_common import (
    GatedFilter,
    KalmanConfig,
    RTSMixin,
    available_rows,
    filtered_step,
    gated_step,
    kalman_batch,
)


@register
class EKFEstimator(GatedFilter, Estimator):
    """Extended Kalman filter on the 4-D stereo reprojection (white-noise acceleration)."""

    name = "ekf"
    Config = KalmanConfig
    models_time_offset = True

    def reset(self) -> None:
        super().reset()
        cfg: KalmanConfig = self.config  # type: ignore[assignment]
        self.A = transition(self.dt)
        self.Q = white_noise_acceleration(self.dt, cfg.process_noise * cfg.q_scale)
        self.R = self.model.covar() * cfg.r_scale
        from filterpy.kalman import ExtendedKalmanFilter  # imported when a filter is built (see base.py)

        self.filter = ExtendedKalmanFilter(dim_x=6, dim_z=4)
        self.filter.F, self.filter.Q, self.filter.R = self.A, self.Q, self.R

    @property
    def x(self) -> np.ndarray:
        return self.filter.x.ravel()

    @property
    def P(self) -> np.ndarray:
        return self.filter.P

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
        rows = available_rows(y)
        if len(rows):
            f.update(y[rows].reshape(-1, 1),
                     lambda x: self.model.jacobian(x[:, 0])[rows],
                     lambda x: self.model.function(x[:, 0])[rows].reshape(-1, 1),
                     R=self.R[np.ix_(rows, rows)])
        return gated_step(filtered_step(f.x, f.P, not len(rows), f), n_gated)

    def _linearize(self, p: np.ndarray, y: np.ndarray):
        """Missing rows get ``H = 0``, residual 0 and unit variance: their gain column is exactly
        zero, so the update equals the reduced one."""
        ok = np.isfinite(y)
        ok[:, :2] &= ok[:, :2].all(axis=1, keepdims=True)
        ok[:, 2:] &= ok[:, 2:].all(axis=1, keepdims=True)
        H = self.model.jacobian(p) * ok[:, :, None]
        r = np.where(ok, np.nan_to_num(y) - self.model.function(p), 0.0)
        R = np.where(ok[:, :, None] & ok[:, None, :], self.R, 0.0) + np.eye(4) * ~ok[:, :, None]
        return H, r, R, ok.any(axis=1)

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        """The same filter vectorised over tracks (M × frames × 4 → M × frames × 3)."""
        return kalman_batch(self, np.asarray(Y, dtype=float), self._linearize)


@register
class EKFRTSEstimator(RTSMixin, EKFEstimator):
    """ekf followed by a Rauch–Tung–Striebel backward pass (offline smoothing)."""

    name = "ekf_rts"
