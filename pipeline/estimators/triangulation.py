"""Stereo triangulation by the homogeneous DLT (thesis ch. I; Hartley & Zisserman §12.2).

For observations ``(u1, v1)``, ``(u2, v2)`` and cameras ``P1``, ``P2`` with rows ``pᵢʲᵀ``::

    A = [u1 p1³ᵀ − p1¹ᵀ;  v1 p1³ᵀ − p1²ᵀ;  u2 p2³ᵀ − p2¹ᵀ;  v2 p2³ᵀ − p2²ᵀ]

and the point is the right singular vector of ``A`` for its smallest singular value. Rows are scaled
to unit norm (conditioning only; the solution of a consistent system is unchanged).

Unit covariance: that row scaling weights the equations differently when ``T`` is in millimetres
rather than metres (the last column of ``P2`` grows 1000×), so a noisy solution would depend on the
calibration's unit. The DLT is therefore solved for ``X / b`` with ``b`` the baseline (``T/b`` is
unit-free) and scaled back: scaling ``T`` by ``s`` scales every point by exactly ``s``.
"""

from __future__ import annotations

import numpy as np

from pipeline.camera import StereoRig
from pipeline.estimators.base import NAN3, Estimator, Step, register


def triangulate(rig: StereoRig, Y: np.ndarray) -> np.ndarray:
    """DLT triangulation of N stereo observations (N×4 pixels) → N×3; NaN where a camera is missing."""
    Y = np.asarray(Y, dtype=float).reshape(-1, 4)
    b = rig.baseline
    P1 = rig.left.K @ np.hstack([rig.left.R, rig.left.t.reshape(3, 1) / b])
    P2 = rig.right.K @ np.hstack([rig.right.R, rig.right.t.reshape(3, 1) / b])
    A = np.empty((len(Y), 4, 4))
    A[:, 0] = Y[:, 0, None] * P1[2] - P1[0]
    A[:, 1] = Y[:, 1, None] * P1[2] - P1[1]
    A[:, 2] = Y[:, 2, None] * P2[2] - P2[0]
    A[:, 3] = Y[:, 3, None] * P2[2] - P2[1]
    ok = np.all(np.isfinite(Y), axis=1)
    out = np.full((len(Y), 3), np.nan)
    if not ok.any():
        return out
    A = A[ok] / np.linalg.norm(A[ok], axis=2, keepdims=True)
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    X[~np.isfinite(X).all(axis=1)] = np.nan
    out[ok] = X * b
    return out


@register
class TriangulationEstimator(Estimator):
    """Frame-by-frame DLT triangulation: no model, no memory. Through a gap it holds the last
    point (flagged ``predicted``) so that it never emits NaN after its first fix."""

    name = "triangulation"

    def reset(self) -> None:
        super().reset()
        self.last = NAN3.copy()

    def _step(self, y: np.ndarray) -> Step:
        X = triangulate(self.rig, y[None])[0]
        if np.all(np.isfinite(X)):
            self.last = X
            self.initialized = True
            return Step(X, NAN3.copy())
        return Step(self.last.copy(), NAN3.copy(), predicted=True)

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        Y = np.asarray(Y, dtype=float)
        return triangulate(self.rig, Y.reshape(-1, 4)).reshape(*Y.shape[:-1], 3)
