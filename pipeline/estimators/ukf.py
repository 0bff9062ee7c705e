"""Unscented Kalman filter (``filterpy.kalman.UnscentedKalmanFilter``) on the same model as the EKF:
sigma points (Van der Merwe's scaled set) through ``x ↦ A x`` and ``h``; no Jacobian needed."""

from __future__ import annotations

import numpy as np
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from pipeline.estimators.base import NAN3, Estimator, Step, register, transition, white_noise_acceleration
from pipeline.estimators.kalman_common import KalmanConfig, available_rows, initial_covariance


@register
class UKFEstimator(Estimator):
    """UKF with white-noise-acceleration ``Q`` and ``R = σ² I``."""

    name = "ukf"
    Config = KalmanConfig

    def reset(self) -> None:
        super().reset()
        cfg: KalmanConfig = self.config  # type: ignore[assignment]
        A = transition(self.dt)
        self.R = np.eye(4) * (cfg.pixel_sigma**2 * cfg.r_scale)
        points = MerweScaledSigmaPoints(6, alpha=0.3, beta=2.0, kappa=-3.0)
        self.filter = UnscentedKalmanFilter(
            dim_x=6, dim_z=4, dt=self.dt, hx=lambda x: self.rig.project(x[:3]), fx=lambda x, dt: A @ x, points=points
        )
        self.filter.Q = white_noise_acceleration(self.dt, cfg.process_noise * cfg.q_scale)
        self.filter.R = self.R

    def _step(self, y: np.ndarray) -> Step:
        f = self.filter
        if not self.initialized:
            x0 = self.initial_state(y)
            if x0 is None:
                return Step(NAN3.copy(), NAN3.copy(), predicted=True)
            P0 = initial_covariance(self.config)  # type: ignore[arg-type]
            if self.config.init.mode == "triangulation":
                # start from the triangulation's own uncertainty: sigma points spread over metres
                # would leave the region where h is nearly linear
                J = self.rig.jacobian(x0[:3])
                cfg: KalmanConfig = self.config  # type: ignore[assignment]
                P0[:3, :3] = cfg.pixel_sigma**2 * np.linalg.inv(J.T @ J)
            f.x, f.P = x0, P0
            self.initialized = True
            # the start state is this frame's triangulation: no update on top of it
            return Step(x0[:3].copy(), x0[3:].copy(), covariance=f.P.copy())
        f.predict()
        rows = available_rows(y)
        if len(rows):
            f.update(y[rows], R=self.R[np.ix_(rows, rows)], hx=lambda x: self.rig.project(x[:3])[rows])
        else:
            f.x, f.P = f.x_prior.copy(), f.P_prior.copy()
        x = f.x
        return Step(x[:3].copy(), x[3:].copy(), covariance=f.P.copy(), predicted=not len(rows))
