"""An example third-party estimator for stereotrack: exponential smoothing of triangulated points.

    p̂_k = p̂_{k−1} + a (X_k − p̂_{k−1}),   X_k = h⁻¹(y_k)  (the measurement model's triangulation)

It starts where every stereotrack point method starts (the shared initiator), holds its estimate
through frames without a triangulation, and then works in `estimate`, `run`, `batch`, reports
and recordings like a built-in method.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from pipeline.estimators import Estimator, EstimatorConfig, Step


class SmoothingConfig(EstimatorConfig):
    """Settings, given with `--config`: `smoothed_triangulation: {smoothing: 0.3}`."""

    #: weight a of the newest triangulation (1 = plain triangulation)
    smoothing: float = Field(0.5, gt=0, le=1)


class SmoothedTriangulationEstimator(Estimator):
    """Exponentially smoothed triangulation (example plugin)."""

    name = "smoothed_triangulation"
    kind = "point"
    Config = SmoothingConfig

    def reset(self) -> None:
        super().reset()
        self.p = np.full(3, np.nan)

    def _step(self, y: np.ndarray) -> Step:
        nan3 = np.full(3, np.nan)
        if not self.initialized:
            start = self.start(y)  # the shared initiator (first triangulation, or a line fit)
            if start is None:
                return Step(nan3, nan3.copy(), predicted=True)
            self.p, self.initialized = start.state[:3].copy(), True
            return Step(self.p.copy(), nan3)
        X = self.model.inverse_function(y[None])[0]
        if not np.all(np.isfinite(X)):
            return Step(self.p.copy(), nan3, predicted=True)
        self.p = self.p + self.config.smoothing * (X - self.p)
        return Step(self.p.copy(), nan3)
