"""``spsa_stereo`` (issue 12) and the predict-only baseline: accuracy against ground truth on
simulated observations with fixed seeds, convergence from a wrong start, gaps, and that Algorithm 1's
default update acts."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.estimators import create

SEEDS = (0, 1, 2, 3)


def noisy(rig, X, sigma, seed):
    return rig.project(X) + np.random.default_rng(100 + seed).normal(0.0, sigma, (len(X), 4))


def err(P, X):
    return np.linalg.norm(P - X, axis=1)


def rmse(P, X):
    return float(np.sqrt(np.nanmean(err(P, X) ** 2)))


def test_cost_in_disparity_coordinates_equals_the_model(receding):
    """The plain-float cost through ``g⁻¹`` equals the rig's normalized projection residual."""
    rig, dt, X, _ = receding
    est = create("spsa_stereo", rig, dt)
    Y = noisy(rig, X, 1.5, 0)
    yn = rig.normalize(Y)
    nrig = rig.normalized()
    for k in range(0, 300, 37):
        q = est.g(X[k] + 0.05)
        np.testing.assert_allclose(est.g_inv(*q), X[k] + 0.05, atol=1e-12)
        want = float(np.sum((nrig.project((X[k] + 0.05)[None])[0] - yn[k]) ** 2))
        assert abs(est.cost(*q, tuple(yn[k]), True, True) - want) < 1e-12 * max(want, 1.0)
        want_l = float(np.sum((nrig.left.project((X[k] + 0.05)[None])[0] - yn[k, :2]) ** 2))
        assert abs(est.cost(*q, tuple(yn[k]), True, False) - want_l) < 1e-12 * max(want_l, 1.0)


def test_spsa_stereo_beats_triangulation_1_5x_at_1_5_px(receding):
    rig, dt, X, _ = receding
    ratios = []
    for seed in SEEDS:
        Y = noisy(rig, X, 1.5, seed)
        tri = rmse(create("triangulation", rig, dt).run(Y).position, X)
        ours = rmse(create("spsa_stereo", rig, dt, {"seed": seed}).run(Y).position, X)
        ratios.append(tri / ours)
    assert min(ratios) >= 1.5, ratios


def test_spsa_stereo_stays_finite_through_gaps_and_recovers(receding):
    rig, dt, X, _ = receding
    Y = noisy(rig, X, 1.5, 0)
    Y[100:115] = np.nan  # a blackout
    Y[150:170, 2:] = np.nan  # the right camera lost
    Y[200:210, :2] = np.nan  # the left camera lost
    tr = create("spsa_stereo", rig, dt).run(Y)
    assert np.isfinite(tr.position[1:]).all() and np.isfinite(tr.velocity[1:]).all()
    assert tr.predicted[100:115].all() and not tr.predicted[150:170].any()
    tri = create("triangulation", rig, dt).run(noisy(rig, X, 1.5, 0)).position
    late = slice(230, 300)
    assert rmse(tr.position[late], X[late]) * 1.5 < rmse(tri[late], X[late])


@pytest.mark.parametrize("start_error", [0.3, 1.0])
def test_spsa_stereo_converges_from_a_wrong_start(receding, start_error):
    """Given a start ``start_error`` metres off (random direction) with a velocity 0.5 m/s off: the
    first update jumps to the measurement (gain 1, by construction), so what is tested is the rest.
    The velocity, which no single measurement gives, is within 0.2 m/s of the truth on average over
    frames 20–40 (the predict-only baseline from the same start stays 0.5 m/s off and fails the
    same bound); the position is within 5 cm at frame 20 and beats triangulation afterwards."""
    rig, dt, X, V = receding
    tri_late, ours_late = [], []
    for seed in SEEDS:
        rng = np.random.default_rng(seed)
        u, w = rng.normal(size=3), rng.normal(size=3)
        state = np.r_[X[0] + start_error * u / np.linalg.norm(u), V[0] + 0.5 * w / np.linalg.norm(w)]
        Y = noisy(rig, X, 1.5, seed)
        given = {"seed": seed, "init": {"mode": "given", "state": tuple(state)}}
        tr = create("spsa_stereo", rig, dt, given).run(Y)
        e = err(tr.position, X)
        assert e[0] == pytest.approx(start_error)
        assert e[20] < 0.05, (seed, e[:25])
        assert np.mean(err(tr.velocity[20:40], V[20:40])) < 0.2, seed
        carried = create("predict_only", rig, dt, given).run(Y)
        assert np.mean(err(carried.velocity[20:40], V[20:40])) > 0.2  # the bound can fail
        tri_late.append(rmse(create("triangulation", rig, dt).run(Y).position[20:], X[20:]))
        ours_late.append(rmse(tr.position[20:], X[20:]))
    assert np.mean(ours_late) * 1.5 < np.mean(tri_late)


def test_predict_only_is_the_start_carried_forward(receding):
    rig, dt, X, _ = receding
    Y = noisy(rig, X, 1.5, 0)
    cfg = {"init": {"frames": 5}}
    po = create("predict_only", rig, dt, cfg).run(Y)
    start = create("ekf", rig, dt, cfg).initiator.first(Y)
    k0 = start.frame
    k = np.arange(k0, 300)
    np.testing.assert_allclose(po.position[k0:], start.state[:3] + (k - k0)[:, None] * dt * start.state[3:], atol=1e-9)
    assert po.predicted[k0 + 1 :].all() and not po.predicted[k0]
    static = create("predict_only", rig, dt, {**cfg, "static": True}).run(Y)
    np.testing.assert_allclose(static.position[k0:], np.broadcast_to(start.state[:3], (300 - k0, 3)), atol=1e-12)


def test_algorithm_1_default_update_acts(receding):
    """Started from the true position with a 0.2 m/s velocity error, Algorithm 1's default gains
    move the estimate: on every seed its trajectory leaves predict-only's (same start, no update) by
    more than 10 cm RMS and its RMSE differs from predict-only's by more than 5 cm. (Whether that
    helps is the benchmark's question: on this rig it mostly does not — see docs/thesis.md.)"""
    rig, dt, X, V = receding
    diffs = []
    for seed in SEEDS:
        rng = np.random.default_rng(seed)
        w = rng.normal(size=3)
        init = {"mode": "given", "state": tuple(np.r_[X[0], V[0] + 0.2 * w / np.linalg.norm(w)])}
        Y = noisy(rig, X, 1.5, seed)
        po = create("predict_only", rig, dt, {"init": init}).run(Y).position
        alg1 = create("spsa", rig, dt, {"init": init, "seed": seed}).run(Y).position
        assert rmse(alg1, po) > 0.10, seed
        diffs.append(abs(rmse(po, X) - rmse(alg1, X)))
    assert min(diffs) > 0.05, diffs


def test_spsa_stereo_gate_skips_an_outlier_detection(receding):
    """A left detection 60 px off vertically on frame 150 (the wrong blob, off the epipolar line):
    with a gate the frame is a gap, ordinary frames pass, and the estimate on that frame is closer to
    the truth than without the gate. (A horizontal offset is a depth change the frame's own cost
    cannot see; the gate does not catch it — stated in the module docstring.)"""
    rig, dt, X, _ = receding
    plain_e, gated_e = [], []
    for seed in range(3):
        Y = noisy(rig, X, 1.0, seed)
        Y[150, 1] += 60.0
        plain = create("spsa_stereo", rig, dt, {"gate": 0}).run(Y)  # the cost gate alone, the χ² gate off
        gated = create("spsa_stereo", rig, dt, {"cost_gate": 1e-4, "gate": 0}).run(Y)
        assert gated.predicted[150] and not plain.predicted[150]
        assert not gated.predicted[1:150].any() and not gated.predicted[151:].any()
        plain_e.append(err(plain.position, X)[150])
        gated_e.append(err(gated.position, X)[150])
        assert gated_e[-1] < plain_e[-1], seed
    assert np.mean(plain_e) > 1.5 * np.mean(gated_e), (plain_e, gated_e)


def test_newton_step_lands_on_the_frames_minimum(receding):
    """From a prediction several pixels off, the simultaneous-perturbation Newton steps reach the
    frame's own least-squares point (scipy) to well under the pixel noise, in ≤ 19 cost calls."""
    from scipy.optimize import least_squares

    rig, dt, X, _ = receding
    est = create("spsa_stereo", rig, dt)
    Y = noisy(rig, X, 1.5, 0)
    yn = rig.normalize(Y)
    nrig = rig.normalized()
    rng = np.random.default_rng(7)
    calls = [0]
    cost = est.cost

    def counted(*a):
        calls[0] += 1
        return cost(*a)

    est.cost = counted
    for k in range(0, 300, 23):
        start = X[k] + rng.normal(0.0, 0.05, 3)  # ~5–20 px off in the image
        calls[0] = 0
        q = est._minimise(est.g(start), tuple(yn[k]), True, True)
        assert calls[0] <= 19
        best = least_squares(lambda p, k=k: nrig.project(p[None])[0] - yn[k], start, xtol=1e-14, ftol=1e-14).x
        got = nrig.project(np.array(est.g_inv(*q[:3]))[None])[0]
        want = nrig.project(best[None])[0]
        assert np.max(np.abs(got - want)) * rig.left.K[0, 0] < 0.1  # pixels, against σ = 1.5 px


def test_disparity_floor_follows_the_disparity(receding):
    """The disparity's gain floor is proportional to the disparity (``alpha_depth_per_disparity ·
    b/z``): near the rig depth may follow more than far away. Against truth, on the two scenarios
    whose depth changes most, it beats a fixed floor of 0.1 (mean 3-D RMSE over 6 seeds; measured
    55.5 against 60.5 mm on receding, 194 against 226 mm on accelerating), and the memory it
    reaches grows as the marker recedes."""
    from renderers.motion import simulate_truth
    from renderers.scenario import load_scenario

    fixed = {"alpha_depth_per_disparity": 1e-9, "alpha_min_depth": 0.1}
    for name in ("receding", "accelerating"):
        sc = load_scenario(name).with_overrides(frames=300)
        rig, dt, X = sc.rig.build(), sc.dt, simulate_truth(sc).positions[:, 0]
        r: dict[str, list[float]] = {"proportional": [], "fixed": []}
        for seed in range(6):
            Y = noisy(rig, X, 1.0, seed)
            for key, cfg in (("proportional", {}), ("fixed", fixed)):
                r[key].append(rmse(create("spsa_stereo", rig, dt, cfg).run(Y).position[1:], X[1:]))
        assert np.mean(r["proportional"]) < np.mean(r["fixed"]), (name, r)
    rig, dt, X, _ = receding
    est = create("spsa_stereo", rig, dt)
    mem = []
    for y in noisy(rig, X, 1.0, 0):
        est.step(y)
        mem.append(est._mem[2] if est.initialized else np.nan)
    assert np.nanmax(mem[:60]) < np.nanmax(mem[-60:])
