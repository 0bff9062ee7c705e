"""Unscented Kalman filter (filterpy's ``UnscentedKalmanFilter`` equations, :mod:`~pipeline.estimators.filters`) on the
same model as the EKF:
sigma points (Van der Merwe's scaled set) through ``x ↦ A x`` and the measurement model's
``function``; no Jacobian needed."""

from __future__ import annotations

import numpy as np

from pipeline.estimators.base import Estimator, Step, not_started, transition, white_noise_acceleration
from pipeline.estimators.filters import MerweSigmaPoints, UnscentedKalmanFilter
from pipeline.estimators.kalman_common import GatedFilter, KalmanConfig, available_rows, filtered_step, gated_step
from pipeline.estimators.registration import register


@register
class UKFEstimator(GatedFilter, Estimator):
    """Unscented Kalman filter on the stereo (or N-camera) reprojection (white-noise acceleration)."""

    name = "ukf"
    joint_check = True
    any_cameras = True
    Config = KalmanConfig
    config: KalmanConfig  # the validated settings, of this method's own type
    models_time_offset = True

    def reset(self) -> None:
        super().reset()
        cfg = self.config
        self.A = transition(self.dt)
        self.Q = white_noise_acceleration(self.dt, cfg.process_noise * cfg.q_scale)
        self.R = self.model.covar() * cfg.r_scale
        points = MerweSigmaPoints(6, alpha=0.3, beta=2.0, kappa=-3.0)
        A = self.A
        # row by row, as filterpy: one matrix product over all points differs in the last bit
        self.filter = UnscentedKalmanFilter(6, points, fx=lambda sigmas: np.array([A @ s for s in sigmas]))
        self.filter.Q = self.Q

    def _step(self, y: np.ndarray) -> Step:
        f = self.filter
        if not self.initialized:
            s = self.start(y)
            if s is None:
                return not_started()
            f.x, f.P = s.state.copy(), s.covariance.copy()
            self.initialized = True
            return filtered_step(f.x, f.P, False)
        f.predict()
        y, n_gated, restart = self.gate(y, f.x, f.P)  # gated on the first-order S at the prediction
        if restart is not None:
            f.x, f.P = restart.state.copy(), restart.covariance.copy()
            return gated_step(filtered_step(f.x, f.P, False), n_gated, True)
        rows = available_rows(y)
        if not len(rows):
            f.x, f.P = f.x_prior.copy(), f.P_prior.copy()
            return gated_step(filtered_step(f.x, f.P, True), n_gated)
        f.update(y[rows], self.R[np.ix_(rows, rows)], self.model.function(f.sigmas_f)[:, rows])  # all points at once
        return gated_step(filtered_step(f.x, f.P, False, f), n_gated)
