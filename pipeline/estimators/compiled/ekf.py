"""The EKF's compiled core (the twin of :mod:`pipeline.estimators.ekf`, after Krivokon 2011,
App. I): one track or a batch of tracks, frame by frame, with the per-camera χ² gate and the
restart protocol of :class:`~pipeline.estimators.kalman_common.GatedFilter`, and the
Rauch–Tung–Striebel backward pass of the smoothers. The measurement model is the camera's own
(:func:`pipeline.core.camera.linearize_point`, compiled here), the update the one Joseph update of
:mod:`.linalg`."""

from __future__ import annotations

import math
from collections import namedtuple

import numpy as np

from pipeline.core.camera import linearize_point

from ._jit import kernel
from .linalg import Workspace, ekf_predict, inv_small, joseph_inlined, joseph_update, mm, mm6

#: the model a track is filtered with: both cameras' 3 × 4 matrices ``Pm`` (2 × 3 × 4), the time
#: offset δ, the frame step, the process and pixel noise ``Q`` (6 × 6) and ``R`` (4 × 4), the gate's
#: threshold on a camera's NIS (inf: no gate), the gated run after which a restart is asked for, and
#: the joint check's threshold on both cameras' NIS together (inf: none; ``gating.joint_gate``)
EKFModel = namedtuple("EKFModel", ["Pm", "delta", "dt", "Q", "R", "threshold", "restart_after", "joint"])
#: a track's state: ``x`` (6), ``P`` (6 × 6), its :data:`GATE` record, and the prediction kept while
#: a restart is asked for (``scratch_x``, ``scratch_P``)
EKFTrack = namedtuple("EKFTrack", ["x", "P", "gate", "scratch_x", "scratch_P"])
#: per-frame outputs: position, velocity (frames × 3), covariance (frames × 6 × 6), whether the frame
#: only predicted, the NIS and its degrees of freedom, the cameras gated, whether it restarted
EKFOutput = namedtuple("EKFOutput", ["pos", "vel", "cov", "pred", "nis", "dof", "gated", "restarted"])
#: a gated track's counters (see :func:`pipeline.estimators.kalman_common.after_gap`): frames in a row
#: with a camera gated, frames each camera has gone unseen, returning frames left; and, while a
#: restart is asked for, how many cameras and which the gate dropped at that frame
GATE = np.dtype([("run", "i8"), ("unseen", "i8", (2,)), ("returning", "i8"), ("held", "i8"), ("camera", "i8", (2,))])

#: the camera's measurement model, compiled
stereo_linearize = kernel(linearize_point)


def new_track(x: np.ndarray, P: np.ndarray) -> EKFTrack:
    """A track starting at ``x``, ``P`` (used in place) with fresh counters (a record that plain
    Python and the compiled code both read by field name)."""
    return EKFTrack(x, P, np.zeros(1, dtype=GATE).view(np.recarray)[0], np.zeros(6), np.zeros((6, 6)))


def new_output(n: int) -> EKFOutput:
    """Per-frame outputs of an ``n``-frame clip: NaN, predicted, no degrees of freedom."""
    nan = np.nan
    return EKFOutput(np.full((n, 3), nan), np.full((n, 3), nan), np.full((n, 6, 6), nan), np.ones(n, dtype=np.bool_),
                     np.full(n, nan), np.zeros(n, dtype=np.int64), np.full(n, nan), np.full(n, nan))


@kernel
def camera_nis2(S, r, c):
    """Camera ``c``'s ``rᵀ S_c⁻¹ r`` from its 2 × 2 block of ``S`` in closed form (NaN stays NaN)."""
    i = 2 * c
    a, b, d = S[i, i], S[i, i + 1], S[i + 1, i + 1]
    u, v = r[i], r[i + 1]
    return (d * u * u - 2.0 * b * u * v + a * v * v) / (a * d - b * b)


@kernel
def ekf_frames(Y, k0, resume, model, track, out):
    """The EKF over frames ``k0…`` of ``Y`` (frames × 4 px, NaN missing) from ``track`` (in place),
    gating each camera at ``model.threshold`` (inf: off) as ``GatedFilter.gate`` does. Returns the
    clip's length, or the frame at which the track was gated ``restart_after`` frames: the caller
    asks for a restart and calls again with ``resume`` 1 (restart state in ``track.x``, ``track.P``)
    or 2 (none: update with what the gate kept; the prediction and the verdict are in the track)."""
    n = Y.shape[0]
    h, kept, r, rs, rows = np.empty(4), np.empty(4), np.empty(4), np.empty(4), np.empty(4, dtype=np.int64)
    H, Hs, Rs = np.empty((4, 6)), np.empty((4, 6)), np.empty((4, 4))
    ws = Workspace(np.empty((6, 4)), np.empty((4, 4)), np.empty((4, 4)), np.empty((6, 4)), np.empty((6, 6)),
                   np.empty((6, 6)), np.empty((6, 4)), np.empty((4, 4)))
    nz, gate_on = 6 if model.delta != 0.0 else 3, model.threshold < np.inf  # the nonzero columns of H; gating
    x, P, g = track.x, track.P, track.gate
    for k in range(k0, n):
        if k == k0 and resume == 1:  # restarted at this frame: a new start, no update
            g.run = 0
            _ekf_output(k, x, P, out, False)
            out.gated[k], out.restarted[k] = g.held, 1.0
            continue
        for i in range(4):
            kept[i] = Y[k, i]
        resumed = k == k0 and resume == 2
        if resumed:  # the prediction and the gate's verdict from before the restart was asked for
            n_gated = _resume(track, kept)
        else:
            ekf_predict(model.dt, model.Q, x, P)
            n_gated = 0
            if gate_on:
                n_gated = _gate(Y[k], model, track, h, H, r, kept, ws, nz)
                if g.run >= model.restart_after:
                    _copy_state(x, P, track.scratch_x, track.scratch_P)
                    g.held = n_gated
                    return k
        out.gated[k], out.restarted[k] = n_gated, 0.0
        m = _present_rows(kept, rows)
        if m == 0:
            _ekf_output(k, x, P, out, True)
            continue
        have_S = 0  # the gate's h, H, P Hᵀ and S (and the joint check's S⁻¹) are this update's
        if gate_on and m == 4 and not resumed:
            have_S = 2 if model.joint < np.inf else 1
        if have_S == 0:
            stereo_linearize(model.Pm, model.delta, x, h, H)
        _gather_rows(rows, m, H, kept, h, model.R, Hs, rs, Rs)
        out.nis[k] = _update(x, P, Hs, rs, Rs, m, nz, ws, have_S)
        out.dof[k] = m
        _ekf_output(k, x, P, out, False)
    return n


@kernel(inline=True)
def _gate(y, model, track, h, H, r, kept, ws, nz):
    """This frame's gate: each camera whose NIS under the track's prediction exceeds the threshold
    is dropped from ``kept``; the track's gate counters move on; the number gated. Leaves ``h``,
    ``H``, ``ws.PHt`` and ``ws.S`` (with ``R``) for the update."""
    x, P, g = track.x, track.P, track.gate
    stereo_linearize(model.Pm, model.delta, x, h, H)
    _gate_products(P, H, ws.PHt, ws.S, nz)
    S = ws.S
    for i in range(4):
        r[i] = y[i] - h[i]
        for j in range(4):
            S[i, j] += model.R[i, j]
    n_gated = 0
    for c in range(2):
        g.camera[c] = 0
        if camera_nis2(S, r, c) > model.threshold:
            kept[2 * c], kept[2 * c + 1] = np.nan, np.nan
            g.camera[c] = 1
            n_gated += 1
    if n_gated == 0 and model.joint < np.inf and _joint_nis(S, r, ws) > model.joint:  # each within its gate, not both
        c = 0 if camera_nis2(S, r, 0) >= camera_nis2(S, r, 1) else 1
        kept[2 * c], kept[2 * c + 1] = np.nan, np.nan
        g.camera[c] = 1
        n_gated = 1
    _count_gated(g, y, n_gated > 0, model.restart_after)
    return n_gated


@kernel(inline=True)
def _joint_nis(S, r, ws):
    """``rᵀ S⁻¹ r`` over both cameras (4 rows; 0 unless both observed: the check is of a pair),
    leaving ``S⁻¹`` in ``ws.Si`` for the update."""
    for i in range(4):
        if not math.isfinite(r[i]):
            return 0.0
    inv_small(S, 4, ws.Si, ws.work)
    acc = 0.0
    for i in range(4):
        for j in range(4):
            acc += r[i] * ws.Si[i, j] * r[j]
    return acc


@kernel
def ekf_batch(Y, begin, x0, P0, model, track, out):
    """:func:`ekf_frames` over M tracks (``Y`` M × frames × 4), each from ``x0[m]``, ``P0[m]`` at its
    frame ``begin[m]`` (none when it is the clip's length), through the scratch ``track``
    (:func:`new_track`), positions into ``out`` (M × frames × 3). Returns, per track, the frame at
    which it asked for a restart (the clip's length: none), for the caller to run those tracks
    again with their restarts."""
    M, n = Y.shape[0], Y.shape[1]
    vel, cov, pred = np.empty((n, 3)), np.empty((n, 6, 6)), np.empty(n, dtype=np.bool_)
    nis, dof, gated, restarted = np.empty(n), np.empty(n, dtype=np.int64), np.empty(n), np.empty(n)
    stopped = np.full(M, n, dtype=np.int64)
    for m in range(M):
        k0 = begin[m]
        if k0 >= n:
            continue
        _copy_state(x0[m], P0[m], track.x, track.P)
        g = track.gate
        g.run, g.returning, g.held, g.camera[0], g.camera[1] = 0, 0, 0, 0, 0
        g.unseen[0], g.unseen[1] = 0, 0
        for a in range(3):
            out[m, k0, a] = track.x[a]
        res = EKFOutput(out[m], vel, cov, pred, nis, dof, gated, restarted)
        stopped[m] = ekf_frames(Y[m], k0 + 1, 0, model, track, res)
    return stopped


@kernel
def _update(x, P, Hs, rs, Rs, m, nz, ws, have_S):
    """The Joseph update; in the common case (both cameras, no time offset: ``m`` 4, ``nz`` 3) the
    copy with constant sizes, which the compiler unrolls (the same operations in the same order)."""
    if m == 4 and nz == 3:
        return joseph_inlined(x, P, Hs, rs, Rs, 4, 3, ws, have_S)
    return joseph_update(x, P, Hs, rs, Rs, m, nz, ws, have_S)


@kernel(inline=True)
def _gate_products(P, H, PHt, S, nz):
    """The gate's ``P Hᵀ`` and ``H P Hᵀ`` on all four rows, the sizes written as constants."""
    if nz == 3:
        mm(P, H, PHt, 6, 3, 4, True)
        mm(H, PHt, S, 4, 3, 4, False)
    else:
        mm(P, H, PHt, 6, 6, 4, True)
        mm(H, PHt, S, 4, 6, 4, False)


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


@kernel(inline=True)
def _resume(track, kept):
    """Back at the frame a restart was asked for: its prediction, and the gate's verdict on ``kept``."""
    _copy_state(track.scratch_x, track.scratch_P, track.x, track.P)
    for c in range(2):
        if track.gate.camera[c] != 0:
            kept[2 * c], kept[2 * c + 1] = np.nan, np.nan
    return track.gate.held


@kernel
def _copy_state(x, P, to_x, to_P):
    for i in range(6):
        to_x[i] = x[i]
        for j in range(6):
            to_P[i, j] = P[i, j]


@kernel(inline=True)
def _count_gated(g, y, gated, restart_after):
    """The gated-run, per-camera unseen and returning counters after one frame (``after_gap``'s
    arithmetic; ``y`` the frame's observation before the gate)."""
    had0 = math.isfinite(y[0]) or math.isfinite(y[1])
    had1 = math.isfinite(y[2]) or math.isfinite(y[3])
    had = had0 or had1
    run = g.run + 1 if gated else (0 if had else g.run)
    returning = g.returning
    back0, back1 = had0 and g.unseen[0] >= restart_after, had1 and g.unseen[1] >= restart_after
    kept = (had0 and g.unseen[0] < restart_after) or (had1 and g.unseen[1] < restart_after)
    if back0 or back1:
        returning = restart_after
    if (gated and returning > 0) or ((back0 or back1) and kept):
        run = max(run, restart_after)
    if had:
        returning = max(returning - 1, 0)
    g.unseen[0] = 0 if had0 else g.unseen[0] + 1
    g.unseen[1] = 0 if had1 else g.unseen[1] + 1
    g.run, g.returning = run, returning


@kernel(inline=True)
def _ekf_output(k, x, P, out, predicted):
    for i in range(3):
        out.pos[k, i] = x[i]
        out.vel[k, i] = x[3 + i]
    for i in range(6):
        for j in range(6):
            out.cov[k, i, j] = P[i, j]
    out.pred[k] = predicted


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

