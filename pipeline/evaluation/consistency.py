"""Filter consistency: NEES against the truth and NIS from the filter's own innovations
(Bar-Shalom, Li & Kirubarajan §5.4). Pure functions of tracks and truth arrays.

For a consistent filter the normalized estimation error squared ``ε = (x − x̂)ᵀ P⁻¹ (x − x̂)`` is
χ²-distributed with ``dim x`` degrees of freedom, and the normalized innovation squared
``yᵀ S⁻¹ y`` with ``dim y``; the 95 % band is ``[χ²₀.₀₂₅, χ²₀.₉₇₅]``.
"""

from __future__ import annotations

import numpy as np

from pipeline.core.chi2 import gammaincinv
from pipeline.estimators.base import Track


def nees(track: Track, truth_position: np.ndarray, truth_velocity: np.ndarray | None = None) -> np.ndarray:
    """Per-frame NEES of a track with state covariance: on position (3 dof) or, with the true
    velocity, on the full state (6 dof). NaN where the track or the truth is missing."""
    if track.covariance is None:
        return np.full(len(track.position), np.nan)
    n = min(len(track.position), len(truth_position))
    if truth_velocity is None:
        e, P = track.position[:n] - truth_position[:n], track.covariance[:n, :3, :3]
    else:
        e = np.hstack([track.position[:n] - truth_position[:n], track.velocity[:n] - truth_velocity[:n]])
        P = track.covariance[:n]
    out = np.full(n, np.nan)
    ok = np.all(np.isfinite(e), axis=1) & np.all(np.isfinite(P), axis=(1, 2))
    if ok.any():
        out[ok] = np.einsum("ni,ni->n", e[ok], np.linalg.solve(P[ok], e[ok][..., None])[..., 0])
    return out


def band(dof: np.ndarray | int, p: float = 0.95) -> tuple[np.ndarray, np.ndarray]:
    """The two-sided ``p`` band of χ²(dof): ``χ²_q(k) = 2·P⁻¹(k/2, q)``, the inverse regularised
    lower incomplete gamma function (:mod:`pipeline.core.chi2`: no scipy import for the usual degrees of freedom)."""
    k = np.asarray(dof, dtype=float) / 2
    return 2 * gammaincinv(k, (1 - p) / 2), 2 * gammaincinv(k, (1 + p) / 2)


def summary(values: np.ndarray, dof: np.ndarray | int) -> dict[str, float] | None:
    """Mean of ``values / dof`` (1 when consistent) and the fraction inside the 95 % band (0.95
    when consistent), over the finite values; None when there are none."""
    values = np.asarray(values, dtype=float)
    dof = np.broadcast_to(np.asarray(dof), values.shape)
    ok = np.isfinite(values) & (dof > 0)
    if not ok.any():
        return None
    lo, hi = band(dof[ok])
    v = values[ok]
    return {"normalized_mean": float(np.mean(v / dof[ok])), "in_95": float(np.mean((v >= lo) & (v <= hi))),
            "frames": int(ok.sum())}
