"""Alpha-beta and alpha-beta-gamma filters (lecture 002; SPEC §4.6), on triangulated 3-D positions
or on each camera's image coordinates (then triangulated). Tracks start through the shared
:class:`~pipeline.estimators.base.Initiator` (position and velocity; in image space their
projection ``h(p₀)`` and rate ``J(p₀) v₀``).

With time step ``dt`` (filterpy's ``GHFilter``/``GHKFilter`` convention; the lecture has dt = 1)::

    predict  x̂ ← x̂ + v̂ dt (+ â dt²/2),   v̂ ← v̂ (+ â dt)
    residual r = x − x̂
    correct  x̂ += α r,   v̂ += β r / dt   (â += 2γ r / dt²)

Written here (vectorised, any number of channels) rather than through filterpy's GH filters
because a tracker must predict through missing measurements, which those classes cannot; a test
checks agreement with filterpy on complete data.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from pydantic import Field

from pipeline.estimators.base import NAN3, Estimator, EstimatorConfig, Step, not_started, register


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
        r = np.where(ok, np.nan_to_num(z) - self.x, 0.0)
        self.x = self.x + self.alpha * r
        self.v = self.v + self.beta * r / self.dt
        if self.gamma is not None:
            self.a = self.a + 2.0 * self.gamma * r / self.dt**2


class AlphaBetaConfig(EstimatorConfig):
    alpha: float = Field(0.5, gt=0, le=1)
    beta: float = Field(0.1, ge=0, le=2)
    #: filter the triangulated 3-D points ("3d") or each camera's pixels, then triangulate ("image")
    space: Literal["3d", "image"] = "3d"


class AlphaBetaGammaConfig(AlphaBetaConfig):
    gamma: float = Field(0.01, ge=0, le=2)


@register
class AlphaBetaEstimator(Estimator):
    """Alpha-beta filter on triangulated 3-D positions or on image coordinates."""

    name = "alphabeta"
    Config = AlphaBetaConfig

    def _gamma(self) -> float | None:
        return None

    def reset(self) -> None:
        super().reset()
        self.f: ABFilter | None = None

    def _step(self, y: np.ndarray) -> Step:
        cfg: AlphaBetaConfig = self.config  # type: ignore[assignment]
        image = cfg.space == "image"
        if self.f is None:
            s = self.start(y)
            if s is None:
                return not_started()
            p0, v0 = s.state[:3], s.state[3:]
            if image:  # the start in pixels: h(p0), and its rate J(p0) v0
                self.f = ABFilter(self.model.function(p0), self.dt, cfg.alpha, cfg.beta, self._gamma())
                self.f.v = self.rig.jacobian(p0) @ v0
            else:
                self.f = ABFilter(p0, self.dt, cfg.alpha, cfg.beta, self._gamma())
                self.f.v = v0.copy()
            self.initialized = True
            have = True
        else:
            z = y if image else self.model.inverse_function(y[None])[0]
            self.f.predict()
            self.f.correct(z)
            have = bool(np.isfinite(z).any())
        if image:
            return Step(self.model.inverse_function(self.f.x[None])[0], NAN3.copy(), predicted=not have)
        return Step(self.f.x.copy(), self.f.v.copy(), predicted=not have)


@register
class AlphaBetaGammaEstimator(AlphaBetaEstimator):
    """Alpha-beta-gamma filter (alpha-beta plus an acceleration channel)."""

    name = "alphabetagamma"
    Config = AlphaBetaGammaConfig

    def _gamma(self) -> float | None:
        return self.config.gamma  # type: ignore[attr-defined]
