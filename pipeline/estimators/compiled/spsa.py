"""Algorithm 1's compiled core (the twin of :mod:`pipeline.estimators.spsa`, after Krivokon 2011,
Algorithm 1): one track frame by frame, or a batch of tracks, with the same operations in the same
order as the estimator's streaming ``step``."""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np

from ._jit import kernel

BIG_COST = 1.0e6  # a trial point behind a camera, as pipeline.estimators.spsa.BIG_COST (which must not import numba)

#: Algorithm 1's three parameters: step α, perturbation β and the projection rule's bound ``th``
SPSAGains = namedtuple("SPSAGains", ["alpha", "beta", "th"])
#: an SPSA track's state between calls: θ (6, frame units), the iteration's phase (0: odd frame
#: next), the Δ index, the odd frame's trial point, its normalized observation and which of its
#: cameras were present
STATE = np.dtype([("theta", "f8", (6,)), ("phase", "f8"), ("it", "i8"), ("xo", "f8", (3,)), ("yo", "f8", (4,)),
                  ("ok_left", "b1"), ("ok_right", "b1")])


def new_state(theta: np.ndarray | list[float]) -> np.record:
    """A track's state at θ, before its first iteration (a record plain Python and the compiled
    code both read by field name)."""
    s = np.zeros(1, dtype=STATE).view(np.recarray)[0]
    s.theta[:] = theta
    return s


@kernel(inline=True)
def spsa_cost(p, y, use_l, use_r, cams):
    """``‖h(p) − y‖²`` in normalized coordinates (``y``: left u, v, right u, v) over the cameras in
    use (``cams``: 2 × 12, each camera's R row-major then t); a trial point behind a camera costs
    ``BIG_COST``. Copied into its caller (a call per trial point cost an eighth of a batch's time)."""
    p0, p1, p2 = p
    c = 0.0
    for i in range(2):
        if (use_l if i == 0 else use_r):
            r = cams[i]
            z = r[6] * p0 + r[7] * p1 + r[8] * p2 + r[11]
            if z <= 1e-9:
                return BIG_COST
            du = (r[0] * p0 + r[1] * p1 + r[2] * p2 + r[9]) / z - (y[0] if i == 0 else y[2])
            dv = (r[3] * p0 + r[4] * p1 + r[5] * p2 + r[10]) / z - (y[1] if i == 0 else y[3])
            c += du * du + dv * dv
    return c


@kernel
def spsa_frames(Yn, okl, okr, deltas, cams, gains, s, states, pred):
    """Algorithm 1 over the frames of ``Yn`` (normalized, frames × 4; ``okl``/``okr``: cameras
    present) from the track state ``s`` (a :data:`STATE` record), writing θ (frames × 6) and
    whether each frame only predicted; ``s`` is left at the state after the last frame (so
    :meth:`step` can call it one frame at a time). The state lives in local variables inside the
    loop (the compiler keeps them in registers; the arithmetic is the same)."""
    b, alpha, th = gains.beta, gains.alpha, gains.th
    t0, t1, t2, t3, t4, t5 = s.theta[0], s.theta[1], s.theta[2], s.theta[3], s.theta[4], s.theta[5]
    phase, i = s.phase, s.it
    xo0, xo1, xo2 = s.xo[0], s.xo[1], s.xo[2]
    yo0, yo1, yo2, yo3 = s.yo[0], s.yo[1], s.yo[2], s.yo[3]
    okl_o, okr_o = s.ok_left, s.ok_right
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
            z_odd = spsa_cost((xo0, xo1, xo2), (yo0, yo1, yo2, yo3), use_l, use_r, cams)
            z_even = spsa_cost((xe0, xe1, xe2), (Yn[j, 0], Yn[j, 1], Yn[j, 2], Yn[j, 3]), use_l, use_r, cams)
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
    s.theta[0], s.theta[1], s.theta[2], s.theta[3], s.theta[4], s.theta[5] = t0, t1, t2, t3, t4, t5
    s.phase, s.it = phase, i
    s.xo[0], s.xo[1], s.xo[2] = xo0, xo1, xo2
    s.yo[0], s.yo[1], s.yo[2], s.yo[3] = yo0, yo1, yo2, yo3
    s.ok_left, s.ok_right = okl_o, okr_o


@kernel
def spsa_batch(Y, Ks, begin, theta0, deltas, cams, gains, s, out):
    """Algorithm 1 over M tracks (``Y`` M × frames × 4 pixels), each from ``theta0[m]`` at its frame
    ``begin[m]`` (none when ``begin[m]`` is the clip's length), through the scratch state ``s``;
    positions into ``out`` (M × frames × 3). Each track's pixels are normalized here through the
    cameras' intrinsics ``Ks`` (2 × 3 × 3), with :meth:`Camera.normalize`'s arithmetic."""
    M, n = Y.shape[0], Y.shape[1]
    states, Yn = np.empty((n, 6)), np.empty((n, 4))
    pred, okl, okr = np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_), np.empty(n, dtype=np.bool_)
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
        for a in range(6):
            s.theta[a] = theta0[m, a]
        s.phase, s.it = 0.0, 0
        for a in range(3):
            s.xo[a] = 0.0
        for a in range(4):
            s.yo[a] = 0.0
        s.ok_left, s.ok_right = False, False
        spsa_frames(Yn[k0 + 1 :], okl[k0 + 1 :], okr[k0 + 1 :], deltas, cams, gains, s, states[k0 + 1 :],
                    pred[k0 + 1 :])
        for a in range(3):
            out[m, k0, a] = theta0[m, a]
            for j in range(k0 + 1, n):
                out[m, j, a] = states[j, a]
