"""Fixed-size linear algebra for the compiled filters: products and inverses of matrices of at most
6 × 6 in plain loops (no BLAS call for tiny matrices), the constant-velocity prediction, and the
one Joseph-form update every compiled Kalman filter uses."""

from __future__ import annotations

from collections import namedtuple

import numpy as np

from ._jit import kernel

#: the scratch matrices of one :func:`joseph_update` (``m`` ≤ 4 observation rows, a 6-state):
#: ``P Hᵀ`` (6 × 4), ``S`` and ``S⁻¹`` (4 × 4), the gain ``K`` (6 × 4), ``I − KH`` and ``(I − KH) P``
#: (6 × 6), ``K R`` (6 × 4) and the inversion's work space (4 × 4)
Workspace = namedtuple("Workspace", ["PHt", "S", "Si", "K", "IKH", "T6", "KR", "work"])


def workspace() -> Workspace:
    """Fresh scratch matrices for :func:`joseph_update` (allocated once per clip, not per frame)."""
    e = np.empty
    return Workspace(e((6, 4)), e((4, 4)), e((4, 4)), e((6, 4)), e((6, 6)), e((6, 6)), e((6, 4)), e((4, 4)))


@kernel(inline=True)
def mm(A, B, out, n, k, m, transpose_b):
    """``out[:n, :m] = A[:n, :k] @ B[:k, :m]`` (``B[:m, :k]ᵀ`` with ``transpose_b``) in plain loops:
    no BLAS call for tiny matrices (copied into each caller, where constant sizes unroll the loops)."""
    for i in range(n):
        for j in range(m):
            acc = 0.0
            if transpose_b:
                for t in range(k):
                    acc += A[i, t] * B[j, t]
            else:
                for t in range(k):
                    acc += A[i, t] * B[t, j]
            out[i, j] = acc


@kernel(inline=True)
def inv_small(S, m, out, work):
    """``out[:m, :m] = S[:m, :m]⁻¹`` by Gauss–Jordan elimination with partial pivoting (``work``: m × m
    or larger; inlined, as :func:`mm`)."""
    for i in range(m):
        for j in range(m):
            work[i, j] = S[i, j]
            out[i, j] = 1.0 if i == j else 0.0
    for c in range(m):
        p = c
        for i in range(c + 1, m):
            if abs(work[i, c]) > abs(work[p, c]):
                p = i
        if p != c:
            for j in range(m):
                work[c, j], work[p, j] = work[p, j], work[c, j]
                out[c, j], out[p, j] = out[p, j], out[c, j]
        d = work[c, c]
        for j in range(m):
            work[c, j] /= d
            out[c, j] /= d
        for i in range(m):
            if i != c:
                f = work[i, c]
                if f != 0.0:
                    for j in range(m):
                        work[i, j] -= f * work[c, j]
                        out[i, j] -= f * out[c, j]


@kernel(signature="void(f8[:, ::1], f8[:, ::1], f8[:, ::1], b1)")
def mm6(A, B, out, transpose_b):
    """``out = A @ B`` (or ``A @ Bᵀ``) for 6 × 6 matrices: fixed sizes the compiler unrolls."""
    for i in range(6):
        for j in range(6):
            acc = 0.0
            if transpose_b:
                for t in range(6):
                    acc += A[i, t] * B[j, t]
            else:
                for t in range(6):
                    acc += A[i, t] * B[t, j]
            out[i, j] = acc



@kernel
def ekf_predict(dt, Q, x, P):
    """``x ← A x``, ``P ← A P Aᵀ + Q`` for the constant-velocity ``A = [[I, dt·I], [0, I]]``,
    by blocks (the same sums as the full products, without the multiplications by 0 and 1)."""
    for i in range(3):
        x[i] += dt * x[3 + i]
    for i in range(3):  # rows of A P: position rows gain dt × velocity rows
        for j in range(6):
            P[i, j] += dt * P[3 + i, j]
    for j in range(3):  # columns of (A P) Aᵀ: position columns gain dt × velocity columns
        for i in range(6):
            P[i, j] += dt * P[i, 3 + j]
    for i in range(6):
        for j in range(6):
            P[i, j] += Q[i, j]


def _joseph(x, P, Hs, rs, Rs, m, nz, ws, have_S):
    """The Joseph-form update on ``m`` observation rows (``Hs`` m × 6, residual ``rs``, noise
    ``Rs``; x, P in place), returning the NIS ``rᵀ S⁻¹ r``: ``S = H P Hᵀ + R``, ``K = P Hᵀ S⁻¹``,
    ``x ← x + K r``, ``P ← (I − KH) P (I − KH)ᵀ + K R Kᵀ`` (Bucy & Joseph 1968; its upper triangle,
    mirrored: a covariance is symmetric). Only the first ``nz`` columns of ``H`` are nonzero (3
    without a time offset: the velocity does not enter ``h``), and the products skip the zeros (sums
    of the same nonzero terms in the same order as the full products). ``ws``: the scratch
    :class:`Workspace`; ``have_S``: 0, or 1 when ``ws.PHt`` and ``ws.S`` hold ``P Hᵀ`` and ``S``
    already (the gate's, for four rows), 2 when ``ws.Si`` holds ``S⁻¹`` too (the joint check's)."""
    PHt, S, Si, K, IKH, T6, KR = ws.PHt, ws.S, ws.Si, ws.K, ws.IKH, ws.T6, ws.KR
    if have_S == 0:
        mm(P, Hs, PHt, 6, nz, m, True)
        mm(Hs, PHt, S, m, nz, m, False)
        for i in range(m):
            for j in range(m):
                S[i, j] += Rs[i, j]
    if have_S < 2:
        inv_small(S, m, Si, ws.work)
    mm(PHt, Si, K, 6, m, m, False)
    mm(K, Hs, IKH, 6, m, nz, False)  # columns ≥ nz of I − KH are the identity's
    for i in range(6):
        for j in range(nz):
            IKH[i, j] = (1.0 if i == j else 0.0) - IKH[i, j]
        acc = 0.0
        for j in range(m):
            acc += K[i, j] * rs[j]
        x[i] += acc
    for i in range(6):  # T = (I − KH) P
        for j in range(6):
            acc = 0.0
            for t in range(nz):
                acc += IKH[i, t] * P[t, j]
            T6[i, j] = acc + P[i, j] if i >= nz else acc
    mm(K, Rs, KR, 6, m, m, False)
    for i in range(6):  # P = T (I − KH)ᵀ + K R Kᵀ, symmetric: the upper triangle, mirrored
        for j in range(i, 6):
            acc = 0.0
            for t in range(nz):
                acc += T6[i, t] * IKH[j, t]
            if j >= nz:
                acc += T6[i, j]
            krk = 0.0
            for t in range(m):
                krk += KR[i, t] * K[j, t]
            P[i, j] = acc + krk
            P[j, i] = P[i, j]
    nis = 0.0
    for i in range(m):
        for j in range(m):
            nis += rs[i] * Si[i, j] * rs[j]
    return nis


#: the Joseph-form update (see ``_joseph``, the one update every compiled Kalman filter runs), for
#: any number of rows
joseph_update = kernel(_joseph)
#: the same update copied into its caller, where constant sizes (both cameras, no time offset: ``m``
#: 4, ``nz`` 3) let the compiler unroll it (the same operations in the same order). One copy only:
#: each costs about a second of compilation
joseph_inlined = kernel(inline=True)(_joseph)
