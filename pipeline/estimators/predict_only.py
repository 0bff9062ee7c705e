"""``predict_only``: the baseline every adaptive method is reported beside — the same start
(:class:`~pipeline.estimators.base.Initiator`, so the same ``init`` settings give the same state),
then the motion model alone, ``x_k = A x_{k−1}``, with no measurement update. A method that does not
beat it has not acted."""

from __future__ import annotations

import numpy as np

from pipeline.estimators.base import Estimator, EstimatorConfig, Step, not_started
from pipeline.estimators.registration import register


class PredictOnlyConfig(EstimatorConfig):
    """``static``: hold the start position (the baseline of position-only methods, velocity 0)."""

    static: bool = False
    """hold the start position (velocity 0) instead of carrying the start's velocity"""


@register
class PredictOnlyEstimator(Estimator):
    """Start as configured, then constant-velocity prediction only (no update): the baseline."""

    name = "predict_only"
    any_cameras = True
    Config = PredictOnlyConfig
    config: PredictOnlyConfig  # the validated settings, of this method's own type

    def reset(self) -> None:
        super().reset()
        self.p = np.full(3, np.nan)
        self.v = np.zeros(3)

    def _step(self, y: np.ndarray) -> Step:
        if not self.initialized:
            s = self.start(y)
            if s is None:
                return not_started()
            self.p = s.state[:3].copy()
            self.v = np.zeros(3) if self.config.static else s.state[3:].copy()
            self.initialized = True
            return Step(self.p.copy(), self.v.copy())
        self.p = self.p + self.v * self.dt
        return Step(self.p.copy(), self.v.copy(), predicted=True)
