"""The practitioner's baseline for the four-point target: planar PnP then a discrete Kalman filter.

``cv2.solvePnPGeneric(..., SOLVEPNP_IPPE_SQUARE)`` returns both poses of a planar target consistent with
the image (the well-known two-fold ambiguity); we keep the one nearer the previous frame's pose
(the lower reprojection error on the first frame), convert it to α and z in the left camera's
frame, and filter [α, α̇, z, ż] with a linear Kalman filter (:mod:`~pipeline.estimators.filters`, filterpy's
equations) on the same second-order channel models as the Kalman–Bucy filter, discretised exactly (``expm`` / Van Loan).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from pipeline.core.lazy import lazy_module
from pipeline.core.linalg import block_diag
from pipeline.estimators.base import Step, expm
from pipeline.estimators.filters import KalmanFilter
from pipeline.estimators.four_point import (
    CAMERA_INDICES,
    TargetEstimator,
    TargetMeasurement,
    alpha_from_normal,
    camera_to_left,
)
from pipeline.estimators.kalman_bucy import C4, G4, KalmanBucyConfig, channel_matrix, propagated_variance
from pipeline.estimators.registration import register

if TYPE_CHECKING:
    import cv2
else:
    cv2 = lazy_module("cv2")  # imported on first use: --help and `methods` need no OpenCV

#: IPPE_SQUARE wants the corners of a square of side s = R√2 in its own order; our points
#: 1 (up), 2 (right), 3 (down), 4 (left) are that square turned by 45°: pass them as 4, 1, 2, 3.
SQUARE_ORDER = [3, 0, 1, 2]
#: the 2–4 axis (towards point 2) in the square's frame
AXIS_IN_SQUARE = np.array([1.0, -1.0, 0.0]) / np.sqrt(2.0)


def object_points(R: float) -> np.ndarray:
    """Square corners for ``SOLVEPNP_IPPE_SQUARE``; the square's z axis faces the camera."""
    h = R / np.sqrt(2.0)
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def van_loan(A: np.ndarray, GQG: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretisation (F, Q_d) of ``ẋ = A x + w`` with white-noise density GQGᵀ (Van Loan,
    "Computing integrals involving the matrix exponential", IEEE TAC 23(3), 1978). filterpy's
    ``van_loan_discretization`` takes G with the density G Gᵀ, which would need a square root of
    this singular GQGᵀ; this takes the density itself, through the cached exponential."""
    n = A.shape[0]
    M = np.zeros((2 * n, 2 * n))
    M[:n, :n], M[:n, n:], M[n:, n:] = -A, GQG, A.T
    E = expm(M * dt)
    F = E[n:, n:].T
    return F, F @ E[:n, n:]


@register
class PnPKFEstimator(TargetEstimator):
    """IPPE-square planar PnP per camera (averaged over cameras) → discrete KF on [α, α̇, z, ż]."""

    name = "pnp_kf"
    models_target_dynamics = True
    startup_imports = ("scipy", "cv2")  # scipy's expm kernel for the transition; OpenCV's PnP
    Config = KalmanBucyConfig
    config: KalmanBucyConfig  # the validated settings, of this method's own type

    def reset(self) -> None:
        super().reset()
        c = self.config
        A = block_diag(channel_matrix(c.a_alpha, c.alpha_feedback), channel_matrix(c.a_z, c.z_feedback))
        F, Qd = van_loan(A, G4 @ np.diag([c.q_alpha, c.q_z]) @ G4.T, self.dt)
        self.kf = KalmanFilter(dim_x=4, dim_z=2)
        self.kf.F, self.kf.Q, self.kf.H = F, Qd, C4
        self.prev_normals: dict[int, np.ndarray] = {}

    def pnp(self, obs: np.ndarray) -> TargetMeasurement:
        """α, z and centre from PnP on each available camera, averaged in the left frame."""
        views = self.views(obs)
        if not views:
            return TargetMeasurement(math.nan, math.nan, np.full(3, math.nan), math.nan, "no PnP solution")
        return TargetMeasurement(float(np.mean([v.alpha for v in views])), float(np.mean([v.distance for v in views])),
                                 np.mean([v.center for v in views], axis=0), math.nan)

    def views(self, obs: np.ndarray) -> list[TargetMeasurement]:
        """Each available camera's PnP: of IPPE's two poses, the one whose normal is nearest the
        camera's previous one (the lower reprojection error on its first frame)."""
        c = self.config
        out = []
        for ci in CAMERA_INDICES[c.cameras]:
            cands = self._poses(obs[:, 2 * ci : 2 * ci + 2], ci)
            if not cands:
                continue
            prev = self.prev_normals.get(ci)
            best = max(cands, key=lambda cd: float(cd[2] @ prev)) if prev is not None else min(cands, key=lambda cd: cd[3])
            self.prev_normals[ci] = best[2]
            alpha, _ = alpha_from_normal(best[2], best[0] @ AXIS_IN_SQUARE)
            out.append(TargetMeasurement(alpha, float(best[1][2]), best[1], math.nan))
        return out

    def _poses(self, pts: np.ndarray, ci: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray, float]]:
        """IPPE-square's poses of the plate in camera ``ci`` as (rotation, centre, normal, error) in
        the left camera's frame; none without all four points or a solution."""
        if not np.all(np.isfinite(pts)):
            return []
        cam = self.rig.cameras[ci]
        try:
            n_sol, rvecs, tvecs, errs = cv2.solvePnPGeneric(
                object_points(self.config.radius), np.ascontiguousarray(pts[SQUARE_ORDER]), cam.K, None,
                flags=cv2.SOLVEPNP_IPPE_SQUARE,
            )
        except cv2.error:
            return []
        to_left = camera_to_left(self.rig, ci)
        cands = []
        for rv, tv, err in zip(rvecs, tvecs, np.ravel(errs), strict=True) if n_sol else ():
            Rt, _ = cv2.Rodrigues(rv)
            Rl = to_left[:3, :3] @ Rt
            center = to_left[:3, :3] @ tv.ravel() + to_left[:3, 3]
            cands.append((Rl, center, Rl[:, 2], float(err)))  # the normal, x × y: towards the camera
        return cands

    def _step(self, obs: np.ndarray) -> Step:
        c = self.config
        m = self.pnp(np.asarray(obs, dtype=float))
        if not self.initialized:
            if not m.ok:
                return self.target_step(math.nan, math.nan, np.full(3, math.nan), True)
            var = [c.sigma_alpha**2 if c.sigma_alpha else None, c.sigma_z**2 if c.sigma_z else None]
            if None in var:
                saved = {k: v.copy() for k, v in self.prev_normals.items()}
                va, vz = propagated_variance(self.pnp, np.asarray(obs, dtype=float), m, c.pixel_sigma)
                self.prev_normals = saved
                var = [var[0] or va, var[1] or vz]
            self.kf.R = np.diag(np.array(var, dtype=float))
            self.kf.x = np.array([[m.alpha], [0.0], [m.distance], [0.0]])
            self.kf.P = np.diag([var[0], c.sigma_rate0**2, var[1], c.sigma_rate0**2])
            self.initialized = True
            self._center_dir = m.center / m.center[2]
            return self.target_step(m.alpha, m.distance, m.center, False)
        self.kf.predict()
        u = np.array([m.alpha, m.distance])
        kf = self.kf
        gated = m.ok and self.gated_measurement(u, (kf.H @ kf.x).ravel(), kf.H @ kf.P @ kf.H.T + kf.R)
        one = self.kept_view(obs, (kf.H @ kf.x).ravel(), kf.H @ kf.P @ kf.H.T + 2.0 * kf.R) if gated else None
        use = m.ok and (not gated or one is not None)
        if use:
            used = m if one is None else one
            kf.update(np.array([[used.alpha], [used.distance]]), R=None if one is None else 2.0 * kf.R)
            self._center_dir = used.center / used.center[2]
        x = kf.x.ravel()
        nis = {"innovation": kf.y.ravel().copy(), "innovation_covariance": kf.S.copy()} if use else {}
        return self.target_step(float(x[0]), float(x[2]), self._center_dir * x[2], not use, float(gated),
                                covariance=kf.P.copy(), **nis)
