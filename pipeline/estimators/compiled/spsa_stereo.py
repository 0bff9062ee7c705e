"""``spsa_stereo``'s compiled core (the twin of :mod:`pipeline.estimators.spsa_stereo`): the
frame update in the rectified disparity coordinates, its simultaneous-perturbation Newton steps,
the growing-memory line fit with Kesten's rule, the robust NIS scale and the gate, frame after
frame, with the same operations in the same order as the estimator's streaming ``step``."""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np

from ._jit import kernel
from .spsa import BIG_COST

#: what the update reads besides the frames (made once per estimator; a record, passed to each
#: function as one pointer): the rectifying frame ``R`` (row-major, 9) and ``t``, the baseline ``b``,
#: the two disparity maps ``AL``, ``AR`` (3 × 4 row-major, 12 each), both cameras' poses (2 × 12: R
#: row-major, t), fx·fy per camera ``f2``, then the frame step, the perturbation size ``c``, the step
#: below which the search stops (``far``), Newton sweeps, the cost gate, the NIS gate, σ², the image
#: coordinates' largest memory, the disparity's memory slope ``kd`` and floor ``amin_d``, Kesten's run
#: length and the gated run that asks for a restart
PARAMS = np.dtype([("R", "f8", (9,)), ("t", "f8", (3,)), ("b", "f8"), ("AL", "f8", (12,)), ("AR", "f8", (12,)),
                   ("poses", "f8", (2, 12)), ("f2", "f8", (2,))]
                  + [(k, "f8") for k in ("dt", "c", "far", "sweeps", "cost_gate", "nis_gate", "sigma2", "nmax", "kd",
                                         "amin_d", "runlen", "restart")])
#: a track's state: position, velocity (m, m/s), each coordinate's memory n, its run of same-signed
#: innovations and its last innovation, and the run of gated frames
TRACK = np.dtype([("p", "f8", (3,)), ("v", "f8", (3,)), ("mem", "f8", (3,)), ("run", "f8", (3,)), ("sgn", "f8", (3,)),
                  ("grun", "f8")])
#: the robust scale's recent NIS values (``RobustNISScale``): a ring in arrival order, the same values
#: sorted (the median without sorting every frame), count, next slot, the scale, its floor
SC_MEMORY = 30
SCALE = np.dtype([("ring", "f8", (SC_MEMORY,)), ("sorted", "f8", (SC_MEMORY,)), ("count", "i8"), ("head", "i8"),
                  ("value", "f8"), ("floor", "f8")])
#: a track's records: its state and robust scale, and room to undo a frame (``*_saved``)
StereoTrack = namedtuple("StereoTrack", ["t", "sc", "t_saved", "sc_saved"])
#: the frames: normalized observations (frames × 4), the cameras present, and per frame what only
#: the caller computes (NaN until asked for): whether both detections are one point, the
#: triangulation ``[x, y, z, known]``
StereoFrames = namedtuple("StereoFrames", ["Yn", "okl", "okr", "consistent", "tri"])
#: per-frame outputs: state (frames × 6), predicted, cost, gain, cameras gated, restarted
StereoOutput = namedtuple("StereoOutput", ["states", "pred", "costs", "gains", "gated", "restarts"])
LN4 = math.log(4.0)
DIAGONALS = np.array([[1.0, 1.0, 1.0], [1.0, 1.0, -1.0], [1.0, -1.0, 1.0], [-1.0, 1.0, 1.0]])


def _record(dtype: np.dtype) -> np.record:
    return np.zeros(1, dtype=dtype).view(np.recarray)[0]


def new_params(**fields: object) -> np.record:
    """A :data:`PARAMS` record holding ``fields`` (every field of the dtype)."""
    prm = _record(PARAMS)
    for name in PARAMS.names or ():
        setattr(prm, name, fields[name])
    return prm


def new_track(scale_floor: float) -> StereoTrack:
    """Fresh records of a track (a record plain Python and the compiled code both read by field
    name); the robust scale starts at its floor."""
    track = StereoTrack(_record(TRACK), _record(SCALE), _record(TRACK), _record(SCALE))
    track.sc.value = track.sc.floor = scale_floor
    return track


def state_of(t: np.record) -> np.ndarray:
    """A track record's ``[p, v]`` (6)."""
    return np.r_[t.p, t.v]


@kernel
def st_cost(q0, q1, q2, yn, use_l, use_r, prm):
    """``J(q) = ‖h(g⁻¹(q)) − y‖²`` through the disparity maps (``SPSAStereoEstimator.cost``)."""
    s0, s1, s2 = q0, q1, q0 - q2
    if s2 <= 1e-12:
        return BIG_COST
    c = 0.0
    for cam in range(2):
        if (use_l if cam == 0 else use_r):
            A = prm.AL if cam == 0 else prm.AR
            w = A[8] * s0 + A[9] * s1 + A[10] + A[11] * s2
            if w <= 1e-12:
                return BIG_COST
            du = (A[0] * s0 + A[1] * s1 + A[2] + A[3] * s2) / w - yn[2 * cam]
            dv = (A[4] * s0 + A[5] * s1 + A[6] + A[7] * s2) / w - yn[2 * cam + 1]
            c += du * du + dv * dv
    return c


@kernel
def st_minimise(q0, q1, q2, yn, use_l, use_r, prm):
    """Simultaneous-perturbation Newton steps on the frame's cost (``SPSAStereoEstimator._minimise``)."""
    c = prm.c
    J0 = st_cost(q0, q1, q2, yn, use_l, use_r, prm)
    one = use_l != use_r
    s1 = math.sqrt(0.5) if (use_l and use_r) else 1.0
    dim = 2.0 if one else 3.0
    for _ in range(int(prm.sweeps)):
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
        if max(abs(t0), abs(t1), abs(t2)) < prm.far:
            break
    return q0, q1, q2, J0


@kernel
def st_g(p0, p1, p2, prm, q):
    """``q = g(p)`` into ``q``; False behind the rectifying frame (``SPSAStereoEstimator.g``)."""
    x = prm.R[0] * p0 + prm.R[1] * p1 + prm.R[2] * p2 + prm.t[0]
    y = prm.R[3] * p0 + prm.R[4] * p1 + prm.R[5] * p2 + prm.t[1]
    z = prm.R[6] * p0 + prm.R[7] * p1 + prm.R[8] * p2 + prm.t[2]
    if z <= 1e-9:
        return False
    q[0], q[1], q[2] = x / z, y / z, (x - prm.b) / z
    return True


@kernel
def st_g_inv(q0, q1, q2, prm, out, at):
    """``g⁻¹(q)`` into ``out[at:at + 3]`` (``SPSAStereoEstimator.g_inv``)."""
    z = prm.b / (q0 - q2)
    a, b, c = q0 * z - prm.t[0], q1 * z - prm.t[1], z - prm.t[2]
    out[at] = prm.R[0] * a + prm.R[3] * b + prm.R[6] * c
    out[at + 1] = prm.R[1] * a + prm.R[4] * b + prm.R[7] * c
    out[at + 2] = prm.R[2] * a + prm.R[5] * b + prm.R[8] * c


@kernel
def st_scale_add(sc, nis):
    """``RobustNISScale.add`` of one value: the oldest value leaves the sorted copy when the ring
    is full, the new one is inserted in order, and the scale is their median over ln 4, at least
    the floor."""
    if not math.isfinite(nis):
        return
    m, h, srt = sc.count, sc.head, sc.sorted
    if m == SC_MEMORY:
        i = 0
        while srt[i] != sc.ring[h]:
            i += 1
        for r in range(i, m - 1):
            srt[r] = srt[r + 1]
        m -= 1
    i = m
    while i > 0 and srt[i - 1] > nis:
        srt[i] = srt[i - 1]
        i -= 1
    srt[i] = nis
    m += 1
    sc.ring[h], sc.head, sc.count = nis, (h + 1) % SC_MEMORY, m
    med = srt[m // 2] if m % 2 else 0.5 * (srt[m // 2 - 1] + srt[m // 2])
    sc.value = max(sc.floor, med / LN4)


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
            r = prm.poses[c]
            x = r[0] * pp[0] + r[1] * pp[1] + r[2] * pp[2] + r[9]
            y = r[3] * pp[0] + r[4] * pp[1] + r[5] * pp[2] + r[10]
            z = r[6] * pp[0] + r[7] * pp[1] + r[8] * pp[2] + r[11]
            nis = ((x / z - yn[2 * c]) ** 2 + (y / z - yn[2 * c + 1]) ** 2) * prm.f2[c] / prm.sigma2
            scale = sc.value
            st_scale_add(sc, nis)
            if nis / scale > prm.nis_gate:
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
    same = (e > 0.0) == (t.sgn[i] > 0.0)
    t.sgn[i] = e
    t.run[i] = t.run[i] + 1 if same else 0
    if t.run[i] >= runlen:
        t.mem[i] = max(1.0, 0.5 * t.mem[i])
        t.run[i] = 0
    else:
        t.mem[i] = min(t.mem[i] + 1.0, cap)
    return t.mem[i]


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
    t.p[0], t.p[1], t.p[2], t.v[0], t.v[1], t.v[2] = p0, p1, p2, v0, v1, v2
    for i in range(3):
        t.mem[i], t.run[i], t.sgn[i] = memory, 0.0, 0.0


@kernel
def st_correct(t, q, h0, h1, h2, prm, w):
    """The line-fit correction of (x/z, y/z, b/z) and the velocity from it (the end of
    ``SPSAStereoEstimator._update``); the image coordinates' gain α."""
    e0, e1, ed = h0 - q[0], h1 - q[1], (h0 - h2) - (q[0] - q[2])
    dd = q[0] - q[2]
    runlen = prm.runlen
    a0, r0 = st_gains(st_memory(t, 0, e0, prm.nmax, runlen))
    a1, r1 = st_gains(st_memory(t, 1, e1, prm.nmax, runlen))
    cap = st_max_memory(min(1.0, max(prm.amin_d, prm.kd * dd)))
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
    k = 1.0 / prm.dt
    for i in range(3):
        t.v[i] = t.v[i] + k * (w[3 + i] - t.p[i])  # t.p[0] still holds the prediction
        t.p[i] = w[i]
    return a0


@kernel
def st_update(track, yn, use_l, use_r, consistent, tri, prm, q, w):
    """One frame after the start (``SPSAStereoEstimator._update``): (predicted, cost, gain α,
    gated, need) where ``need`` asks for the frame's ``consistent`` (1) or ``tri`` (2) when they
    are not known yet (NaN; the state is then left half-updated: the caller restores it)."""
    t, sc = track.t, track.sc
    for i in range(3):
        t.p[i] = t.p[i] + t.v[i] * prm.dt
    if not (use_l or use_r):
        return True, math.nan, math.nan, 0, 0
    gated = 0
    if math.isfinite(prm.nis_gate):
        use_l, use_r, gated, need = st_gate(t.p, yn, use_l, use_r, consistent, prm, sc)
        if need:
            return True, math.nan, math.nan, gated, 1
        if not (use_l or use_r):
            return True, math.nan, math.nan, gated, 0
    if not st_g(t.p[0], t.p[1], t.p[2], prm, q):  # behind the camera: from the frame's own minimum
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
    if cost > prm.cost_gate * (int(use_l) + int(use_r)):
        return True, cost, math.nan, gated, 0
    return False, cost, st_correct(t, q, h0, h1, h2, prm, w), gated, 0


#: why :func:`spsa_stereo_frames` stopped: the end, a restart to ask for, or a frame's
#: ``consistent`` or ``tri`` to compute (then that frame is run again)
ST_DONE, ST_RESTART, ST_CONSISTENT, ST_TRI = 0, 1, 2, 3


@kernel
def spsa_stereo_frames(frames, k0, prm, track, out):
    """``spsa_stereo`` from frame ``k0`` on (``SPSAStereoEstimator._update`` and the count of gated
    frames, frame after frame): ``(frame, why)``. At a restart (the gated run reached
    ``restart_after``) the frame's outputs are written as if none and the caller asks the initiator.
    A frame that needs what only the caller computes (``consistent``: both cameras gated;
    ``tri``, row ``[x, y, z, known]``: a prediction behind the cameras) is undone, to be run again."""
    q, w = np.empty(3), np.empty(6)
    t, sc = track.t, track.sc
    for j in range(k0, frames.Yn.shape[0]):
        _copy_track(t, track.t_saved)
        _copy_scale(sc, track.sc_saved)
        okl, okr = frames.okl[j], frames.okr[j]
        p, cost, gain, g, need = st_update(track, frames.Yn[j], okl, okr, frames.consistent[j], frames.tri[j], prm, q, w)
        if need:
            _copy_track(track.t_saved, t)
            _copy_scale(track.sc_saved, sc)
            return j, ST_CONSISTENT if need == 1 else ST_TRI
        had = okl or okr
        t.grun = t.grun + 1 if g else (0.0 if had else t.grun)
        for i in range(3):
            out.states[j, i], out.states[j, 3 + i] = t.p[i], t.v[i]
        out.pred[j], out.costs[j], out.gains[j], out.gated[j], out.restarts[j] = p, cost, gain, g, 0.0
        if t.grun >= prm.restart:
            return j, ST_RESTART
    return frames.Yn.shape[0], ST_DONE


@kernel
def _copy_track(a, b):
    """Every field of the track record ``a`` into ``b``."""
    for i in range(3):
        b.p[i], b.v[i], b.mem[i], b.run[i], b.sgn[i] = a.p[i], a.v[i], a.mem[i], a.run[i], a.sgn[i]
    b.grun = a.grun


@kernel
def _copy_scale(a, b):
    """Every field of the robust scale record ``a`` into ``b``."""
    for i in range(SC_MEMORY):
        b.ring[i], b.sorted[i] = a.ring[i], a.sorted[i]
    b.count, b.head, b.value, b.floor = a.count, a.head, a.value, a.floor
