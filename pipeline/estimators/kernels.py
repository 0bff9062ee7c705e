"""Compiled cores of the estimators whose per-frame loop is the cost: Algorithm 1 (SPSA) and the EKF,
single track and batch, ``spsa_stereo``'s frame update, and the Rauch–Tung–Striebel backward pass of
the smoothers. Each core is plain Python over float arrays, compiled by numba (``njit``, cached on
disk, so a fresh process loads it instead of compiling) and run as it is when ``STEREOTRACK_JIT=0``
is set before this module is imported (:func:`uncompiled` loads such a copy: the tests run both and
compare). The estimators import this module on the first ``run`` that takes the compiled path
(:func:`pipeline.estimators.base.use_compiled`), so neither ``import pipeline``, the streaming
``step`` nor a short clip pays for numba.

The equations are the estimators' own (see :mod:`pipeline.estimators.spsa`,
:mod:`pipeline.estimators.spsa_stereo` and :mod:`pipeline.estimators.ekf`, after Krivokon 2011,
Algorithm 1 and App. I), and the measurement model is
:meth:`pipeline.core.camera.StereoMeasurementModel.linearize` written out for one state. Algorithm 1
and ``spsa_stereo`` are the same operations in the same order; the EKF differs in rounding only (the
prediction by blocks, the covariance's upper triangle mirrored, small inverses by Gauss–Jordan
rather than LAPACK), and the tests hold every path equal to 1e-9.
"""

from __future__ import annotations

import importlib.util
import math
import os
import sys
from types import ModuleType

import numpy as np

JIT = os.environ.get("STEREOTRACK_JIT", "1") != "0"

if JIT:
    from numba import njit

    def kernel(fn=None, *, signature: str | None = None, inline: bool = False):
        """Compile ``fn`` with numba on its first call (cached on disk across processes); with a
        ``signature``, for those argument types only (one compilation for every caller); ``inline``:
        copied into each caller, where constant sizes let the compiler unroll its loops."""
        def wrap(f):
            if inline:
                return njit(cache=True, nogil=True, inline="always")(f)
            return njit(signature, cache=True, nogil=True)(f) if signature else njit(cache=True, nogil=True)(f)
        return wrap if fn is None else wrap(fn)
else:
    def kernel(fn=None, *, signature: str | None = None, inline: bool = False):
        return (lambda f: f) if fn is None else fn

def uncompiled() -> ModuleType:
    """This module loaded once more with every kernel left as plain Python (for the tests)."""
    name = __name__ + "_python"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, __file__)
    assert spec is not None and spec.loader is not None  # a file that exists: this one
    module = importlib.util.module_from_spec(spec)
    before = os.environ.get("STEREOTRACK_JIT")
    os.environ["STEREOTRACK_JIT"] = "0"
    try:
        spec.loader.exec_module(module)
    finally:
        if before is None:
            del os.environ["STEREOTRACK_JIT"]
        else:
            os.environ["STEREOTRACK_JIT"] = before
    sys.modules[name] = module
    return module


BIG_COST = 1.0e6  # a trial point behind a camera, as pipeline.estimators.spsa.BIG_COST (which must not import numba)

# -- SPSA (Algorithm 1) -------------------------------------------------------------------------
#: layout of an SPSA track's state vector ``s``: θ (frame units), phase, Δ index, the odd frame's
#: trial point (3), its normalized observation (4) and which of its cameras were present (2)
S_THETA, S_PHASE, S_IT, S_XO, S_YO, S_OK = 0, 6, 7, 8, 11, 15
S_SIZE = 17


@kernel(inline=True)
def spsa_cost(p0, p1, p2, y0, y1, y2, y3, use_l, use_r, cams):
    """``‖h(p) − y‖²`` in normalized coordinates (``y``: left u, v, right u, v) over the cameras in
    use (``cams``: 2 × 12, each camera's R row-major then t); a trial point behind a camera costs
    ``BIG_COST``. Copied into its caller (a call per trial point cost an eighth of a batch's time)."""
    c = 0.0
    for i in range(2):
        if (use_l if i == 0 else use_r):
            r = cams[i]
            z = r[6] * p0 + r[7] * p1 + r[8] * p2 + r[11]
            if z <= 1e-9:
                return BIG_COST
            du = (r[0] * p0 + r[1] * p1 + r[2] * p2 + r[9]) / z - (y0 if i == 0 else y2)
            dv = (r[3] * p0 + r[4] * p1 + r[5] * p2 + r[10]) / z - (y1 if i == 0 else y3)
            c += du * du + dv * dv
    return c


@kernel
def spsa_frames(Yn, okl, okr, deltas, cams, alpha, beta, th, s, states, pred):
    """Algorithm 1 over the frames of ``Yn`` (normalized, frames × 4; ``okl``/``okr``: cameras
    present) from the track state ``s`` (layout ``S_*``), writing θ (frames × 6) and whether each
    frame only predicted; ``s`` is left at the state after the last frame (so :meth:`step` can
    call it one frame at a time). The state lives in local variables inside the loop (the compiler
    keeps them in registers; the arithmetic is the same)."""
    b = beta
    t0, t1, t2, t3, t4, t5 = s[0], s[1], s[2], s[3], s[4], s[5]
    phase, i = s[S_PHASE], int(s[S_IT])
    xo0, xo1, xo2 = s[S_XO], s[S_XO + 1], s[S_XO + 2]
    yo0, yo1, yo2, yo3 = s[S_YO], s[S_YO + 1], s[S_YO + 2], s[S_YO + 3]
    okl_o, okr_o = s[S_OK] > 0.0, s[S_OK + 1] > 0.0
    for j in range(Yn.shape[0]):
        D = deltas[i]
        if phase == 0.0:  # x_{2k−1} = A(θ − βΔ); θ_{2k−1} = Aθ
            xo0, xo1, xo2 = t0 - b * D[0] + t3 - b * D[3], t1 - b * D[1] + t4 - b * D[4], t2 - b * D[2] + t5 - b * D[5]
            states[j, 0], states[j, 1], states[j, 2] = t0 + t3, t1 + t4, t2 + t5
            states[j, 3], states[j, 4], states[j, 5] = t3, t4, t5
            yo0, yo1, yo2, yo3 = Yn[j, 0], Yn[j, 1], Yn[j, 2], Yn[j, 3]
            okl_o, okr_o = okl[j], okr[j]
            pred[j] = not (okl_o or okr_o)
            phase = 1.0
            continue
        phase = 0.0  # x_{2k} = A²(θ + βΔ); θ_{2k} = A²θ − αΔd
        use_l, use_r = okl[j] and okl_o, okr[j] and okr_o
        n0, n1, n2, n3, n4, n5 = t0 + 2 * t3, t1 + 2 * t4, t2 + 2 * t5, t3, t4, t5
        if use_l or use_r:
            xe0 = t0 + b * D[0] + 2 * (t3 + b * D[3])
            xe1 = t1 + b * D[1] + 2 * (t4 + b * D[4])
            xe2 = t2 + b * D[2] + 2 * (t5 + b * D[5])
            z_odd = spsa_cost(xo0, xo1, xo2, yo0, yo1, yo2, yo3, use_l, use_r, cams)
            z_even = spsa_cost(xe0, xe1, xe2, Yn[j, 0], Yn[j, 1], Yn[j, 2], Yn[j, 3], use_l, use_r, cams)
            d = (z_even - z_odd) / (2 * b)
            if d > th:
                d = th
            elif d < -th:
                d = -th
            if d == d:  # not NaN
                ad = alpha * d
                n0, n1, n2 = n0 - ad * D[0], n1 - ad * D[1], n2 - ad * D[2]
                n3, n4, n5 = n3 - ad * D[3], n4 - ad * D[4], n5 - ad * D[5]
        t0, t1, t2, t3, t4, t5 = n0, n1, n2, n3, n4, n5
        states[j, 0], states[j, 1], states[j, 2], states[j, 3], states[j, 4], states[j, 5] = n0, n1, n2, n3, n4, n5
        i += 1
        pred[j] = not (use_l or use_r)
    s[0], s[1], s[2], s[3], s[4], s[5] = t0, t1, t2, t3, t4, t5
    s[S_PHASE], s[S_IT] = phase, i
    s[S_XO], s[S_XO + 1], s[S_XO + 2] = xo0, xo1, xo2
    s[S_YO], s[S_YO + 1], s[S_YO + 2], s[S_YO + 3] = yo0, yo1, yo2, yo3
    s[S_OK], s[S_OK + 1] = 1.0 if okl_o else 0.0, 1.0 if okr_o else 0.0


@kernel
def spsa_batch(Y, Ks, begin, theta0, deltas, cams, alpha, beta, th, out):
    """Algorithm 1 over M tracks (``Y`` M × frames × 4 pixels), each from ``theta0[m]`` at its frame
    ``begin[m]`` (none when ``begin[m]`` is the clip's length); positions into ``out`` (M × frames ×
    3). Each track's pixels are normalized here through the cameras' intrinsics ``Ks`` (2 × 3 × 3),
    with :meth:`Camera.normalize`'s arithmetic."""
    M, n = Y.shape[0], Y.shape[1]
    states, Yn = np.empty((n, 6)), np.empty((n, 4))
    pred, okl, okr = np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_)
    s = np.zeros(S_SIZE)
    for m in range(M):
        k0 = begin[m]
        if k0 >= n:
            continue
        for k in range(k0 + 1, n):
            for c in range(2):
                K, u, v = Ks[c], Y[m, k, 2 * c], Y[m, k, 2 * c + 1]
                Yn[k, 2 * c] = (u - K[0, 2] - K[0, 1] * (v - K[1, 2]) / K[1, 1]) / K[0, 0]
                Yn[k, 2 * c + 1] = (v - K[1, 2]) / K[1, 1]
            okl[k] = math.isfinite(Y[m, k, 0]) and math.isfinite(Y[m, k, 1])
            okr[k] = math.isfinite(Y[m, k, 2]) and math.isfinite(Y[m, k, 3])
        for a in range(S_SIZE):
            s[a] = theta0[m, a] if a < 6 else 0.0
        spsa_frames(Yn[k0 + 1 :], okl[k0 + 1 :], okr[k0 + 1 :], deltas, cams, alpha, beta, th, s, states[k0 + 1 :],
                    pred[k0 + 1 :])
        for a in range(3):
            out[m, k0, a] = theta0[m, a]
            for j in range(k0 + 1, n):
                out[m, j, a] = states[j, a]


# -- EKF ----------------------------------------------------------------------------------------
#: counters of a gated track: frames in a row with a camera gated, frames unseen, returning frames
#: left (see pipeline.estimators.kalman_common.after_gap)
C_GATED, C_UNSEEN, C_RETURNING = 0, 1, 2


@kernel
def stereo_linearize(Pm, delta, x, h, H):
    """``h(x)`` (4) and ``∂h/∂x`` (4 × 6) of one state through both cameras' 3 × 4 matrices
    ``Pm`` (2 × 3 × 4), the right camera seeing ``p + v·δ``: the arithmetic of
    :meth:`StereoMeasurementModel.linearize`."""
    for c in range(2):
        dc = delta if c == 1 else 0.0
        p0, p1, p2 = x[0] + x[3] * dc, x[1] + x[4] * dc, x[2] + x[5] * dc
        q2 = Pm[c, 2, 0] * p0 + Pm[c, 2, 1] * p1 + Pm[c, 2, 2] * p2 + Pm[c, 2, 3]
        for r in range(2):
            uv = (Pm[c, r, 0] * p0 + Pm[c, r, 1] * p1 + Pm[c, r, 2] * p2 + Pm[c, r, 3]) / q2
            h[2 * c + r] = uv
            for a in range(3):
                J = (Pm[c, r, a] - uv * Pm[c, 2, a]) / q2
                H[2 * c + r, a] = J
                H[2 * c + r, 3 + a] = dc * J


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
def camera_nis2(S, r, c):
    """Camera ``c``'s ``rᵀ S_c⁻¹ r`` from its 2 × 2 block of ``S`` in closed form (NaN stays NaN)."""
    i = 2 * c
    a, b, d = S[i, i], S[i, i + 1], S[i + 1, i + 1]
    u, v = r[i], r[i + 1]
    return (d * u * u - 2.0 * b * u * v + a * v * v) / (a * d - b * b)


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


@kernel
def joseph_update(x, P, Hs, rs, Rs, m, nz, PHt, S, Si, K, IKH, T6, KR, work, have_S):
    """The Joseph-form update on ``m`` observation rows (``Hs`` m × 6, residual ``rs``, noise
    ``Rs``; x, P in place), returning the NIS ``rᵀ S⁻¹ r``: ``S = H P Hᵀ + R``, ``K = P Hᵀ S⁻¹``,
    ``x ← x + K r``, ``P ← (I − KH) P (I − KH)ᵀ + K R Kᵀ`` (its upper triangle, mirrored: a covariance
    is symmetric). Only the first ``nz`` columns of ``H``
    are nonzero (3 without a time offset: the velocity does not enter ``h``), and the products
    skip the zeros (sums of the same nonzero terms in the same order as the full products).
    ``have_S``: ``PHt`` and ``S`` hold ``P Hᵀ`` and ``S`` already (the gate's, for four rows)."""
    if not have_S:
        mm(P, Hs, PHt, 6, nz, m, True)
        mm(Hs, PHt, S, m, nz, m, False)
        for i in range(m):
            for j in range(m):
                S[i, j] += Rs[i, j]
    inv_small(S, m, Si, work)
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


@kernel
def ekf_frames(Y, k0, resume, Pm, delta, dt, Q, R, threshold, restart_after, x, P, counters, scratch_x, scratch_P,
               pos, vel, cov, pred, nis, dof, gated, restarted):
    """The EKF over frames ``k0…`` of ``Y`` (frames × 4 px, NaN missing) from ``x``, ``P`` (in place),
    gating each camera at ``threshold`` (inf: off) as ``GatedFilter.gate`` does. Returns the clip's
    length, or the frame at which the track was gated ``restart_after`` frames: the caller asks for a
    restart and calls again with ``resume`` 1 (restart state in ``x``, ``P``) or 2 (none: update with
    what the gate kept; prediction and verdict kept in ``scratch_x``, ``scratch_P``, ``counters[3:]``)."""
    n = Y.shape[0]
    h, kept, r, rs, rows = np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4, dtype=np.int64)
    H, Hs, Rs, S, Si, work = np.empty((4, 6)), np.empty((4, 6)), np.empty((4, 4)), np.empty((4, 4)), np.empty((4, 4)), \
        np.empty((4, 4))
    T6, IKH, PHt, K, KR = np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 4)), np.empty((6, 4)), np.empty((6, 4))
    nz, gate_on = 6 if delta != 0.0 else 3, threshold < np.inf  # the nonzero columns of H; gating
    for k in range(k0, n):
        if k == k0 and resume == 1:  # restarted at this frame: a new start, no update
            _restarted(k, x, P, counters, pos, vel, cov, pred, gated, restarted)
            continue
        for i in range(4):
            kept[i] = Y[k, i]
        resumed = k == k0 and resume == 2
        if resumed:  # the prediction and the gate's verdict from before the restart was asked for
            n_gated = _resume(scratch_x, scratch_P, x, P, counters, kept)
        else:
            ekf_predict(dt, Q, x, P)
            n_gated = 0
            if gate_on:
                stereo_linearize(Pm, delta, x, h, H)
                _gate_products(P, H, PHt, S, nz)
                for i in range(4):
                    r[i] = Y[k, i] - h[i]
                    for j in range(4):
                        S[i, j] += R[i, j]
                had = False
                for c in range(2):
                    counters[4 + c] = 0
                    if camera_nis2(S, r, c) > threshold:
                        kept[2 * c], kept[2 * c + 1] = np.nan, np.nan
                        counters[4 + c] = 1
                        n_gated += 1
                    had = had or math.isfinite(Y[k, 2 * c]) or math.isfinite(Y[k, 2 * c + 1])
                _count_gated(counters, had, n_gated > 0, restart_after)
                if counters[C_GATED] >= restart_after:
                    _copy_state(x, P, scratch_x, scratch_P)
                    counters[3] = n_gated
                    return k
        gated[k], restarted[k] = n_gated, 0.0
        m = _present_rows(kept, rows)
        if m == 0:
            _ekf_output(k, x, P, pos, vel, cov, pred, True)
            continue
        have_S = gate_on and m == 4 and not resumed  # the gate's h, H, P Hᵀ and S are this update's
        if not have_S:
            stereo_linearize(Pm, delta, x, h, H)
        _gather_rows(rows, m, H, kept, h, R, Hs, rs, Rs)
        nis[k] = _update(x, P, Hs, rs, Rs, m, nz, PHt, S, Si, K, IKH, T6, KR, work, have_S)
        dof[k] = m
        _ekf_output(k, x, P, pos, vel, cov, pred, False)
    return n


@kernel
def ekf_batch(Y, begin, x0, P0, Pm, delta, dt, Q, R, threshold, restart_after, out):
    """:func:`ekf_frames` over M tracks (``Y`` M × frames × 4), each from ``x0[m]``, ``P0[m]`` at its
    frame ``begin[m]`` (none when it is the clip's length), positions into ``out`` (M × frames × 3).
    Returns, per track, the frame at which it asked for a restart (the clip's length: none), for the
    caller to run those tracks again with their restarts."""
    M, n = Y.shape[0], Y.shape[1]
    vel, cov, pred = np.empty((n, 3)), np.empty((n, 6, 6)), np.empty(n, dtype=np.bool_)
    nis, gated, restarted, dof = np.empty(n), np.empty(n), np.empty(n), np.empty(n, dtype=np.int64)
    x, P, counters, sx, sP = np.empty(6), np.empty((6, 6)), np.zeros(6, dtype=np.int64), np.empty(6), np.empty((6, 6))
    stopped = np.full(M, n, dtype=np.int64)
    for m in range(M):
        k0 = begin[m]
        if k0 >= n:
            continue
        _copy_state(x0[m], P0[m], x, P)
        for a in range(6):
            counters[a] = 0
        for a in range(3):
            out[m, k0, a] = x[a]
        stopped[m] = ekf_frames(Y[m], k0 + 1, 0, Pm, delta, dt, Q, R, threshold, restart_after, x, P, counters, sx, sP,
                                out[m], vel, cov, pred, nis, dof, gated, restarted)
    return stopped


@kernel(inline=True)
def _gate_products(P, H, PHt, S, nz):
    """The gate's ``P Hᵀ`` and ``H P Hᵀ`` on all four rows, the sizes written as constants."""
    if nz == 3:
        mm(P, H, PHt, 6, 3, 4, True)
        mm(H, PHt, S, 4, 3, 4, False)
    else:
        mm(P, H, PHt, 6, 6, 4, True)
        mm(H, PHt, S, 4, 6, 4, False)


#: :func:`joseph_update` copied into its caller, where constant sizes let the compiler unroll it
_joseph_inlined = kernel(inline=True)(getattr(joseph_update, "py_func", joseph_update))


@kernel
def _update(x, P, Hs, rs, Rs, m, nz, PHt, S, Si, K, IKH, T6, KR, work, have_S):
    """:func:`joseph_update`; in the common case (both cameras, no time offset: ``m`` 4, ``nz`` 3)
    a copy with the sizes written as constants, which the compiler unrolls (the same operations in
    the same order). One copy only: each costs about a second of compilation."""
    if m == 4 and nz == 3:
        return _joseph_inlined(x, P, Hs, rs, Rs, 4, 3, PHt, S, Si, K, IKH, T6, KR, work, have_S)
    return joseph_update(x, P, Hs, rs, Rs, m, nz, PHt, S, Si, K, IKH, T6, KR, work, have_S)


@kernel
def _restarted(k, x, P, counters, pos, vel, cov, pred, gated, restarted):
    """Frame ``k`` is a restart: the new start is its output, with the cameras the gate dropped."""
    counters[C_GATED] = 0
    _ekf_output(k, x, P, pos, vel, cov, pred, False)
    gated[k], restarted[k] = counters[3], 1.0


@kernel
def _gather_rows(rows, m, H, y, h, R, Hs, rs, Rs):
    """The update's ``H``, residual and ``R`` on the ``m`` rows present."""
    for i in range(m):
        for j in range(6):
            Hs[i, j] = H[rows[i], j]
        rs[i] = y[rows[i]] - h[rows[i]]
        for j in range(m):
            Rs[i, j] = R[rows[i], rows[j]]


@kernel
def _present_rows(kept, rows):
    """The observation rows present (both coordinates of a camera together) into ``rows``; how many."""
    m = 0
    for i in range(4):
        if math.isfinite(kept[i]) and math.isfinite(kept[i ^ 1]):
            rows[m] = i
            m += 1
    return m


@kernel
def _resume(scratch_x, scratch_P, x, P, counters, kept):
    """Back at the frame a restart was asked for: its prediction, and the gate's verdict on ``kept``."""
    _copy_state(scratch_x, scratch_P, x, P)
    for c in range(2):
        if counters[4 + c] != 0:
            kept[2 * c], kept[2 * c + 1] = np.nan, np.nan
    return counters[3]


@kernel
def _copy_state(x, P, to_x, to_P):
    for i in range(6):
        to_x[i] = x[i]
        for j in range(6):
            to_P[i, j] = P[i, j]


@kernel
def _count_gated(counters, had, gated, restart_after):
    """The gated-run, unseen and returning counters after one frame (``after_gap``'s arithmetic)."""
    run = counters[C_GATED] + 1 if gated else (0 if had else counters[C_GATED])
    unseen, returning = counters[C_UNSEEN], counters[C_RETURNING]
    if had and unseen >= restart_after:
        returning = restart_after
    if gated and returning > 0:
        run = max(run, restart_after)
    if had:
        returning = max(returning - 1, 0)
    unseen = 0 if had else unseen + 1
    counters[C_GATED], counters[C_UNSEEN], counters[C_RETURNING] = run, unseen, returning


@kernel
def _ekf_output(k, x, P, pos, vel, cov, pred, predicted):
    for i in range(3):
        pos[k, i] = x[i]
        vel[k, i] = x[3 + i]
    for i in range(6):
        for j in range(6):
            cov[k, i, j] = P[i, j]
    pred[k] = predicted


@kernel
def rts_backward(xs, Ps, dt, Q):
    """The Rauch–Tung–Striebel backward pass over filtered states ``xs`` (n × 6) and covariances
    ``Ps`` (n × 6 × 6), in place, for the constant-velocity ``A = [[I, dt·I], [0, I]]`` (filterpy's
    ``rts_smoother``)::

        P⁻ = A Pₖ Aᵀ + Q,  Cₖ = Pₖ Aᵀ (P⁻)⁻¹,  xₖ ← xₖ + Cₖ (xₖ₊₁ − A xₖ),  Pₖ ← Pₖ + Cₖ (Pₖ₊₁ − P⁻) Cₖᵀ
    """
    xp, Pp, Pi, work = np.empty(6), np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6))
    PAt, C, D, T = np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6)), np.empty((6, 6))
    for k in range(xs.shape[0] - 2, -1, -1):
        for i in range(6):
            xp[i] = xs[k, i]
            for j in range(6):
                Pp[i, j] = Ps[k, i, j]
        ekf_predict(dt, Q, xp, Pp)  # A x, A P Aᵀ + Q
        for i in range(6):  # P Aᵀ: columns j < 3 gain dt × column j + 3
            for j in range(6):
                PAt[i, j] = Ps[k, i, j] + dt * Ps[k, i, j + 3] if j < 3 else Ps[k, i, j]
        inv_small(Pp, 6, Pi, work)
        mm6(PAt, Pi, C, False)
        for i in range(6):
            acc = 0.0
            for j in range(6):
                acc += C[i, j] * (xs[k + 1, j] - xp[j])
                D[i, j] = Ps[k + 1, i, j] - Pp[i, j]
            xs[k, i] += acc
        mm6(C, D, T, False)
        mm6(T, C, D, True)
        for i in range(6):
            for j in range(6):
                Ps[k, i, j] += D[i, j]


# -- spsa_stereo ----------------------------------------------------------------------------------
#: layout of a ``spsa_stereo`` track's state ``t``: position, velocity (m, m/s), each coordinate's
#: memory n, its run of same-signed innovations, its last innovation, and the run of gated frames
T_P, T_V, T_MEM, T_RUN, T_SGN, T_GRUN = 0, 3, 6, 9, 12, 15
T_SIZE = 16
#: layout of its parameters ``prm``: the rectifying frame (R row-major, t), the baseline, the two
#: disparity maps (3×4 row-major), both cameras' poses (R, t), fx·fy per camera, then scalars
P_R, P_T, P_B, P_AL, P_AR, P_POSE, P_F2 = 0, 9, 12, 13, 25, 37, 61
P_DT, P_C, P_FAR, P_SWEEPS, P_COST_GATE, P_NIS_GATE, P_SIGMA2, P_NMAX, P_KD, P_AMIN_D, P_RUNLEN, P_RESTART = range(63, 75)
P_SIZE = 75
#: the robust scale's recent NIS values (``RobustNISScale``): a ring in arrival order, the same
#: values sorted (the median without sorting every frame), count, next slot, the scale, its floor
SC_MEMORY = 30
SC_SORTED = 30
SC_COUNT, SC_HEAD, SC_VALUE, SC_MIN = 60, 61, 62, 63
SC_SIZE = 64
LN4 = math.log(4.0)
DIAGONALS = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, -1.0], [1.0, -1.0, 1.0], [-1.0, 1.0, 1.0]])


@kernel
def st_cost(q0, q1, q2, yn, use_l, use_r, prm):
    """``J(q) = ‖h(g⁻¹(q)) − y‖²`` through the disparity maps (``SPSAStereoEstimator.cost``)."""
    s0, s1, s2 = q0, q1, q0 - q2
    if s2 <= 1e-12:
        return BIG_COST
    c = 0.0
    for cam in range(2):
        if (use_l if cam == 0 else use_r):
            a = P_AL if cam == 0 else P_AR
            w = prm[a + 8] * s0 + prm[a + 9] * s1 + prm[a + 10] + prm[a + 11] * s2
            if w <= 1e-12:
                return BIG_COST
            du = (prm[a] * s0 + prm[a + 1] * s1 + prm[a + 2] + prm[a + 3] * s2) / w - yn[2 * cam]
            dv = (prm[a + 4] * s0 + prm[a + 5] * s1 + prm[a + 6] + prm[a + 7] * s2) / w - yn[2 * cam + 1]
            c += du * du + dv * dv
    return c


@kernel
def st_minimise(q0, q1, q2, yn, use_l, use_r, prm):
    """Simultaneous-perturbation Newton steps on the frame's cost (``SPSAStereoEstimator._minimise``)."""
    c = prm[P_C]
    J0 = st_cost(q0, q1, q2, yn, use_l, use_r, prm)
    one = use_l != use_r
    s1 = math.sqrt(0.5) if (use_l and use_r) else 1.0
    dim = 2.0 if one else 3.0
    for _ in range(int(prm[P_SWEEPS])):
        g0 = g1 = g2 = hsum = 0.0
        for i in range(4):
            D0, D1, D2 = DIAGONALS[i, 0], DIAGONALS[i, 1], DIAGONALS[i, 2]
            d0, d1, d2 = D0, D1 * s1, (D0 if one else D2)
            Jp = st_cost(q0 + c * d0, q1 + c * d1, q2 + c * d2, yn, use_l, use_r, prm)
            Jm = st_cost(q0 - c * d0, q1 - c * d1, q2 - c * d2, yn, use_l, use_r, prm)
            d = Jp - Jm
            g0 += D0 * d
            g1 += D1 * d
            g2 += (D0 if one else D2) * d
            hsum += Jp + Jm - 2.0 * J0
        if not hsum > 0.0:
            break
        k = dim * c / (2.0 * hsum)
        t0, t1, t2 = k * g0, k * g1 * s1, k * g2
        while (q0 - t0) - (q2 - t2) <= 1e-12:
            t0, t1, t2 = 0.5 * t0, 0.5 * t1, 0.5 * t2
        J1 = st_cost(q0 - t0, q1 - t1, q2 - t2, yn, use_l, use_r, prm)
        if not J1 < J0:
            break
        q0, q1, q2, J0 = q0 - t0, q1 - t1, q2 - t2, J1
        if max(abs(t0), abs(t1), abs(t2)) < prm[P_FAR]:
            break
    return q0, q1, q2, J0


@kernel
def st_g(p0, p1, p2, prm, q):
    """``q = g(p)`` into ``q``; False behind the rectifying frame (``SPSAStereoEstimator.g``)."""
    x = prm[P_R] * p0 + prm[P_R + 1] * p1 + prm[P_R + 2] * p2 + prm[P_T]
    y = prm[P_R + 3] * p0 + prm[P_R + 4] * p1 + prm[P_R + 5] * p2 + prm[P_T + 1]
    z = prm[P_R + 6] * p0 + prm[P_R + 7] * p1 + prm[P_R + 8] * p2 + prm[P_T + 2]
    if z <= 1e-9:
        return False
    q[0], q[1], q[2] = x / z, y / z, (x - prm[P_B]) / z
    return True


@kernel
def st_g_inv(q0, q1, q2, prm, out, at):
    """``g⁻¹(q)`` into ``out[at:at + 3]`` (``SPSAStereoEstimator.g_inv``)."""
    z = prm[P_B] / (q0 - q2)
    a, b, c = q0 * z - prm[P_T], q1 * z - prm[P_T + 1], z - prm[P_T + 2]
    out[at] = prm[P_R] * a + prm[P_R + 3] * b + prm[P_R + 6] * c
    out[at + 1] = prm[P_R + 1] * a + prm[P_R + 4] * b + prm[P_R + 7] * c
    out[at + 2] = prm[P_R + 2] * a + prm[P_R + 5] * b + prm[P_R + 8] * c


@kernel
def st_scale_add(sc, nis):
    """``RobustNISScale.add`` of one value: the oldest value leaves the sorted copy when the ring
    is full, the new one is inserted in order, and the scale is their median over ln 4, at least
    the floor."""
    if not math.isfinite(nis):
        return
    m, h, srt = int(sc[SC_COUNT]), int(sc[SC_HEAD]), SC_SORTED
    if m == SC_MEMORY:
        i = 0
        while sc[srt + i] != sc[h]:
            i += 1
        for r in range(i, m - 1):
            sc[srt + r] = sc[srt + r + 1]
        m -= 1
    i = m
    while i > 0 and sc[srt + i - 1] > nis:
        sc[srt + i] = sc[srt + i - 1]
        i -= 1
    sc[srt + i] = nis
    m += 1
    sc[h], sc[SC_HEAD], sc[SC_COUNT] = nis, (h + 1) % SC_MEMORY, m
    med = sc[srt + m // 2] if m % 2 else 0.5 * (sc[srt + m // 2 - 1] + sc[srt + m // 2])
    sc[SC_VALUE] = max(sc[SC_MIN], med / LN4)


@kernel
def st_gate(pp, yn, use_l, use_r, consistent, prm, sc):
    """``SPSAStereoEstimator._gate_cameras``: (use left, use right, cameras gated, whether the
    frame's ``consistent`` is needed and not known yet: NaN)."""
    for i in range(3):
        if not math.isfinite(pp[i]):
            return use_l, use_r, 0, False
    out_l, out_r, gated = use_l, use_r, 0
    for c in range(2):
        if (out_l if c == 0 else out_r):
            r = P_POSE + 12 * c
            x = prm[r] * pp[0] + prm[r + 1] * pp[1] + prm[r + 2] * pp[2] + prm[r + 9]
            y = prm[r + 3] * pp[0] + prm[r + 4] * pp[1] + prm[r + 5] * pp[2] + prm[r + 10]
            z = prm[r + 6] * pp[0] + prm[r + 7] * pp[1] + prm[r + 8] * pp[2] + prm[r + 11]
            nis = ((x / z - yn[2 * c]) ** 2 + (y / z - yn[2 * c + 1]) ** 2) * prm[P_F2 + c] / prm[P_SIGMA2]
            scale = sc[SC_VALUE]
            st_scale_add(sc, nis)
            if nis / scale > prm[P_NIS_GATE]:
                gated += 1
                if c == 0:
                    out_l = False
                else:
                    out_r = False
    if gated == 2:
        if math.isnan(consistent):
            return use_l, use_r, gated, True
        if consistent > 0.0:
            return use_l, use_r, 0, False
    return out_l, out_r, gated, False


@kernel
def st_memory(t, i, e, cap, runlen):
    """Kesten's rule on coordinate ``i``'s memory (``SPSAStereoEstimator._memory``)."""
    same = (e > 0.0) == (t[T_SGN + i] > 0.0)
    t[T_SGN + i] = e
    t[T_RUN + i] = t[T_RUN + i] + 1 if same else 0
    if t[T_RUN + i] >= runlen:
        t[T_MEM + i] = max(1.0, 0.5 * t[T_MEM + i])
        t[T_RUN + i] = 0
    else:
        t[T_MEM + i] = min(t[T_MEM + i] + 1.0, cap)
    return t[T_MEM + i]


@kernel
def st_gains(n):
    """(α, β/α) of the growing-memory line fit after n corrections (``SPSAStereoEstimator._gains``)."""
    if n <= 1.0:
        return 1.0, 0.0
    return 2.0 * (2 * n - 1) / (n * (n + 1)), 3.0 / (2 * n - 1)


@kernel
def st_max_memory(alpha):
    """The memory at which the growing-memory gain falls to α (``spsa_stereo.max_memory``)."""
    return ((4 - alpha) + math.sqrt((4 - alpha) ** 2 - 8 * alpha)) / (2 * alpha)


@kernel
def st_begin(t, p0, p1, p2, v0, v1, v2, memory):
    """A fresh start at ``(p, v)`` with ``memory`` frames of evidence (``SPSAStereoEstimator._begin``)."""
    t[T_P], t[T_P + 1], t[T_P + 2], t[T_V], t[T_V + 1], t[T_V + 2] = p0, p1, p2, v0, v1, v2
    for i in range(3):
        t[T_MEM + i], t[T_RUN + i], t[T_SGN + i] = memory, 0.0, 0.0


@kernel
def st_correct(t, q, h0, h1, h2, prm, w):
    """The line-fit correction of (x/z, y/z, b/z) and the velocity from it (the end of
    ``SPSAStereoEstimator._update``); the image coordinates' gain α."""
    e0, e1, ed = h0 - q[0], h1 - q[1], (h0 - h2) - (q[0] - q[2])
    dd = q[0] - q[2]
    runlen = prm[P_RUNLEN]
    a0, r0 = st_gains(st_memory(t, 0, e0, prm[P_NMAX], runlen))
    a1, r1 = st_gains(st_memory(t, 1, e1, prm[P_NMAX], runlen))
    cap = st_max_memory(min(1.0, max(prm[P_AMIN_D], prm[P_KD] * dd)))
    ad, rad = st_gains(st_memory(t, 2, ed, cap, runlen))
    d_new = dd + ad * ed
    if d_new <= 1e-12:
        d_new = dd
    x0, x1 = q[0] + a0 * e0, q[1] + a1 * e1
    st_g_inv(x0, x1, x0 - d_new, prm, w, 0)
    d_vel = dd + rad * ad * ed
    x0v, x1v = q[0] + r0 * a0 * e0, q[1] + r1 * a1 * e1
    if d_vel > 1e-12:
        st_g_inv(x0v, x1v, x0v - d_vel, prm, w, 3)
    else:
        w[3], w[4], w[5] = w[0], w[1], w[2]
    k = 1.0 / prm[P_DT]
    for i in range(3):
        t[T_V + i] = t[T_V + i] + k * (w[3 + i] - t[T_P + i])  # t[T_P] still holds the prediction
        t[T_P + i] = w[i]
    return a0


@kernel
def st_update(t, yn, use_l, use_r, consistent, tri, prm, sc, q, w):
    """One frame after the start (``SPSAStereoEstimator._update``): (predicted, cost, gain α,
    gated, need) where ``need`` asks for the frame's ``consistent`` (1) or ``tri`` (2) when they
    are not known yet (NaN; the state is then left half-updated: the caller restores it)."""
    for i in range(3):
        t[T_P + i] = t[T_P + i] + t[T_V + i] * prm[P_DT]
    if not (use_l or use_r):
        return True, math.nan, math.nan, 0, 0
    gated = 0
    if math.isfinite(prm[P_NIS_GATE]):
        use_l, use_r, gated, need = st_gate(t[T_P : T_P + 3], yn, use_l, use_r, consistent, prm, sc)
        if need:
            return True, math.nan, math.nan, gated, 1
        if not (use_l or use_r):
            return True, math.nan, math.nan, gated, 0
    if not st_g(t[T_P], t[T_P + 1], t[T_P + 2], prm, q):  # behind the camera: from the frame's own minimum
        if use_l and use_r and math.isnan(tri[3]):
            return True, math.nan, math.nan, gated, 2
        if not (use_l and use_r and st_g(tri[0], tri[1], tri[2], prm, q)) or not (
                math.isfinite(q[0]) and math.isfinite(q[1]) and math.isfinite(q[2])) or q[0] - q[2] <= 1e-12:
            return True, math.nan, math.nan, gated, 0
        h0, h1, h2, cost = st_minimise(q[0], q[1], q[2], yn, True, True, prm)
        st_g_inv(h0, h1, h2, prm, w, 0)
        st_begin(t, w[0], w[1], w[2], 0.0, 0.0, 0.0, 1.0)
        return False, cost, 1.0, gated, 0
    h0, h1, h2, cost = st_minimise(q[0], q[1], q[2], yn, use_l, use_r, prm)
    if cost > prm[P_COST_GATE] * (int(use_l) + int(use_r)):
        return True, cost, math.nan, gated, 0
    return False, cost, st_correct(t, q, h0, h1, h2, prm, w), gated, 0


#: why :func:`spsa_stereo_frames` stopped: the end, a restart to ask for, or a frame's
#: ``consistent`` or ``tri`` to compute (then that frame is run again)
ST_DONE, ST_RESTART, ST_CONSISTENT, ST_TRI = 0, 1, 2, 3


@kernel
def spsa_stereo_frames(Yn, okl, okr, consistent, tri, k0, prm, t, sc, states, pred, costs, gains, gated, restarts):
    """``spsa_stereo`` from frame ``k0`` on (``SPSAStereoEstimator._update`` and the count of gated
    frames, frame after frame): ``(frame, why)``. At a restart (the gated run reached
    ``restart_after``) the frame's outputs are written as if none and the caller asks the initiator.
    A frame that needs what only the caller computes (``consistent``: both cameras gated;
    ``tri``, row ``[x, y, z, known]``: a prediction behind the cameras) is undone, to be run again."""
    q, w, t0, sc0 = np.empty(3), np.empty(6), np.empty(T_SIZE), np.empty(SC_SIZE)
    for j in range(k0, Yn.shape[0]):
        t0[:], sc0[:] = t, sc
        p, cost, gain, g, need = st_update(t, Yn[j], okl[j], okr[j], consistent[j], tri[j], prm, sc, q, w)
        if need:
            t[:], sc[:] = t0, sc0
            return j, ST_CONSISTENT if need == 1 else ST_TRI
        had = okl[j] or okr[j]
        t[T_GRUN] = t[T_GRUN] + 1 if g else (0.0 if had else t[T_GRUN])
        for i in range(6):
            states[j, i] = t[i]
        pred[j], costs[j], gains[j], gated[j], restarts[j] = p, cost, gain, g, 0.0
        if t[T_GRUN] >= prm[P_RESTART]:
            return j, ST_RESTART
    return Yn.shape[0], ST_DONE


_warm: set[str] = set()


def warm_up(*names: str) -> None:
    """Compile, or load from numba's cache, the named kernels (``ekf_frames``, ``spsa_frames``,
    ``rts_backward``; all without names) once per process, each with the argument types the
    estimators pass, so that a timed loop times arithmetic, not compilation."""
    for name in names or ("ekf_frames", "spsa_frames", "rts_backward", "spsa_stereo_frames"):
        if name not in _warm:
            _warm.add(name)
            if JIT:
                _WARM_UPS[name]()


def _warm_ekf() -> None:
    n, f, z, I6 = 3, np.zeros, np.zeros, np.eye(6)
    ekf_frames(np.full((n, 4), np.nan), 1, 0, np.ones((2, 3, 4)), 0.0, 0.1, I6, np.eye(4), np.inf, 8, z(6), I6.copy(),
               z(6, dtype=np.int64), z(6), I6.copy(), f((n, 3)), f((n, 3)), f((n, 6, 6)), np.ones(n, dtype=np.bool_), f(n),
               z(n, dtype=np.int64), f(n), f(n))


def _warm_spsa() -> None:
    n = 3
    spsa_frames(np.full((n, 4), np.nan), np.zeros(n, np.bool_), np.zeros(n, np.bool_), np.ones((2, 6)), np.ones((2, 12)),
                0.1, 0.01, 0.03, np.zeros(S_SIZE), np.zeros((n, 6)), np.ones(n, dtype=np.bool_))


def _warm_spsa_stereo() -> None:
    n, f = 3, np.zeros
    spsa_stereo_frames(np.full((n, 4), np.nan), f(n, np.bool_), f(n, np.bool_), f(n), f((n, 4)), 0, f(P_SIZE),
                       f(T_SIZE), f(SC_SIZE), f((n, 6)), np.ones(n, dtype=np.bool_), f(n), f(n), f(n), f(n))


_WARM_UPS = {"ekf_frames": _warm_ekf, "spsa_frames": _warm_spsa, "spsa_stereo_frames": _warm_spsa_stereo,
             "rts_backward": lambda: rts_backward(np.zeros((3, 6)), np.stack([np.eye(6)] * 3), 0.1, np.eye(6))}
