"""Point estimators on simulated observations: accuracy against truth, the thesis's claims as
orderings measured in the same run, agreement with filterpy, gaps and bad input."""

from __future__ import annotations

import itertools

import cv2
import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter

from pipeline.core.alphabeta import ABFilter
from pipeline.core.camera import Camera, StereoRig, triangulate
from pipeline.core.errors import CalibrationError, StereotrackError
from pipeline.estimators import create, methods
from pipeline.estimators.base import transition, white_noise_acceleration

POINT_METHODS = methods("point")

SEEDS = (0, 1, 2)


def observe(rig, X, sigma, seed):
    rng = np.random.default_rng(seed)
    return rig.project(X) + rng.normal(0.0, sigma, (len(X), 4)), rng


def given(X, V, rng, sigma_start=0.05):
    state = np.r_[X[0] + rng.normal(0, sigma_start, 3), V[0]]
    return {"mode": "given", "state": tuple(state.tolist()), "sigma_position": sigma_start, "sigma_velocity": 0.05}


def rmse(P, X):
    e = np.linalg.norm(P - X, axis=1)
    return float(np.sqrt(np.nanmean(e**2)))


def test_triangulation_matches_opencv(receding):
    rig, _, X, _ = receding
    np.testing.assert_allclose(triangulate(rig, rig.project(X)), X, atol=1e-9)
    Y, _ = observe(rig, X, 1.0, 0)
    ref = cv2.triangulatePoints(rig.left.P, rig.right.P, Y[:, :2].T, Y[:, 2:].T)
    ref = (ref[:3] / ref[3]).T
    ours = triangulate(rig, Y)
    # same DLT; OpenCV does not scale rows, so noisy solutions differ by a little
    assert np.median(np.linalg.norm(ours - ref, axis=1)) < 0.01 * np.median(np.linalg.norm(ours - X, axis=1)) + 1e-6


def test_claim_a_triangulation_error_grows_with_noise(receding):
    rig, _dt, X, _ = receding
    errs = [np.mean([rmse(triangulate(rig, observe(rig, X, s, seed)[0]), X) for seed in SEEDS]) for s in (0.5, 1, 2, 4)]
    assert all(a < b for a, b in itertools.pairwise(errs)), errs


def test_claim_b_noise_free_vgg_latches_algorithm1_acts_but_does_not_follow(receding):
    """Claim (b), measured from a start at rest (the velocity must be learned, so carrying a given
    velocity passes nothing): on noise-free observations the unmodified SPSA latches — its final
    error is over 90 % of the distance the marker travelled — while Algorithm 1's update acts (its
    final error well under predict-only's, which is the whole travel) but does not follow: it ends
    over 30 % of the travel away (measured 2.4–4.9 m of 6.3 m). A method that only carries its
    start fails the first bound; one that tracks fails the last."""
    rig, dt, X, _ = receding
    travel = float(np.linalg.norm(X[-1] - X[0]))
    finals: dict[str, list[float]] = {"spsa": [], "spsa_vgg": [], "predict_only": []}
    for seed in SEEDS:
        Y, rng = observe(rig, X, 0.0, seed)
        state = np.r_[X[0] + rng.normal(0, 0.05, 3), 0.0, 0.0, 0.0]
        init = {"mode": "given", "state": tuple(state.tolist()), "sigma_position": 0.05, "sigma_velocity": 0.05}
        for m in finals:
            P = create(m, rig, dt, {"init": init, "seed": seed}).run(Y).position
            finals[m].append(float(np.linalg.norm(P[-1] - X[-1])))
    f = {m: float(np.mean(v)) for m, v in finals.items()}
    assert f["spsa_vgg"] > 0.9 * travel, (f, travel)
    assert f["spsa"] < 0.85 * f["predict_only"] and f["spsa"] < f["spsa_vgg"], f
    assert f["spsa"] > 0.3 * travel, (f, travel)  # the thesis's "follows" is not supported


def _noisy_runs(receding, sigma=2.0):
    rig, dt, X, V = receding
    out = {}
    for seed in SEEDS:
        Y, rng = observe(rig, X, sigma, seed)
        init = given(X, V, rng)
        good = {"pixel_sigma": sigma, "process_noise": 1e-4}
        cfgs = {
            "spsa": ("spsa", {}),
            "spsa_no_projection": ("spsa", {"th": None}),
            "ekf": ("ekf", good),
            "ekf_wrong": ("ekf", {**good, "q_scale": 100.0, "r_scale": 0.01}),
        }
        for key, (m, cfg) in cfgs.items():
            P = create(m, rig, dt, {**cfg, "init": init, "seed": seed}).run(Y).position
            out.setdefault(key, []).append(P)
    return X, out


@pytest.fixture(scope="module")
def noisy(receding):
    return _noisy_runs(receding)


def test_claim_c_projection_rule_keeps_spsa_bounded(noisy, receding):
    """Without the projection rule Algorithm 1 runs away; with it its worst error over a run stays
    below the worst error of triangulation on the same observations (mean over seeds; measured
    1.8 m against 2.7 m). The bound is one a looser rule crosses: th 3.3× the default gives 5.0 m,
    10× gives 5.6 m."""
    X, out = noisy
    rig = receding[0]
    final = {k: np.mean([np.linalg.norm(P[-1] - X[-1]) for P in v]) for k, v in out.items()}
    assert final["spsa_no_projection"] > 100 * final["spsa"], final
    worst = np.mean([np.nanmax(np.linalg.norm(P - X, axis=1)) for P in out["spsa"]])
    tri = np.mean([np.nanmax(np.linalg.norm(triangulate(rig, observe(rig, X, 2.0, seed)[0]) - X, axis=1))
                   for seed in SEEDS])
    assert worst < tri, (worst, tri)


def test_claim_d_ekf_with_correct_covariances_beats_spsa(noisy):
    X, out = noisy
    assert np.mean([rmse(P, X) for P in out["ekf"]]) < np.mean([rmse(P, X) for P in out["spsa"]])


def test_claim_e_is_not_supported_once_algorithm_1_acts(noisy):
    """Claim (e), measured: an EKF told q×100, R×0.01 is still better than Algorithm 1 with gains at
    which its update acts. (With the earlier inert gains Algorithm 1 "won" only because it never
    left its true-velocity start.)"""
    X, out = noisy
    r = {k: np.mean([rmse(P, X) for P in v]) for k, v in out.items()}
    assert r["ekf_wrong"] < r["spsa"], r


def test_ekf_agrees_with_plain_filterpy(receding):
    """Our EKF equals filterpy's ``ExtendedKalmanFilter`` driven by an independent projection and a
    numerical Jacobian, frame by frame to 1e-9 (a gap in one camera included)."""
    rig, dt, X, _ = receding
    Y, _ = observe(rig, X, 1.0, 5)
    Y[40:45, 2:] = np.nan  # a gap in one camera exercises the reduced update too
    ours = create("ekf", rig, dt, {"pixel_sigma": 1.0, "process_noise": 0.5}).run(Y)
    f = ExtendedKalmanFilter(dim_x=6, dim_z=4)
    f.F, f.Q = transition(dt), white_noise_acceleration(dt, 0.5)
    X0 = triangulate(rig, Y[:1])[0]
    f.x = np.r_[X0, 0, 0, 0].reshape(6, 1)
    P1, P2 = rig.left.P, rig.right.P

    def hx(x):
        p = x[:3, 0]
        out = []
        for P in (P1, P2):
            q = P @ np.r_[p, 1.0]
            out += [q[0] / q[2], q[1] / q[2]]
        return np.array(out).reshape(4, 1)

    def H(x):
        eps = 1e-7
        J = np.zeros((4, 6))
        for j in range(3):
            d = np.zeros((6, 1))
            d[j] = eps
            J[:, j] = ((hx(x + d) - hx(x - d)) / (2 * eps)).ravel()
        return J

    # the start: the first triangulation with its own covariance σ²(JᵀJ)⁻¹, velocity 0 ± 1 m/s, and
    # no update on frame 0 (its measurement made the start)
    J = H(f.x)[:, :3]
    f.P = np.diag([0.0] * 3 + [1.0] * 3)
    f.P[:3, :3] = np.linalg.inv(J.T @ J)
    np.testing.assert_allclose(ours.position[0], X0, atol=1e-12)
    for k in range(1, len(Y)):
        f.predict()
        rows = [0, 1, 2, 3] if np.all(np.isfinite(Y[k])) else [0, 1]
        f.update(Y[k, rows].reshape(-1, 1), lambda x, r=rows: H(x)[r], lambda x, r=rows: hx(x)[r],
                 R=np.eye(len(rows)))
        np.testing.assert_allclose(ours.position[k], f.x[:3, 0], atol=1e-9 * max(1.0, abs(f.x[2, 0])) + 1e-9)
    # the comparison is sensitive: a process noise 20 % off, or measurement noise 20 % off, moves the
    # estimates by far more than its tolerance
    for wrong in ({"pixel_sigma": 1.0, "process_noise": 0.6}, {"pixel_sigma": 1.2, "process_noise": 0.5}):
        assert np.abs(create("ekf", rig, dt, wrong).run(Y).position - ours.position).max() > 1e-5


def test_ukf_is_filterpys_ukf_step_by_step(receding):
    """Our UKF (every sigma point projected at once) equals filterpy's ``UnscentedKalmanFilter``
    calling the measurement model once per sigma point, frame by frame, from the same start
    (gate off; a gap in one camera exercises the reduced update)."""
    from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

    from pipeline.core.camera import StereoMeasurementModel
    from pipeline.estimators.base import InitConfig, Initiator

    rig, dt, X, _ = receding
    Y, _ = observe(rig, X, 1.0, 7)
    Y[40:45, 2:] = np.nan
    ours = create("ukf", rig, dt, {"pixel_sigma": 1.0, "process_noise": 0.5, "gate": 0}).run(Y)
    model = StereoMeasurementModel(rig, 1.0)
    start = Initiator(InitConfig(), model, dt, propagate=True).first(Y)
    A = transition(dt)
    f = UnscentedKalmanFilter(dim_x=6, dim_z=4, dt=dt, hx=model.function, fx=lambda x, dt: A @ x,
                              points=MerweScaledSigmaPoints(6, alpha=0.3, beta=2.0, kappa=-3.0))
    f.Q, R = white_noise_acceleration(dt, 0.5), model.covar()
    f.x, f.P = start.state.copy(), start.covariance.copy()
    for k in range(start.frame + 1, len(Y)):
        f.predict()
        rows = [0, 1, 2, 3] if np.all(np.isfinite(Y[k])) else [0, 1]
        f.update(Y[k, rows], R=R[np.ix_(rows, rows)], hx=lambda x, r=rows: model.function(x)[r])
        np.testing.assert_allclose(ours.position[k], f.x[:3], rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("method", ["ekf", "kf3d"])
def test_vectorised_batch_equals_single_track(receding, method):
    rig, dt, X, _ = receding
    Ys = []
    for seed in range(3):
        Y, rng = observe(rig, X[:80], 1.0, seed)
        Y[rng.random(80) < 0.1, :2] = np.nan
        Ys.append(Y)
    est = create(method, rig, dt, {})
    batch = est.run_batch(np.stack(Ys))
    for i, Y in enumerate(Ys):
        np.testing.assert_allclose(batch[i], create(method, rig, dt, {}).run(Y).position, atol=1e-8)


def test_batch_spsa_equals_run_and_its_update_acts(receding):
    """Algorithm 1's batch path gives each track's ``run``. From the oracle start (the true state)
    on this constant-velocity path predict-only is exact, so "tracks" means nothing there; what can
    fail: the update acts (it moves the estimate off the exact prediction: 26 mm median, measured)
    and stays below triangulation's error (39 mm). From a start 0.1 m off it does not converge
    (0.26 m median against predict-only's 0.1 m, measured; benchmarks/thesis.py finds Algorithm 1
    behind predict-only with the thesis's own settings too)."""
    rig, dt, X, V = receding
    Y = np.stack([observe(rig, X, 1.0, s)[0] for s in range(20)])
    init = {"mode": "given", "state": np.r_[X[0], V[0]].tolist()}  # oracle start: the true state
    P = create("spsa", rig, dt, {"init": init}).run_batch(Y)
    for i in (0, 7, 19):
        np.testing.assert_allclose(P[i], create("spsa", rig, dt, {"init": init}).run(Y[i]).position, atol=1e-9)
    exact = create("predict_only", rig, dt, {"init": init}).run_batch(Y)
    assert np.max(np.linalg.norm(exact - X, axis=2)) < 1e-9  # the baseline is exact here
    tri = triangulate(rig, Y.reshape(-1, 4)).reshape(P.shape)
    err = np.median(np.linalg.norm(P - X, axis=2))
    assert 1e-3 < err < np.median(np.linalg.norm(tri - X, axis=2)), err


def test_alphabeta_agrees_with_filterpy_gh():
    from filterpy.gh import GHFilter, GHKFilter

    rng = np.random.default_rng(0)
    z = np.cumsum(rng.normal(size=50)) + rng.normal(size=50)
    ours, ref = ABFilter(np.array([z[0]]), 0.1, 0.5, 0.2), GHFilter(z[0], 0.0, 0.1, 0.5, 0.2)
    ours3, ref3 = ABFilter(np.array([z[0]]), 0.1, 0.5, 0.2, 0.05), GHKFilter(z[0], 0.0, 0.0, 0.1, 0.5, 0.2, 0.05)
    for zk in z[1:]:
        ours.predict()
        ours.correct(np.array([zk]))
        ref.update(zk)
        ours3.predict()
        ours3.correct(np.array([zk]))
        ref3.update(zk)
        assert abs(ours.x[0] - ref.x) < 1e-12 and abs(ours3.x[0] - ref3.x) < 1e-12


@pytest.mark.parametrize("method", POINT_METHODS)
def test_gaps_never_nan_and_kalman_recovers(receding, method):
    rig, dt, X, V = receding
    Y, rng = observe(rig, X[:200], 1.0, 11)
    drop = rng.random(200) < 0.1
    Y[drop, :2] = np.nan
    Y[100:120, 2:] = np.nan  # 20-frame blackout of the right camera
    cfg = {"init": given(X, V, rng)} if method.startswith("spsa") else {}
    tr = create(method, rig, dt, cfg).run(Y)
    first = np.flatnonzero(np.all(np.isfinite(tr.position), axis=1))[0]
    assert np.all(np.isfinite(tr.position[first:]))
    if method in ("ekf", "ukf", "kf3d"):
        e = np.linalg.norm(tr.position - X[:200], axis=1)
        pre = np.median(e[70:100])
        assert np.median(e[120:150]) < 2 * pre + 1e-3


def test_bad_input(receding):
    rig, dt, X, _ = receding
    K = np.diag([600.0, 600.0, 1.0])
    with pytest.raises(CalibrationError, match="zero baseline"):
        create("ekf", StereoRig(Camera(K), Camera(K), (640, 480)), dt)
    with pytest.raises(StereotrackError, match="infinite"):
        create("ekf", rig, dt).run(np.full((5, 4), np.inf))
    with pytest.raises(StereotrackError, match="frames × 4"):
        create("spsa", rig, dt).run(np.zeros((5, 3)))
    for m in POINT_METHODS:
        tr = create(m, rig, dt).run(np.full((10, 4), np.nan))  # all-NaN: flagged, no crash
        assert np.all(np.isnan(tr.position)) and tr.predicted.all()
    # a point behind the cameras: mirrored observations triangulate behind → no start until valid
    behind = rig.project(-X[:5])
    Y = np.vstack([behind, rig.project(X[5:30])])
    for m in POINT_METHODS:
        tr = create(m, rig, dt).run(Y)
        assert np.all(np.isfinite(tr.position[-5:]))
