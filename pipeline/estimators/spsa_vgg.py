"""The unmodified nonstationary SPSA of Vakhitov, Granichin & Gurevich (2009): the
baseline Algorithm 1 improves on. State = position only; Δ_n components ±1/√3::

    x_{2n−1} = θ_{2n−2} − βΔ_n,   x_{2n} = θ_{2n−2} + βΔ_n
    θ_{2n} = θ_{2n−2} − (α/2β) Δ_n (z_{2n} − z_{2n−1}),   θ_{2n−1} = θ_{2n−2}

with ``z_j = ‖h(x_j) − y_j‖²`` in normalized image coordinates. It knows nothing of the motion, so
it "latches" behind a moving point even without noise (thesis Fig. 3). As published it has no
projection rule (``th: null``, the default); setting ``th`` applies Algorithm 1's ``|d| ≤ th``.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.estimators.base import NAN3, Estimator, Start, Step
from pipeline.estimators.registration import register
from pipeline.estimators.spsa import SPSAConfig, SPSAEstimator, _cost


class SPSAVGGConfig(SPSAConfig):
    """Algorithm 1's settings, without the projection rule by default (the 2009 algorithm)."""

    th: float | None = None
    """projection threshold on |d|; None (the 2009 algorithm) switches the rule off"""


@register
class SPSAVGGEstimator(SPSAEstimator):
    """Position-only SPSA without motion prediction."""

    name = "spsa_vgg"
    Config = SPSAVGGConfig
    config: SPSAVGGConfig  # the validated settings, of this method's own type
    state_dim = 3

    def _begin(self, s: Start) -> None:
        self.theta = s.state[:3].tolist()
        self.initialized = True
        self._phase = 0

    def _out(self, th: list[float], predicted: bool) -> Step:
        return Step(np.array(th[:3]), NAN3.copy(), predicted=predicted)

    def _iterate(self, yn: tuple, ok_l: bool, ok_r: bool) -> tuple[list[float], bool]:
        cfg = self.config
        t = self.theta
        b, th = cfg.beta, self._th
        if self._phase == 0:
            self._delta = self._draw_delta()
            self._y_odd = (yn, ok_l, ok_r)
            self._phase = 1
            return list(t), not (ok_l or ok_r)  # θ_{2n−1} = θ_{2n−2}
        self._phase = 0
        D = self._delta
        yo, ol, orr = self._y_odd
        use_l, use_r = ok_l and ol, ok_r and orr
        if use_l or use_r:
            z_odd = _cost(t[0] - b * D[0], t[1] - b * D[1], t[2] - b * D[2], yo, use_l, use_r, self._cams)
            z_even = _cost(t[0] + b * D[0], t[1] + b * D[1], t[2] + b * D[2], yn, use_l, use_r, self._cams)
            d = max(-th, min(th, (z_even - z_odd) / (2 * b)))
            if math.isfinite(d):
                self.theta = [t[i] - cfg.alpha * d * D[i] for i in range(3)]
        return list(self.theta), not (use_l or use_r)

    def _path(self, frames: int):
        """Always the interpreted loop: the compiled core is Algorithm 1's, not this iteration's."""
        return self._loop

    run_batch = Estimator.run_batch
