"""The alpha-beta(-gamma) filter over independent channels: the fixed-gain tracker behind the
``alphabeta`` estimators and the meanshift detector's window prediction (Kalata, "The tracking
index", IEEE Trans. AES 20(2), 1984)."""

from __future__ import annotations

import numpy as np


class ABFilter:
    """Alpha-beta(-gamma) filter over independent channels (a vector state per channel)."""

    def __init__(self, x0: np.ndarray, dt: float, alpha: float, beta: float, gamma: float | None = None) -> None:
        self.x = np.asarray(x0, dtype=float).copy()
        self.v = np.zeros_like(self.x)
        self.a = np.zeros_like(self.x)
        self.dt, self.alpha, self.beta, self.gamma = dt, alpha, beta, gamma

    def predict(self) -> np.ndarray:
        dt = self.dt
        if self.gamma is None:
            self.x = self.x + self.v * dt
        else:
            self.x = self.x + self.v * dt + 0.5 * self.a * dt * dt
            self.v = self.v + self.a * dt
        return self.x

    def correct(self, z: np.ndarray) -> None:
        """Correct the channels whose measurement is finite."""
        ok = np.isfinite(z)
        with np.errstate(invalid="ignore"):
            r = np.where(ok, z - self.x, 0.0)  # a missing channel's NaN never reaches the state
        self.x = self.x + self.alpha * r
        self.v = self.v + self.beta * r / self.dt
        if self.gamma is not None:
            self.a = self.a + 2.0 * self.gamma * r / self.dt**2
