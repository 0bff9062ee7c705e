"""The compiled cores (pipeline/estimators/compiled/): the same numbers compiled and as plain
Python, and the same as stepping frame by frame (the estimators' streaming arithmetic), on tracks
that start late, lose a camera, black out, carry outliers and restart."""

from __future__ import annotations

import numpy as np
import pytest

import pipeline.estimators as estimators
from pipeline.core.camera import Camera, StereoMeasurementModel, StereoRig
from pipeline.estimators import base, create
from pipeline.estimators import compiled as kernels
from pipeline.estimators.base import Estimator

RIG = StereoRig.from_parameters(640, 480, (610.0, 590.0), (322.0, 241.0), 0.3, 4.0)
ABOVE = StereoRig(RIG.left, Camera(RIG.left.K, np.eye(3), np.array([0.0, 0.3, 0.0])), RIG.image_size)  # above the left
DT = 1 / 30
COMPILED = ["spsa", "ekf", "ekf_rts", "spsa_stereo"]


def observations(rig: StereoRig, seed: int, n: int = 120) -> np.ndarray:
    """A receding, turning point: late start, a one-camera gap, a blackout, single outliers, and a
    run of frames where both cameras follow another point (the gate holds, then the track restarts)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * DT
    X = np.column_stack([0.1 + 0.3 * np.sin(t), -0.05 + 0.1 * t, 2.0 + 0.5 * t])
    Y = rig.project(X) + rng.normal(0, 0.7, (n, 4))
    Y[: 3 + seed] = np.nan
    Y[30:33, :2] = np.nan
    Y[50:56] = np.nan
    Y[rng.random(n) < 0.05, 2:] += 35.0
    Y[80:100] = rig.project(X[80:100] + np.array([0.25, 0.1, 0.0])) + rng.normal(0, 0.7, (20, 4))
    return Y


@pytest.fixture(autouse=True)
def always_compiled(monkeypatch):
    """The compiled cores for every clip length (``run`` steps through short clips otherwise)."""
    monkeypatch.setattr(base, "JIT_MIN_FRAMES", 0)


@pytest.fixture
def uncompiled(monkeypatch):
    """Every kernel as plain Python (``STEREOTRACK_JIT=0``'s module) for the estimators."""
    monkeypatch.setattr(estimators, "compiled", kernels.uncompiled())


def assert_same_track(a, b, tol: float = 1e-9) -> None:
    for field in ("position", "velocity", "predicted", "covariance", "nis", "nis_dof", "reprojection_error"):
        x, y = getattr(a, field), getattr(b, field)
        assert (x is None) == (y is None), field
        if x is not None:
            np.testing.assert_allclose(x, y, rtol=tol, atol=tol, err_msg=field)
    assert sorted(a.extra) == sorted(b.extra)
    for key in a.extra:
        np.testing.assert_allclose(a.extra[key], b.extra[key], rtol=tol, atol=tol, err_msg=key)


def stepped(est: Estimator, Y: np.ndarray):
    """The track from the streaming path: reset, step every frame, finish."""
    est.reset()
    return est.finish([est.step(y) for y in Y], Y)


@pytest.mark.parametrize("rig", [RIG, ABOVE], ids=["right", "above"])
@pytest.mark.parametrize("method", COMPILED)
def test_compiled_run_equals_the_streaming_steps(method, rig):
    for seed in range(2):
        Y = observations(rig, seed)
        est = create(method, rig, DT)
        assert_same_track(est.run(Y), stepped(est, Y))


@pytest.mark.parametrize("method", COMPILED)
def test_compiled_equals_plain_python(method, uncompiled):
    """The kernels run uncompiled (plain Python) give the numbers the compiled ones give."""
    compiled = kernels  # this module, compiled (the fixture swapped what the estimators import)
    assert estimators.compiled is not compiled and not estimators.compiled.JIT
    Ys = np.stack([observations(RIG, s) for s in range(2)])
    plain = [create(method, RIG, DT).run(Y) for Y in Ys]
    plain_batch = create(method, RIG, DT).run_batch(Ys)
    estimators.compiled = compiled
    for Y, p in zip(Ys, plain, strict=True):
        assert_same_track(create(method, RIG, DT).run(Y), p)
    np.testing.assert_allclose(create(method, RIG, DT).run_batch(Ys), plain_batch, rtol=1e-9, atol=1e-9)


def test_the_test_tracks_exercise_every_branch():
    """The observations above make the EKF gate single cameras, restart, and predict through gaps."""
    tr = create("ekf", RIG, DT).run(observations(RIG, 0))
    assert np.nansum(tr.extra["restart"]) >= 1
    assert np.nansum(tr.extra["gated"]) >= 5
    assert tr.predicted[50:56].all() and not tr.predicted[60:70].any()
    assert set(np.unique(tr.nis_dof)) >= {0, 2, 4}


def stereo_observations(rig: StereoRig, seed: int, n: int = 160) -> np.ndarray:
    """:func:`observations`, then the second camera's detection sliding 40 px along its epipolar
    line for 15 frames (one camera gated until the track restarts), then running off along it (gated
again right after a restart), then the marker rushing at the
    cameras (``spsa_stereo``'s prediction falls behind them and it starts from the frame's minimum)."""
    rng = np.random.default_rng(seed)
    Y = observations(rig, seed, n)
    Y[110:125, 2 if rig is RIG else 3] += 40.0
    Y[128:136, 2 if rig is RIG else 3] += 12.0 * np.arange(1, 9)  # and then runs away from it, frame after frame
    z = np.linspace(0.6, 0.02, n - 140)
    Y[140:] = rig.project(np.column_stack([np.full_like(z, 0.05), np.full_like(z, 0.02), z])) + rng.normal(0, 0.7, (len(z), 4))
    return Y


@pytest.mark.parametrize("rig", [RIG, ABOVE], ids=["right", "above"])
def test_spsa_stereo_compiled_through_every_branch(rig):
    """The compiled ``spsa_stereo`` equals its streaming steps through restarts (the kernel stops,
    the initiator is asked, the kernel resumes), single cameras gated, both gated but one point
    (lag, not an outlier), gaps and a prediction behind the cameras; the branches occur."""
    for seed in range(3):
        Y = stereo_observations(rig, seed)
        for restart_after in (3, 8):
            est = create("spsa_stereo", rig, DT, {"restart_after": restart_after})
            tr = est.run(Y)
            assert_same_track(tr, stepped(est, Y))
            assert np.nansum(tr.extra["restart"]) >= 1 and np.nansum(tr.extra["gated"]) >= 5
    behind = create("spsa_stereo", rig, DT, {"restart_after": 8}).run(stereo_observations(rig, 0))
    assert np.any(behind.extra["gain"][140:] == 1.0)  # the start from the frame's own minimum


def test_ekf_with_a_time_offset_compiled_and_stepped():
    est = create("ekf", RIG, DT, time_offset=0.4 * DT)
    Y = observations(RIG, 1)
    assert_same_track(est.run(Y), stepped(est, Y))


@pytest.mark.parametrize("offset", [0.0, 0.4 * DT])
def test_ekf_batch_mixes_restarting_plain_and_unstarted_tracks(offset):
    """The batch core runs the tracks that never restart, a track that asks for a restart runs again
    on its own, and one that never starts stays NaN: every row equals that track's own ``run``."""
    rng = np.random.default_rng(5)
    t = np.arange(120) * DT
    plain = RIG.project(np.column_stack([0.2 * np.cos(t), 0.1 * t, 2.5 + 0.3 * t])) + rng.normal(0, 0.7, (120, 4))
    Ys = np.stack([observations(RIG, 0), plain, np.full((120, 4), np.nan), plain[::-1], observations(RIG, 1)])
    est = create("ekf", RIG, DT, time_offset=offset)
    runs = [est.run(Y) for Y in Ys]
    restarts = [np.nansum(tr.extra.get("restart", [0.0])) for tr in runs]
    assert restarts[0] >= 1 and restarts[4] >= 1 and restarts[1] == restarts[3] == 0
    np.testing.assert_allclose(est.run_batch(Ys), np.stack([tr.position for tr in runs]), rtol=1e-9, atol=1e-9)


def test_linearize_kernel_is_the_measurement_model():
    rng = np.random.default_rng(0)
    Pm = np.stack([RIG.left.P, RIG.right.P])
    for delta in (0.0, 0.013):
        model = StereoMeasurementModel(RIG, time_offset=delta)
        for x in np.c_[rng.normal(0, 0.3, (20, 3)) + np.array([0.0, 0.0, 3.0]), rng.normal(0, 1, (20, 3))]:
            h, H = np.empty(4), np.empty((4, 6))
            kernels.stereo_linearize(Pm, delta, x, h, H)
            h0, H0 = model.linearize(x)
            np.testing.assert_allclose(h, h0, rtol=1e-14)
            np.testing.assert_allclose(H, H0, rtol=1e-12, atol=1e-12 * np.abs(H0).max())


def test_small_inverse_kernel():
    rng = np.random.default_rng(1)
    for m in (1, 2, 3, 4):
        A = rng.normal(size=(m, m))
        S = A @ A.T + np.eye(m) * 0.1
        S[[0, -1]] = S[[-1, 0]]  # a pivot away from the diagonal
        out, work = np.zeros((4, 4)), np.zeros((4, 4))
        kernels.inv_small(np.ascontiguousarray(np.pad(S, ((0, 4 - m), (0, 4 - m)))), m, out, work)
        np.testing.assert_allclose(out[:m, :m], np.linalg.inv(S), rtol=1e-10, atol=1e-12)


def test_rts_kernel_is_filterpys_smoother():
    """The compiled backward pass against filterpy's ``rts_smoother`` on a filtered EKF track."""
    from filterpy.kalman import KalmanFilter

    est = create("ekf", RIG, DT)
    tr = est.run(observations(RIG, 0)[:79])  # before the restart: one segment
    ok = np.all(np.isfinite(tr.position), axis=1)
    xs, Ps = np.hstack([tr.position[ok], tr.velocity[ok]]), tr.covariance[ok]
    kf = KalmanFilter(dim_x=6, dim_z=1)
    kf.F, kf.Q = est.A, est.Q
    want_x, want_P, _, _ = kf.rts_smoother(xs.copy(), Ps.copy())
    got_x, got_P = xs.copy(), Ps.copy()
    kernels.rts_backward(got_x, got_P, DT, np.ascontiguousarray(est.Q))
    np.testing.assert_allclose(got_x, want_x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(got_P, want_P, rtol=1e-9, atol=1e-15)
    assert np.abs(got_x - xs).max() > 1e-4  # it smoothed


def test_short_clips_step_unless_the_cores_are_loaded(monkeypatch):
    """Below ``JIT_MIN_FRAMES`` a fresh process steps (no numba to load); the numbers are the same."""
    import sys

    monkeypatch.setattr(base, "JIT_MIN_FRAMES", 10_000)
    monkeypatch.delitem(sys.modules, "pipeline.estimators.compiled")
    assert not base.use_compiled(120) and base.use_compiled(10_000)
    Y = observations(RIG, 0)
    stepped_track = create("ekf", RIG, DT).run(Y)
    assert "pipeline.estimators.compiled" not in sys.modules
    monkeypatch.setattr(base, "JIT_MIN_FRAMES", 0)
    assert_same_track(create("ekf", RIG, DT).run(Y), stepped_track)


@pytest.mark.parametrize("rig", [RIG, ABOVE], ids=["right", "above"])
@pytest.mark.parametrize("method", ["spsa", "spsa_vgg"])
def test_short_spsa_clips_loop_as_the_steps(monkeypatch, rig, method):
    """Below ``JIT_MIN_FRAMES`` spsa runs its interpreted loop (:meth:`SPSAEstimator._loop`, no
    numba loaded), and spsa_vgg always does: the same numbers as stepping them frame by frame."""
    import sys

    monkeypatch.setattr(base, "JIT_MIN_FRAMES", 10_000)
    monkeypatch.delitem(sys.modules, "pipeline.estimators.compiled")
    for seed in range(3):
        Y = observations(rig, seed)
        looped = create(method, rig, DT).run(Y)
        assert "pipeline.estimators.compiled" not in sys.modules
        assert_same_track(looped, Estimator.run(create(method, rig, DT), Y))
