"""Extended Kalman filter on the stereo reprojection (Krivokon 2011, App. I).

Model of :mod:`pipeline.estimators.base`; with ``H_k = ∂h/∂x`` at the prediction (the measurement
model's analytic ``jacobian``, zeros for the velocity)::

    x⁻ = A x,            P⁻ = A P Aᵀ + Q
    S = H P⁻ Hᵀ + R,      K = P⁻ Hᵀ S⁻¹
    x = x⁻ + K (y − h(x⁻)),  P = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ   (Joseph form, as filterpy)

Single tracks run filterpy's ``ExtendedKalmanFilter`` equations written out in numpy (a test holds
them equal to filterpy itself, driven directly, to 1e-9; the per-call checks filterpy makes cost
about as much as the arithmetic). ``run_batch`` runs the same
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
    config: KalmanConfig  # the validated settings, of this method's own type
    models_time_offset = True

    def reset(self) -> None:
        super().reset()
        cfg = self.config
        self.A = transition(self.dt)
        self.Q = white_noise_acceleration(self.dt, cfg.process_noise * cfg.q_scale)
        self.R = self.model.covar() * cfg.r_scale
        self._x = np.zeros(6)
        self._P = np.eye(6)
        self._I = np.eye(6)
        self._R_rows = {}  # the noise of each set of available rows
        self.y: np.ndarray | None = None  # the last update's innovation and its covariance (filterpy's names)
        self.S: np.ndarray | None = None

    @property
    def x(self) -> np.ndarray:
        return self._x

    @property
    def P(self) -> np.ndarray:
        return self._P

    def _step(self, y: np.ndarray) -> Step:
        """filterpy's ``ExtendedKalmanFilter`` predict/update written out in numpy (the same
        arithmetic, tested equal to it; faster without its per-call checks and reshapes)."""
        if not self.initialized:
            s = self.start(y)
            if s is None:
                return not_started()
            self._x, self._P = s.state.copy(), s.covariance.copy()
            self.initialized = True
            return filtered_step(self._x, self._P, False)
        A = self.A
        x = A @ self._x
        P = A @ self._P @ A.T + self.Q
        h_all, H_all = self.model.linearize(x)
        PHt = P @ H_all.T  # both cameras' S, shared by the gate and a full update
        S_all = H_all @ PHt + self.R
        n_gated = 0
        if self.config.gate > 0:
            y, n_gated, restart = self.gate(y, x, P, h_all, H_all, S_all)
            if restart is not None:
                self._x, self._P = restart.state.copy(), restart.covariance.copy()
                return gated_step(filtered_step(self._x, self._P, False), n_gated, True)
        rows = available_rows(y)
        if not len(rows):
            self._x, self._P = x, P
            return gated_step(Step(x[:3].copy(), x[3:].copy(), True, P), n_gated)
        x, P, r, S, nis = self._update(x, P, y, rows, h_all, H_all, PHt, S_all)
        self._x, self._P, self.y, self.S = x, P, r, S
        return gated_step(Step(x[:3].copy(), x[3:].copy(), False, P, r, S, known_nis=nis), n_gated)

    def _update(self, x, P, y, rows, h_all, H_all, PHt_all, S_all):
        """The Joseph-form update on the rows present: (x, P, innovation, S, NIS)."""
        if len(rows) == 4:
            H, r, R, PHt, S = H_all, y - h_all, self.R, PHt_all, S_all
        else:
            H, r = H_all[rows], y[rows] - h_all[rows]
            key = rows.tobytes()
            if key not in self._R_rows:
                self._R_rows[key] = self.R[np.ix_(rows, rows)]
            R = self._R_rows[key]
            PHt = P @ H.T
            S = H @ PHt + R
        Si = np.linalg.inv(S)
        K = PHt @ Si
        IKH = self._I - K @ H
        return x + K @ r, IKH @ P @ IKH.T + K @ R @ K.T, r, S, float(r @ Si @ r)

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
