"""Pieces the Kalman-family point estimators share: config, initial covariance, partial updates."""

from __future__ import annotations

import numpy as np
from pydantic import Field

from pipeline.estimators.base import EstimatorConfig


class KalmanConfig(EstimatorConfig):
    """Noise settings of the Kalman family.

    ``process_noise``: spectral density q (m²/s³) of the white-noise acceleration model.
    ``pixel_sigma``: std (px) of detection noise, ``R = σ² I``. ``covariance_scale`` multiplies
    both Q and R's *assumed* values — the thesis's "wrong covariances" experiment (Fig. 12) sets
    ``q_scale`` and ``r_scale`` off by orders of magnitude.
    """

    process_noise: float = Field(0.5, gt=0)
    pixel_sigma: float = Field(1.0, gt=0)
    q_scale: float = Field(1.0, gt=0)
    r_scale: float = Field(1.0, gt=0)


def initial_covariance(cfg: KalmanConfig) -> np.ndarray:
    """Diagonal prior covariance from the init section's position/velocity stds."""
    s = np.r_[np.full(3, cfg.init.sigma_position**2), np.full(3, cfg.init.sigma_velocity**2)]
    return np.diag(s)


def available_rows(y: np.ndarray) -> np.ndarray:
    """Indices of the observation rows present (both coordinates of a camera go together)."""
    ok = np.isfinite(y)
    ok[:2] = ok[:2].all()
    ok[2:] = ok[2:].all()
    return np.flatnonzero(ok)
