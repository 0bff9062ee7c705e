"""A fixed-size compiled EKF for two cameras: the plainest fast implementation to hold the project's
compiled EKF against. Every size is a constant (6 states, 4 rows), the matrices live in a few
arrays allocated once, the products are loops the compiler unrolls, the 4 × 4 innovation
covariance is inverted through its Cholesky factor; no gate, no missing rows, no diagnostics beyond
the positions. Krivokon 2011 App. I's filter (white-noise acceleration, Joseph update)."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, fastmath=False)
def fixed_ekf(Y, k0, x0, P0, Pm, dt, Q, R, out):
    """Filter frames ``k0 + 1 …`` of ``Y`` (frames × 4) from ``x0``, ``P0`` at frame ``k0``; positions into ``out``."""
    x, P = x0.copy(), P0.copy()
    H, h = np.zeros((4, 6)), np.empty(4)
    PHt, S, L, Si, K = np.empty((6, 4)), np.empty((4, 4)), np.zeros((4, 4)), np.empty((4, 4)), np.empty((6, 4))
    IKH, T, KR, z = np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 4)), np.empty(4)
    for a in range(3):
        out[k0, a] = x[a]
    for k in range(k0 + 1, Y.shape[0]):
        for a in range(3):  # x ← A x, P ← A P Aᵀ + Q with A = [[I, dt I], [0, I]]
            x[a] += dt * x[a + 3]
        for i in range(3):
            for j in range(6):
                P[i, j] += dt * P[i + 3, j]
        for i in range(6):
            for j in range(3):
                P[i, j] += dt * P[i, j + 3]
        for i in range(6):
            for j in range(6):
                P[i, j] += Q[i, j]
        for c in range(2):  # h(x) and its Jacobian (first three columns)
            q2 = Pm[c, 2, 0] * x[0] + Pm[c, 2, 1] * x[1] + Pm[c, 2, 2] * x[2] + Pm[c, 2, 3]
            for r in range(2):
                u = (Pm[c, r, 0] * x[0] + Pm[c, r, 1] * x[1] + Pm[c, r, 2] * x[2] + Pm[c, r, 3]) / q2
                h[2 * c + r] = u
                for a in range(3):
                    H[2 * c + r, a] = (Pm[c, r, a] - u * Pm[c, 2, a]) / q2
        for i in range(6):  # P Hᵀ, S = H P Hᵀ + R
            for j in range(4):
                acc = 0.0
                for t in range(3):
                    acc += P[i, t] * H[j, t]
                PHt[i, j] = acc
        for i in range(4):
            for j in range(4):
                acc = R[i, j]
                for t in range(3):
                    acc += H[i, t] * PHt[t, j]
                S[i, j] = acc
        for j in range(4):  # S = L Lᵀ, then S⁻¹ = L⁻ᵀ L⁻¹ column by column
            d = S[j, j]
            for t in range(j):
                d -= L[j, t] * L[j, t]
            L[j, j] = np.sqrt(d)
            for i in range(j + 1, 4):
                acc = S[i, j]
                for t in range(j):
                    acc -= L[i, t] * L[j, t]
                L[i, j] = acc / L[j, j]
        for col in range(4):
            for i in range(4):
                acc = 1.0 if i == col else 0.0
                for t in range(i):
                    acc -= L[i, t] * z[t]
                z[i] = acc / L[i, i]
            for i in range(3, -1, -1):
                acc = z[i]
                for t in range(i + 1, 4):
                    acc -= L[t, i] * Si[t, col]
                Si[i, col] = acc / L[i, i]
        for i in range(6):  # K = P Hᵀ S⁻¹, x ← x + K (y − h)
            for j in range(4):
                acc = 0.0
                for t in range(4):
                    acc += PHt[i, t] * Si[t, j]
                K[i, j] = acc
        for i in range(6):
            acc = 0.0
            for j in range(4):
                acc += K[i, j] * (Y[k, j] - h[j])
            x[i] += acc
        for i in range(6):  # Joseph: P ← (I − K H) P (I − K H)ᵀ + K R Kᵀ
            for j in range(6):
                acc = 1.0 if i == j else 0.0
                if j < 3:
                    for t in range(4):
                        acc -= K[i, t] * H[t, j]
                IKH[i, j] = acc
        for i in range(6):
            for j in range(6):
                acc = 0.0
                for t in range(6):
                    acc += IKH[i, t] * P[t, j]
                T[i, j] = acc
            for j in range(4):
                acc = 0.0
                for t in range(4):
                    acc += K[i, t] * R[t, j]
                KR[i, j] = acc
        for i in range(6):
            for j in range(6):
                acc = 0.0
                for t in range(6):
                    acc += T[i, t] * IKH[j, t]
                for t in range(4):
                    acc += KR[i, t] * K[j, t]
                P[i, j] = acc
        for a in range(3):
            out[k, a] = x[a]


def run_fixed(rig, dt: float, Y: np.ndarray, start, q: float = 0.5, sigma: float = 1.0) -> tuple[np.ndarray, callable]:
    """Positions of the fixed-size EKF from the initiator's ``start``, and a call that reruns it (for timing)."""
    from pipeline.estimators.base import white_noise_acceleration

    Pm = np.ascontiguousarray(np.stack([rig.left.P, rig.right.P]), dtype=float)
    Q, R = white_noise_acceleration(dt, q), np.eye(4) * sigma**2
    out = np.full((len(Y), 3), np.nan)
    Yc = np.ascontiguousarray(Y, dtype=float)

    def call() -> None:
        fixed_ekf(Yc, start.frame, start.state, start.covariance, Pm, dt, Q, R, out)

    call()
    return out, call
