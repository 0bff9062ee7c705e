"""Alpha-beta and alpha-beta-gamma filters (Kalata, *The tracking index*, IEEE TAES 20(2), 1984;
Brookner, *Tracking and Kalman Filtering Made Easy*, ch. 1), on triangulated 3-D positions
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

from pipeline.core.alphabeta import ABFilter
from pipeline.estimators.base import NAN3, Estimator, EstimatorConfig, Step, not_started
from pipeline.estimators.gating import RobustNISScale, camera_gate, camera_nis, stereo_consistent
from pipeline.estimators.kalman_common import update_gated_run
from pipeline.estimators.registration import register

#: frames in a row with one camera gated while both cameras' detections triangulate to one point
#: after which the track restarts: the filter's depth drifted along the kept camera's ray (which
#: cannot see it) and the other camera's right detections fall outside the gate; outliers in one
#: camera are off the epipolar line, and do not line up on it three frames running
DRIFT_RESTART = 3


class AlphaBetaConfig(EstimatorConfig):
    gate: float = Field(0.9995, ge=0.0, lt=1.0)
    """the per-camera χ² gate (0 turns it off), scaled by the robust NIS scale so that the lag of fixed gains through a
    manoeuvre widens it; a track gated ``restart_after`` frames in a row restarts, and in 3-D one whose gate leaves one
    camera three frames running although both triangulate to one point (its depth drifted along the kept camera's
    ray: :data:`DRIFT_RESTART`). Ungated, 5 % random-pixel outliers
    make alphabeta's RMSE 8× its clean one (benchmarks/trackers.py)"""
    alpha: float = Field(0.5, gt=0, le=1)
    """position gain α: the share of each residual taken into the position"""
    beta: float = Field(0.1, ge=0, le=2)
    """velocity gain β: the share of each residual, over dt, taken into the velocity"""
    space: Literal["3d", "image"] = "3d"
    """filter the triangulated 3-D points ("3d") or each camera's pixels, then triangulate ("image")"""


class AlphaBetaGammaConfig(AlphaBetaConfig):
    gamma: float = Field(0.01, ge=0, le=2)
    """acceleration gain γ: 2γ/dt² of each residual goes into the acceleration"""


@register
class AlphaBetaEstimator(Estimator):
    """Alpha-beta filter on triangulated 3-D positions or on image coordinates."""

    name = "alphabeta"
    Config = AlphaBetaConfig
    config: AlphaBetaConfig  # the validated settings, of this method's own type

    def _gamma(self) -> float | None:
        return None

    def reset(self) -> None:
        super().reset()
        self.f: ABFilter | None = None
        cfg = self.config
        self.threshold = camera_gate(cfg.gate)
        gamma = self._gamma()
        order = 2 if gamma is None else 3
        self.F1 = np.array([[1.0, self.dt, 0.5 * self.dt**2], [0.0, 1.0, self.dt], [0.0, 0.0, 1.0]])[:order, :order]
        self.K1 = np.array([cfg.alpha, cfg.beta / self.dt, 2.0 * (gamma or 0.0) / self.dt**2])[:order]
        self.IKH = np.eye(order) - np.outer(self.K1, np.eye(order)[0])  # the fixed gain's I − K H, and K Kᵀ
        self.KKt = np.outer(self.K1, self.K1)
        self.R_pixels = self.model.covar()  # the gate's pixel noise, σ² I
        self.scale = RobustNISScale(cfg.pixel_sigma)  # the innovations' variance over the model's (≥ 1; lag raises it)
        self.drift_run = 0  # frames in a row with one camera gated although the pair is one point

    def _begin(self, s) -> None:
        """Start the filter and its error covariance (per channel: position, rate(, acceleration))
        from the initiator's start."""
        cfg = self.config
        p0, v0 = s.state[:3], s.state[3:]
        order = len(self.K1)
        if cfg.space == "image":  # the start in pixels: h(p0), and its rate J(p0) v0
            self.f = ABFilter(self.model.function(p0), self.dt, cfg.alpha, cfg.beta, self._gamma())
            J = self.rig.jacobian(p0)
            self.f.v = J @ v0
            pos_var = np.full(4, self.model.pixel_sigma**2)
            rate_var = np.diag(J @ s.covariance[3:, 3:] @ J.T)
        else:
            self.f = ABFilter(p0, self.dt, cfg.alpha, cfg.beta, self._gamma())
            self.f.v = v0.copy()
            pos_var, rate_var = np.diag(s.covariance[:3, :3]), np.diag(s.covariance[3:, 3:])
        self.P = np.zeros((len(pos_var), order, order))
        self.P[:, 0, 0], self.P[:, 1, 1] = pos_var, rate_var
        if order == 3:
            self.P[:, 2, 2] = rate_var  # acceleration prior: the velocity's std per second
        self.initialized = True

    def _correct_covariance(self, z: np.ndarray) -> None:
        """The fixed-gain filter's error covariance, per channel (predicted ``P⁻ = F P Fᵀ`` in
        :meth:`_step`); on the channels corrected by ``z``, ``P = (I − KH) P⁻ (I − KH)ᵀ + K R Kᵀ``
        with R the measurement's variance (σ², or the triangulation's): exact for white measurement
        noise, and its limit is Kalata's steady state (IEEE TAES 20(2), 1984)."""
        corrected = np.isfinite(z)
        if self.config.space == "image":
            R = np.full(len(z), self.model.pixel_sigma**2)
        else:
            R = np.diag(self.model.inverse_covariance(z)) if corrected.all() else np.zeros(3)
        upd = self.IKH @ self.P @ self.IKH.T + R[:, None, None] * self.KKt
        self.P = np.where(corrected[:, None, None], upd, self.P)

    def _gate(self, y: np.ndarray) -> tuple[np.ndarray, int]:
        """Drop the cameras whose innovation falls outside the χ² gate, on the filter's predicted
        error covariance (:meth:`_correct_covariance`; in 3-D seen through the cameras) times a
        robust scale (:class:`~pipeline.estimators.gating.RobustNISScale`): an α-β filter lags a
        manoeuvre, and its innovations grow with the lag."""
        assert self.f is not None
        if not np.isfinite(self.threshold):
            return y, 0
        if self.config.space == "image":
            r = (y - self.f.x).reshape(2, 2)
            S = (self.P[:, 0, 0] + self.model.pixel_sigma**2).reshape(2, 2)
            nis = np.where(np.all(np.isfinite(r), axis=1), np.nansum(r**2 / S, axis=1), np.nan)
        else:
            P = np.zeros((6, 6))
            P[:3, :3] = np.diag(self.P[:, 0, 0])
            x = np.concatenate((self.f.x, np.zeros(3)))
            h, H = self.model.linearize(x)  # h and ∂h/∂x in one pass
            nis = camera_nis(self.model, x, P, y, self.R_pixels, h, H)
        with np.errstate(invalid="ignore"):
            g = nis / self.scale.value > self.threshold
        self.scale.add(nis)
        if g.all() and stereo_consistent(self.model, y, self.config.pixel_sigma, self.config.gate):
            g[:] = False  # both far from the prediction but one point: the filter lags, no outlier
        kept = y.copy()
        for c in np.flatnonzero(g):
            kept[2 * c : 2 * c + 2] = np.nan
        return kept, int(g.sum())

    def _point(self, y: np.ndarray) -> np.ndarray:
        """The 3-D measurement of a frame: its triangulation; with one camera kept, the point of
        that camera's ray nearest the prediction, to first order ``x + J⁺ (y_c − h_c(x))`` with
        ``J⁺ = Jᵀ (J Jᵀ)⁻¹`` (the correction moves the track across the ray, never along it)."""
        assert self.f is not None
        rows = np.flatnonzero(np.isfinite(y))
        if len(rows) != 2:
            return self.model.inverse_function(y[None])[0]
        h, H = self.model.linearize(np.concatenate((self.f.x, np.zeros(3))))
        J = H[rows, :3]
        return self.f.x + J.T @ np.linalg.solve(J @ J.T, y[rows] - h[rows])

    def _step(self, y: np.ndarray) -> Step:
        cfg = self.config
        image = cfg.space == "image"
        n_gated, restarted = 0, False
        if self.f is None:
            s = self.start(y)
            if s is None:
                return not_started()
            self._begin(s)
            have = True
        else:
            self.f.predict()
            self.P = self.F1 @ self.P @ self.F1.T
            kept, n_gated = self._gate(y)
            self.gated_run = int(update_gated_run(self.gated_run, y, kept))
            drifted = (not image and n_gated == 1 and np.isfinite(y).all()
                       and stereo_consistent(self.model, y, cfg.pixel_sigma, cfg.gate))
            self.drift_run = self.drift_run + 1 if drifted else 0
            lost = self.gated_run >= cfg.restart_after or self.drift_run >= DRIFT_RESTART
            s = self.initiator.restart(self.frame, self.recent_observations()) if lost else None
            if s is not None:
                self._begin(s)
                self.gated_run, self.drift_run, restarted = 0, 0, True
                have = True
            else:
                z = kept if image else self._point(kept)
                self.f.correct(z)
                if image or np.isfinite(kept).sum() != 2:  # one camera's ray leaves the depth's error as predicted
                    self._correct_covariance(z)
                have = bool(np.isfinite(z).any())
        extra = {"gated": float(n_gated), "restart": float(restarted)}
        f = self.f
        assert f is not None  # started above, or earlier
        if image:
            return Step(self.model.inverse_function(f.x[None])[0], NAN3.copy(), predicted=not have, extra=extra)
        return Step(f.x.copy(), f.v.copy(), predicted=not have, extra=extra)


@register
class AlphaBetaGammaEstimator(AlphaBetaEstimator):
    """Alpha-beta-gamma filter (alpha-beta plus an acceleration channel)."""

    name = "alphabetagamma"
    Config = AlphaBetaGammaConfig
    config: AlphaBetaGammaConfig  # the validated settings, of this method's own type

    def _gamma(self) -> float | None:
        return self.config.gamma
