"""Frame-by-frame stereo triangulation, the inverse of the measurement model
(:func:`pipeline.core.camera.triangulate`, the homogeneous DLT; thesis ch. I; Hartley & Zisserman §12.2).

The estimator holds no state beyond the last fix; every other method starts from the same
triangulation through :class:`pipeline.estimators.base.Initiator`.
"""

from __future__ import annotations

import numpy as np

from pipeline.core.rig import triangulate_robust
from pipeline.estimators.base import NAN3, Estimator, Step
from pipeline.estimators.gating import GATE_FLOOR_PX, camera_gate, plausible_residual, reprojection_residual
from pipeline.estimators.registration import register


@register
class TriangulationEstimator(Estimator):
    """Frame-by-frame DLT triangulation, no motion model and no memory.

    Through a gap it holds the last point (flagged ``predicted``) so that it never emits NaN after
    its first fix. A frame whose reprojection residual is implausible for the pixel noise (χ², one
    degree of freedom, at ``gate``: a detection off the epipolar line) is marked gated and
    treated as a gap. With more than two cameras a frame keeps the largest set of cameras that
    agree (each within the per-camera χ² gate, two degrees of freedom, of a noise of
    ``max(pixel_sigma, 1 px)``): one camera's outlier drops that camera, not the frame
    (:func:`~pipeline.core.rig.triangulate_robust`): ``extra["gated"]`` counts the cameras dropped
    in a frame, ``extra["dropped:<camera>"]`` says which (``metrics.json``: ``dropped_cameras``)."""

    name = "triangulation"
    any_cameras = True

    def reset(self) -> None:
        super().reset()
        self.last = NAN3.copy()
        self.max_residual = plausible_residual(self.config.pixel_sigma, self.config.gate)

    def _fix(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Triangulations (…×3, NaN where implausible) and which frames were gated (…)."""
        if self.rig.n > 2:
            X, gated, _ = self._fix_views(Y)
            return X, gated
        X = self.model.inverse_function(Y)
        gated = np.all(np.isfinite(X), axis=-1) & (reprojection_residual(self.model, X, Y) > self.max_residual)
        X[gated] = np.nan
        return X, gated

    def _fix_views(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """N cameras: the robust subset triangulation; (points, frames gated, cameras dropped:
        observing cameras left out of the frame's point, …×N)."""
        shape = Y.shape[:-1]
        limit = max(self.config.pixel_sigma, GATE_FLOOR_PX) * float(np.sqrt(camera_gate(self.config.gate)))
        X, used = triangulate_robust(self.rig, Y.reshape(-1, Y.shape[-1]), limit)
        observed = np.isfinite(Y.reshape(-1, self.rig.n, 2)).all(axis=2)
        gated = (observed.sum(axis=1) >= 2) & ~np.isfinite(X).all(axis=1)
        return X.reshape(*shape, 3), gated.reshape(shape), (observed & ~used).reshape(*shape, self.rig.n)

    def _step(self, y: np.ndarray) -> Step:
        if self.rig.n > 2:
            return self._step_views(y)
        Xs, gated_all = self._fix(y[None])
        X, gated = Xs[0], bool(gated_all[0])
        if np.all(np.isfinite(X)):
            self.last = X
            self.initialized = True
            return Step(X, NAN3.copy(), extra={"gated": 0.0})
        return Step(self.last.copy(), NAN3.copy(), predicted=True, extra={"gated": float(gated)})

    def _step_views(self, y: np.ndarray) -> Step:
        """:meth:`_step` over N cameras, with the cameras dropped in this frame."""
        Xs, _, dropped_all = self._fix_views(y[None])
        X, dropped = Xs[0], dropped_all[0]
        extra = {"gated": float(dropped.sum()), **{f"dropped:{n}": float(d) for n, d in zip(self.rig.names, dropped,
                                                                                          strict=True)}}
        if np.all(np.isfinite(X)):
            self.last = X
            self.initialized = True
            return Step(X, NAN3.copy(), extra=extra)
        return Step(self.last.copy(), NAN3.copy(), predicted=True, extra=extra)

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        """All tracks triangulated at once; gaps hold the last fix as :meth:`step` does."""
        X = self._fix(np.asarray(Y, dtype=float))[0]
        ok = np.all(np.isfinite(X), axis=-1)
        last = np.maximum.accumulate(np.where(ok, np.arange(X.shape[1]), -1), axis=1)
        out = np.take_along_axis(X, np.maximum(last, 0)[..., None], axis=1)
        out[last < 0] = np.nan
        return out
