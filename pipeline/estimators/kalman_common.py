"""Pieces the Kalman-family point estimators share: config, partial updates, the batched Joseph
update and the batched filter loop (one copy, used by ``kf3d`` and ``ekf``), and the
Rauch–Tung–Striebel backward pass (filterpy's ``rts_smoother``)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from pydantic import Field

from pipeline.estimators.base import Estimator, EstimatorConfig, Step, Track, reprojection_errors


class KalmanConfig(EstimatorConfig):
    """Noise settings of the Kalman family.

    ``process_noise``: spectral density q (m²/s³) of the white-noise acceleration model.
    ``pixel_sigma``: std (px) of detection noise, ``R = σ² I`` (the pipeline sets it from the data
    unless configured). ``q_scale`` and ``r_scale`` multiply the *assumed* Q and R — the thesis's
    "wrong covariances" experiment (Fig. 12) sets them off by orders of magnitude.
    """

    process_noise: float = Field(0.5, gt=0)
    pixel_sigma: float = Field(1.0, gt=0)
    q_scale: float = Field(1.0, gt=0)
    r_scale: float = Field(1.0, gt=0)


def available_rows(y: np.ndarray) -> np.ndarray:
    """Indices of the observation rows present (both coordinates of a camera go together)."""
    ok = np.isfinite(y)
    ok[:2] = ok[:2].all()
    ok[2:] = ok[2:].all()
    return np.flatnonzero(ok)


def joseph_update(x: np.ndarray, P: np.ndarray, H: np.ndarray, r: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update of M states at once (filterpy's equations, Joseph form)::

        S = H P Hᵀ + R,  K = P Hᵀ S⁻¹,  x ← x + K r,  P ← (I − K H) P (I − K H)ᵀ + K R Kᵀ

    ``x`` M×d, ``P`` M×d×d, ``H`` M×m×d, residual ``r`` M×m, ``R`` M×m×m.
    """
    PHt = P @ H.transpose(0, 2, 1)
    S = H @ PHt + R
    K = np.linalg.solve(S, PHt.transpose(0, 2, 1)).transpose(0, 2, 1)  # P Hᵀ S⁻¹ (S symmetric)
    x = x + np.einsum("mij,mj->mi", K, r)
    IKH = np.eye(x.shape[1]) - K @ H
    return x, IKH @ P @ IKH.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)


#: (positions M×3, observations M×4) → (H M×m×6, residual M×m, R M×m×m, has-measurement M)
Linearize = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


def kalman_batch(est: Estimator, Y: np.ndarray, linearize: Linearize) -> np.ndarray:
    """The filter of a Kalman-family estimator over M tracks at once (M × frames × 4 → M × frames
    × 3): each track starts where :class:`~pipeline.estimators.base.Initiator` says (the same
    start as :meth:`Estimator.run`), then predict with ``est.A, est.Q`` and update through
    ``linearize`` on every later frame with a measurement."""
    M, n, _ = Y.shape
    est.reset()
    starts = est.initiator.first_batch(Y)
    begin = np.array([s.frame if s is not None else n for s in starts])
    x, P = np.zeros((M, 6)), np.tile(np.eye(6), (M, 1, 1))
    out = np.full((M, n, 3), np.nan)
    A, Q = est.A, est.Q
    for k in range(n):
        run = begin < k
        x[run] = x[run] @ A.T
        P[run] = A @ P[run] @ A.T + Q
        for m in np.flatnonzero(begin == k):
            x[m], P[m] = starts[m].state, starts[m].covariance
        idx = np.flatnonzero(run)
        if len(idx):
            H, r, R, have = linearize(x[idx, :3], Y[idx, k])
            u = idx[have]
            if len(u):
                x[u], P[u] = joseph_update(x[u], P[u], H[have], r[have], R[have])
        out[begin <= k, k] = x[begin <= k, :3]
    return out


def rts_smooth(est: Estimator, track: Track) -> Track:
    """Rauch–Tung–Striebel backward pass over a filtered track (filterpy's ``rts_smoother`` with
    the filter's constant ``A``, ``Q``), from its first estimate to its last::

        P⁻ₖ₊₁ = A Pₖ Aᵀ + Q,  Cₖ = Pₖ Aᵀ (P⁻ₖ₊₁)⁻¹,
        x̂ₖ ← xₖ + Cₖ (x̂ₖ₊₁ − A xₖ),  P̂ₖ ← Pₖ + Cₖ (P̂ₖ₊₁ − P⁻ₖ₊₁) Cₖᵀ
    """
    ok = np.flatnonzero(np.all(np.isfinite(track.position), axis=1))
    if len(ok) < 2 or track.covariance is None:  # never started: nothing to smooth
        return track
    s = ok[0]
    Xs = np.hstack([track.position[s:], track.velocity[s:]])
    from filterpy.kalman import KalmanFilter  # imported when a filter is built (see base.py)

    kf = KalmanFilter(dim_x=6, dim_z=1)
    kf.F, kf.Q = est.A, est.Q
    xs, Ps, _, _ = kf.rts_smoother(Xs, track.covariance[s:].copy())
    track.position = track.position.copy()
    track.velocity = track.velocity.copy()
    track.covariance = track.covariance.copy()
    track.position[s:], track.velocity[s:], track.covariance[s:] = xs[:, :3], xs[:, 3:], Ps
    track.covariance_trace = np.trace(track.covariance, axis1=1, axis2=2)
    return track


def filtered_step(x: np.ndarray, P: np.ndarray, predicted: bool, f=None) -> Step:
    """A Kalman-family step from the filter's state; with ``f`` (a filterpy filter that just
    updated) its innovation ``y`` and covariance ``S`` are kept for NIS."""
    x = np.ravel(x)
    if f is None or predicted:
        return Step(x[:3].copy(), x[3:].copy(), predicted, P.copy())
    return Step(x[:3].copy(), x[3:].copy(), predicted, P.copy(), np.ravel(f.y).copy(), np.array(f.S, dtype=float).copy())


class RTSMixin:
    """Makes a Kalman-family estimator a smoother: :meth:`finish` runs :func:`rts_smooth` over the
    filtered track (the streaming ``step`` output stays the filter's); ``run_batch`` loops over
    :meth:`run` so that every track is smoothed."""

    def finish(self, steps: list[Step], Y: np.ndarray, seconds_per_step: float = float("nan")) -> Track:
        tr = rts_smooth(self, super().finish(steps, Y, seconds_per_step))  # type: ignore[misc,arg-type]
        tr.reprojection_error = reprojection_errors(self.rig, tr.position, Y)  # type: ignore[attr-defined]
        return tr

    run_batch = Estimator.run_batch
