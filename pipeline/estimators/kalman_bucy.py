"""Continuous-time Kalman–Bucy filter for the four-point target (Soifer et al. §3; SPEC §4.8).

Per channel (α, then z) the model is ``ẍ = a ẋ + q``; with feedback ``L`` the closed loop is
``A = [[0, 1], [−L₀, a − L₁]]`` (the paper: a_α = −1, L = [1, 0.73] → [[0, 1], [−1, −1.73]]).
State ``x = [α, α̇, z, ż]``, measurement ``u = C x + v`` with ``C = [[1,0,0,0],[0,0,1,0]]``::

    dx̂/dt = A x̂ + K (u − C x̂),          K = P Cᵀ R⁻¹
    steady state:  A P + P Aᵀ + G Q Gᵀ − P Cᵀ R⁻¹ C P = 0   (scipy.linalg.solve_continuous_are)
    time-varying:  dP/dt = A P + P Aᵀ + G Q Gᵀ − P Cᵀ R⁻¹ C P,   P(0) = P₀

``R`` is the measurement noise *density*: samples of variance σ² every dt act like a density
σ²·dt. Integration between samples (measurement held over the step): ``euler`` — the paper's
first-order differences — or ``exact`` — the matrix exponential of the closed loop ``A − K C``
with its input integral (Van Loan's block exponential), and RK4 sub-steps for the Riccati
equation. The channels are independent in this model, so "separate" and "joint" coincide
numerically; the joint 4-state form is what runs.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from pydantic import Field
from scipy.linalg import expm, solve_continuous_are

from pipeline.errors import StereotrackError
from pipeline.estimators.four_point import TargetConfig, TargetEstimator, register_target

C4 = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
G4 = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 0.0], [0.0, 1.0]])


def channel_matrix(a: float, feedback: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """``[[0, 1], [−L₀, a − L₁]]``: ``ẍ = a ẋ − L x`` in state form."""
    return np.array([[0.0, 1.0], [-feedback[0], a - feedback[1]]])


def block_diag2(A1: np.ndarray, A2: np.ndarray) -> np.ndarray:
    A = np.zeros((4, 4))
    A[:2, :2], A[2:, 2:] = A1, A2
    return A


def observability_rank(A: np.ndarray, C: np.ndarray) -> int:
    """Rank of ``[C; CA; …; CA^{n−1}]`` (lecture 001's test)."""
    n = A.shape[0]
    O = np.vstack([C @ np.linalg.matrix_power(A, k) for k in range(n)])
    return int(np.linalg.matrix_rank(O))


def check_model(A: np.ndarray, C: np.ndarray) -> None:
    """Clear errors for an unobservable model or an unstable closed loop (the paper's conditions)."""
    r = observability_rank(A, C)
    if r < A.shape[0]:
        raise StereotrackError(f"model is not observable (rank {r} < {A.shape[0]}): the filter cannot converge")


def steady_state_gain(A: np.ndarray, C: np.ndarray, GQG: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K, P) from the algebraic Riccati equation; an unstable ``A − K C`` is an error."""
    try:
        P = solve_continuous_are(A.T, C.T, GQG, R)
    except (np.linalg.LinAlgError, ValueError) as exc:
        raise StereotrackError(f"Riccati equation has no stabilising solution ({exc})") from None
    K = P @ C.T @ np.linalg.inv(R)
    if np.max(np.linalg.eigvals(A - K @ C).real) >= 0:
        raise StereotrackError("the steady-state filter A − K C is not asymptotically stable")
    return K, P


def riccati_rhs(P: np.ndarray, A: np.ndarray, C: np.ndarray, GQG: np.ndarray, Rinv: np.ndarray) -> np.ndarray:
    return A @ P + P @ A.T + GQG - P @ C.T @ Rinv @ C @ P


def riccati_step(P: np.ndarray, dt: float, A, C, GQG, Rinv, method: Literal["euler", "exact"], substeps: int = 8) -> np.ndarray:
    """Advance the Riccati differential equation by dt (Euler, or RK4 sub-steps)."""
    if method == "euler":
        return P + dt * riccati_rhs(P, A, C, GQG, Rinv)
    h = dt / substeps
    for _ in range(substeps):
        k1 = riccati_rhs(P, A, C, GQG, Rinv)
        k2 = riccati_rhs(P + h / 2 * k1, A, C, GQG, Rinv)
        k3 = riccati_rhs(P + h / 2 * k2, A, C, GQG, Rinv)
        k4 = riccati_rhs(P + h * k3, A, C, GQG, Rinv)
        P = P + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return 0.5 * (P + P.T)


def filter_step(x: np.ndarray, u: np.ndarray | None, dt: float, A, K, C, method: Literal["euler", "exact"]) -> np.ndarray:
    """Integrate ``dx̂/dt = A x̂ + K (u − C x̂)`` over dt with u held (None: model only)."""
    if u is None:
        return x + dt * (A @ x) if method == "euler" else expm(A * dt) @ x
    F = A - K @ C
    if method == "euler":
        return x + dt * (F @ x + K @ u)
    n, m = F.shape[0], K.shape[1]
    M = np.zeros((n + m, n + m))
    M[:n, :n], M[:n, n:] = F, K
    E = expm(M * dt)  # [[e^{F dt}, ∫ e^{F s} ds K], [0, I]]
    return E[:n, :n] @ x + E[:n, n:] @ u


class KalmanBucyConfig(TargetConfig):
    """Channel models, noise, gain and integration of the Kalman–Bucy filter."""

    a_alpha: float = -1.0
    alpha_feedback: tuple[float, float] = (1.0, 0.73)
    a_z: float = -0.2
    z_feedback: tuple[float, float] = (0.0, 0.0)
    #: process-noise densities of the α̈ and z̈ inputs
    q_alpha: float = Field(0.05, ge=0)
    q_z: float = Field(0.05, ge=0)
    #: measurement noise std of α (rad) and z (m) per sample
    sigma_alpha: float = Field(0.02, gt=0)
    sigma_z: float = Field(0.01, gt=0)
    gain: Literal["steady", "riccati"] = "riccati"
    integration: Literal["euler", "exact"] = "exact"
    #: initial std of the rates (α̇ rad/s, ż m/s); the levels start from the first measurement
    sigma_rate0: float = Field(0.5, gt=0)


@register_target
class KalmanBucyEstimator(TargetEstimator):
    """Four-point measurement → Kalman–Bucy filter on [α, α̇, z, ż]."""

    name = "kalman_bucy"
    Config = KalmanBucyConfig

    def reset(self) -> None:
        super().reset()
        c: KalmanBucyConfig = self.config  # type: ignore[assignment]
        self.A = block_diag2(channel_matrix(c.a_alpha, c.alpha_feedback), channel_matrix(c.a_z, c.z_feedback))
        check_model(self.A, C4)
        self.GQG = G4 @ np.diag([c.q_alpha, c.q_z]) @ G4.T
        self.R = np.diag([c.sigma_alpha**2, c.sigma_z**2]) * self.dt  # density of sampled noise
        self.Rinv = np.linalg.inv(self.R)
        if c.gain == "steady":
            self.K, self.P = steady_state_gain(self.A, C4, self.GQG, self.R)
        self.x = np.zeros(4)

    def step(self, obs: np.ndarray) -> tuple[float, float, np.ndarray, bool]:
        c: KalmanBucyConfig = self.config  # type: ignore[assignment]
        m = self.measure(obs)
        if not self.initialized:
            if not m.ok:
                return math.nan, math.nan, np.full(3, math.nan), True
            self.x = np.array([m.alpha, 0.0, m.distance, 0.0])
            if c.gain == "riccati":
                self.P = np.diag([c.sigma_alpha**2, c.sigma_rate0**2, c.sigma_z**2, c.sigma_rate0**2])
                self.K = self.P @ C4.T @ self.Rinv
            self.initialized = True
            self._center_dir = m.center / m.center[2]
            return m.alpha, m.distance, m.center, False
        u = np.array([m.alpha, m.distance]) if m.ok else None
        if c.gain == "riccati":
            if u is not None:
                self.K = self.P @ C4.T @ self.Rinv
                self.P = riccati_step(self.P, self.dt, self.A, C4, self.GQG, self.Rinv, c.integration)
            else:  # no measurement: the covariance grows with the model only
                self.P = riccati_step(self.P, self.dt, self.A, np.zeros_like(C4), self.GQG, self.Rinv, c.integration)
        self.x = filter_step(self.x, u, self.dt, self.A, self.K, C4, c.integration)
        if m.ok:
            self._center_dir = m.center / m.center[2]
        return float(self.x[0]), float(self.x[2]), self._center_dir * self.x[2], u is None
