"""The linear Kalman filter, its Rauch–Tung–Striebel smoother and the unscented Kalman filter,
written out in numpy with filterpy's equations and public names (``x, P, F, Q, H, R, y, S, K``,
``x_prior, P_prior``): filterpy's own classes import ``scipy.stats`` (about a second, more than a
whole default estimate stage's steps), so the built-in methods build these instead. Tests drive
both on the same observations and hold them equal to the last bit (filterpy's operations in its order).

References: R. E. Kalman, "A new approach to linear filtering and prediction problems", J. Basic
Eng. 82 (1960); H. E. Rauch, F. Tung & C. T. Striebel, "Maximum likelihood estimates of linear
dynamic systems", AIAA J. 3(8), 1965; R. van der Merwe, "Sigma-point Kalman filters for
probabilistic inference in dynamic state-space models", PhD thesis, OGI 2004 (scaled sigma points).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


class KalmanFilter:
    """Linear Kalman filter ``x⁻ = F x, P⁻ = F P Fᵀ + Q``; update in Joseph form::

        y = z − H x⁻,  S = H P⁻ Hᵀ + R,  K = P⁻ Hᵀ S⁻¹,
        x = x⁻ + K y,  P = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ

    (filterpy's ``KalmanFilter.predict``/``update``, column-vector state)."""

    def __init__(self, dim_x: int, dim_z: int) -> None:
        self.x = np.zeros((dim_x, 1))
        self.P, self.F, self.Q = np.eye(dim_x), np.eye(dim_x), np.eye(dim_x)
        self.H, self.R = np.zeros((dim_z, dim_x)), np.eye(dim_z)
        self.y, self.S = np.zeros((dim_z, 1)), np.zeros((dim_z, dim_z))
        self.K = np.zeros((dim_x, dim_z))
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()
        self._I = np.eye(dim_x)

    def predict(self) -> None:
        """Propagate the state and covariance one step."""
        self.x = np.dot(self.F, self.x)  # np.dot throughout, in filterpy's order: equal to its last bit
        self.P = np.dot(np.dot(self.F, self.P), self.F.T) + self.Q
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()

    def update(self, z: np.ndarray, R: np.ndarray | None = None) -> None:
        """Fold in measurement ``z`` (dim_z × 1) with covariance ``R`` (the filter's own if None)."""
        R = self.R if R is None else R
        H = self.H
        self.y = np.reshape(z, (-1, 1)) - np.dot(H, self.x)
        PHT = np.dot(self.P, H.T)
        self.S = np.dot(H, PHT) + R
        self.K = np.dot(PHT, np.linalg.inv(self.S))
        self.x = self.x + np.dot(self.K, self.y)
        I_KH = self._I - np.dot(self.K, H)
        self.P = np.dot(np.dot(I_KH, self.P), I_KH.T) + np.dot(np.dot(self.K, R), self.K.T)

    def rts_smoother(self, Xs: np.ndarray, Ps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rauch–Tung–Striebel backward pass over filtered means ``Xs`` (n × d) and covariances
        ``Ps`` (n × d × d) with this filter's ``F`` and ``Q``; returns the smoothed pair (copies)::

            P⁻ₖ₊₁ = F Pₖ Fᵀ + Q,  Cₖ = Pₖ Fᵀ (P⁻ₖ₊₁)⁻¹,
            xₖ += Cₖ (xₖ₊₁ − F xₖ),  Pₖ += Cₖ (Pₖ₊₁ − P⁻ₖ₊₁) Cₖᵀ
        """
        F, Q = self.F, self.Q
        x, P = Xs.copy(), Ps.copy()
        for k in range(len(x) - 2, -1, -1):
            Pp = np.dot(np.dot(F, P[k]), F.T) + Q
            C = np.dot(np.dot(P[k], F.T), np.linalg.inv(Pp))
            x[k] += np.dot(C, x[k + 1] - np.dot(F, x[k]))
            P[k] += np.dot(np.dot(C, P[k + 1] - Pp), C.T)
        return x, P


class MerweSigmaPoints:
    """Van der Merwe's scaled sigma points: ``λ = α²(n + κ) − n``, points ``x`` and ``x ± rowsₖ(U)``
    with ``UᵀU = (n + λ) P``; weights ``Wm₀ = λ/(n+λ)``, ``Wc₀ = Wm₀ + 1 − α² + β``, the rest
    ``1/(2(n+λ))``."""

    def __init__(self, n: int, alpha: float, beta: float, kappa: float) -> None:
        self.n, lam = n, alpha**2 * (n + kappa) - n
        self.scale = lam + n
        c = 0.5 / (n + lam)
        self.Wm, self.Wc = np.full(2 * n + 1, c), np.full(2 * n + 1, c)
        self.Wm[0] = lam / (n + lam)
        self.Wc[0] = lam / (n + lam) + (1 - alpha**2 + beta)

    def sigma_points(self, x: np.ndarray, P: np.ndarray) -> np.ndarray:
        """The 2n + 1 points (rows) for mean ``x`` and covariance ``P``."""
        return np.vstack([x, x + (U := self.cholesky(self.scale * P)), x - U])

    @staticmethod
    def cholesky(A: np.ndarray) -> np.ndarray:
        """The upper factor ``U`` (``UᵀU = A``) that filterpy takes from ``scipy.linalg.cholesky``:
        numpy's ``upper=True`` is LAPACK's ``dpotrf`` on the upper triangle too, equal to it bit for
        bit (tests/estimators/test_filters.py), without importing scipy.linalg (0.15–0.2 s)."""
        if not np.isfinite(A).all():
            raise ValueError("array must not contain infs or NaNs")
        return np.linalg.cholesky(A, upper=True)


def unscented_transform(sigmas: np.ndarray, Wm: np.ndarray, Wc: np.ndarray,
                        noise: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted mean and covariance of transformed sigma points, plus additive noise."""
    sigmas = np.ascontiguousarray(sigmas)  # C order and np.dot: the same BLAS calls as filterpy, equal to the last bit
    x = np.dot(Wm, sigmas)
    d = sigmas - x
    return x, np.dot(d.T, np.dot(np.diag(Wc), d)) + noise


class UnscentedKalmanFilter:
    """Unscented Kalman filter with additive noise (filterpy's ``UnscentedKalmanFilter``: the prior's
    sigma points are redrawn from ``x⁻, P⁻`` after the prediction and pushed through ``h``)::

        x⁻, P⁻ = UT(f(χ)),  ẑ, S = UT(h(χ⁻)) + R,  Pxz = Σ Wcᵢ (χ⁻ᵢ − x⁻)(h(χ⁻ᵢ) − ẑ)ᵀ,
        K = Pxz S⁻¹,  x = x⁻ + K (z − ẑ),  P = P⁻ − K S Kᵀ

    ``fx`` and ``hx`` take all sigma points at once (rows)."""

    def __init__(self, dim_x: int, points: MerweSigmaPoints, fx: Callable[[np.ndarray], np.ndarray]) -> None:
        self.points, self.fx = points, fx
        self.x, self.P, self.Q = np.zeros(dim_x), np.eye(dim_x), np.eye(dim_x)
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()
        self.sigmas_f = np.zeros((2 * dim_x + 1, dim_x))
        self.y: np.ndarray = np.zeros(0)
        self.S: np.ndarray = np.zeros((0, 0))
        self.K: np.ndarray = np.zeros((dim_x, 0))

    def predict(self) -> None:
        """Propagate the sigma points, re-estimate the prior and redraw its sigma points."""
        pts = self.points
        moved = self.fx(pts.sigma_points(self.x, self.P))
        self.x, self.P = unscented_transform(moved, pts.Wm, pts.Wc, self.Q)
        self.sigmas_f = pts.sigma_points(self.x, self.P)
        self.x_prior, self.P_prior = self.x.copy(), self.P.copy()

    def update(self, z: np.ndarray, R: np.ndarray, sigmas_h: np.ndarray) -> None:
        """Fold in ``z`` given the prior's sigma points through the measurement model (``sigmas_h``)."""
        pts = self.points
        zp, self.S = unscented_transform(sigmas_h, pts.Wm, pts.Wc, R)
        dx, dz = self.sigmas_f - self.x, sigmas_h - zp
        Pxz = np.zeros((len(self.x), len(zp)))
        for term in pts.Wc[:, None, None] * (dx[:, :, None] * dz[:, None, :]):  # filterpy's w · outer(dx, dz), all at once
            Pxz += term  # summed point by point in its order
        self.K = np.dot(Pxz, np.linalg.inv(self.S))
        self.y = z - zp
        self.x = self.x + np.dot(self.K, self.y)
        self.P = self.P - np.dot(self.K, np.dot(self.S, self.K.T))
