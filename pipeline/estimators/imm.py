"""Interacting multiple model EKF for markers that cruise and manoeuvre (Blom & Bar-Shalom 1988;
Bar-Shalom, Li & Kirubarajan, *Estimation with Applications to Tracking and Navigation*, 2001, §11.6.6).

Two EKFs on the stereo reprojection share the constant-velocity transition ``A`` and differ in the
white-noise acceleration: ``Q₁`` (the EKF's ``process_noise``) for smooth motion and
``Q₂ = manoeuvre_q_scale · Q₁`` for manoeuvres. A Markov chain switches between them with
probability ``switch_probability`` per frame (``Π = [[1−p, p], [p, 1−p]]``). Each frame::

    c̄ⱼ = Σᵢ πᵢⱼ μᵢ,   μᵢ|ⱼ = πᵢⱼ μᵢ / c̄ⱼ                                    (mixing, eq. 11.6.6-6)
    x⁰ⱼ = Σᵢ μᵢ|ⱼ xᵢ,  P⁰ⱼ = Σᵢ μᵢ|ⱼ [Pᵢ + (xᵢ − x⁰ⱼ)(xᵢ − x⁰ⱼ)ᵀ]             (11.6.6-7, -8)
    xⱼ, Pⱼ, Λⱼ = EKF predict and update of (x⁰ⱼ, P⁰ⱼ) with Qⱼ;  Λⱼ = 𝒩(rⱼ; 0, Sⱼ)  (11.6.6-10…-14)
    μⱼ = Λⱼ c̄ⱼ / Σₗ Λₗ c̄ₗ                                                   (11.6.6-15)
    x = Σⱼ μⱼ xⱼ,  P = Σⱼ μⱼ [Pⱼ + (xⱼ − x)(xⱼ − x)ᵀ]                          (11.6.6-16, -17)

One frame's cameras are gated once, against the mixture's prediction (``Σⱼ c̄ⱼ A x⁰ⱼ``), and both
models update from the cameras kept, so the gate, its joint check of the cameras kept
(:func:`~pipeline.estimators.gating.joint_gate`) and the restarts are the EKF's:
a look-alike blob within one camera's own gate still moves the triangulated depth far more than
the marker can, and an update from it hands the
manoeuvre model the likelihood, whose wider gates then keep the look-alike (on the rendered
``lookalike`` clip the IMM ran 3.9 m off without the check). With ``manoeuvre_q_scale = 1`` the
two models are one EKF and so is the result wherever the joint check keeps every camera (tested).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from pipeline.estimators.base import Estimator, Step, Track, not_started, white_noise_acceleration
from pipeline.estimators.ekf import EKFEstimator
from pipeline.estimators.kalman_common import KalmanConfig, available_rows, filtered_step, gated_step
from pipeline.estimators.registration import register


class IMMConfig(KalmanConfig):
    """The EKF's settings, and the second model and the switching between the two."""

    manoeuvre_q_scale: float = Field(20.0, ge=1.0)
    """the manoeuvre model's process noise over the smooth model's (``process_noise``)"""
    switch_probability: float = Field(0.05, gt=0.0, lt=0.5)
    """probability per frame that the motion switches between smooth and manoeuvring"""


@register
class IMMEstimator(EKFEstimator):
    """IMM of two EKFs (smooth and manoeuvring motion); run when --methods names it."""

    name = "ekf_imm"
    joint_check = True  # without it the manoeuvre model keeps a look-alike
    default = False
    Config = IMMConfig
    config: IMMConfig
    models_time_offset = False

    def reset(self) -> None:
        super().reset()
        cfg, p = self.config, self.config.switch_probability
        q = cfg.process_noise * cfg.q_scale
        self.Qs = [white_noise_acceleration(self.dt, q), white_noise_acceleration(self.dt, q * cfg.manoeuvre_q_scale)]
        self.Pi = np.array([[1.0 - p, p], [p, 1.0 - p]])
        self.mu = np.array([0.5, 0.5])  # the chain's stationary distribution: no model favoured at the start
        self._xs = [np.zeros(6), np.zeros(6)]
        self._Ps = [np.eye(6), np.eye(6)]

    def _step(self, y: np.ndarray) -> Step:
        """Mix, gate against the mixture's prediction, update each model, reweigh, combine."""
        if not self.initialized:
            s = self.start(y)
            if s is None:
                return not_started()
            self._restart(s.state, s.covariance)
            self.initialized = True
            return self._imm_step(filtered_step(self._x, self._P, False))
        c, xs, Ps = self._predicted()
        x, P = _combine(c, xs, Ps)
        h_all, H_all = self.model.linearize(x)
        n_gated = 0
        if self.config.gate > 0:
            S_all = H_all @ P @ H_all.T + self.R
            y, n_gated, restart = self.gate(y, x, P, h_all, H_all, S_all)
            if restart is not None:
                self._restart(restart.state, restart.covariance)
                return gated_step(self._imm_step(filtered_step(self._x, self._P, False)), n_gated, True)
        rows = available_rows(y)
        if not len(rows):
            self._xs, self._Ps, self.mu, self._x, self._P = xs, Ps, c, x, P
            return gated_step(self._imm_step(Step(x[:3].copy(), x[3:].copy(), True, P)), n_gated)
        like = np.empty(2)
        for j in range(2):
            hj, Hj = self.model.linearize(xs[j])
            xs[j], Ps[j], r, S, nis = self._update(xs[j], Ps[j], y, rows, hj, Hj, Ps[j] @ Hj.T, Hj @ Ps[j] @ Hj.T + self.R)
            like[j] = -0.5 * (nis + np.linalg.slogdet(2 * np.pi * S)[1])
        w = c * np.exp(like - like.max())
        self.mu = w / w.sum()
        self._xs, self._Ps = xs, Ps
        self._x, self._P = _combine(self.mu, xs, Ps)
        r = y[rows] - h_all[rows]  # the mixture's innovation (what NIS and the consistency tables read)
        S = H_all[rows] @ P @ H_all[rows].T + self.R[np.ix_(rows, rows)]
        self.y, self.S = r, S
        step = Step(self._x[:3].copy(), self._x[3:].copy(), False, self._P, r, S, known_nis=float(r @ np.linalg.solve(S, r)))
        return gated_step(self._imm_step(step), n_gated)

    def _predicted(self) -> tuple[np.ndarray, list[np.ndarray], list[np.ndarray]]:
        """(c̄, each model's prediction from its mixed start, and covariance)."""
        c = self.mu @ self.Pi
        mix = self.Pi * self.mu[:, None] / c[None, :]  # μᵢ|ⱼ, column j
        xs, Ps = [], []
        for j in range(2):
            x0, P0 = _combine(mix[:, j], self._xs, self._Ps)
            xs.append(self.A @ x0)
            Ps.append(self.A @ P0 @ self.A.T + self.Qs[j])
        return c, xs, Ps

    def _restart(self, x: np.ndarray, P: np.ndarray) -> None:
        """Both models from one state (a start or a restart), no model favoured."""
        self._xs, self._Ps = [x.copy(), x.copy()], [P.copy(), P.copy()]
        self.mu = np.array([0.5, 0.5])
        self._x, self._P = x.copy(), P.copy()

    def _imm_step(self, step: Step) -> Step:
        """The step with the manoeuvre model's probability in ``extra``."""
        step.extra["manoeuvre_probability"] = float(self.mu[1])
        return step

    def run(self, Y: np.ndarray) -> Track:
        """Step by step (no compiled core)."""
        return Estimator.run(self, Y)

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        return Estimator.run_batch(self, Y)


def _combine(w: np.ndarray, xs: list[np.ndarray], Ps: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The moment-matched Gaussian of a mixture: ``Σ wᵢ xᵢ`` and ``Σ wᵢ [Pᵢ + dᵢ dᵢᵀ]``."""
    x = w[0] * xs[0] + w[1] * xs[1]
    d0, d1 = xs[0] - x, xs[1] - x
    return x, w[0] * (Ps[0] + np.outer(d0, d0)) + w[1] * (Ps[1] + np.outer(d1, d1))
