"""Four-point target: exact geometry, the paper's formulas, Riccati solutions, Table 1, end to end."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from scipy.linalg import block_diag

from pipeline.core.camera import StereoRig
from pipeline.core.errors import StereotrackError
from pipeline.core.settings import RunSettings
from pipeline.estimators import create
from pipeline.estimators.four_point import alpha_z_from_y, measure_camera, measure_stereo
from pipeline.estimators.kalman_bucy import (
    C4,
    G4,
    channel_matrix,
    check_model,
    riccati_step,
    steady_state_gain,
)
from renderers.motion import target_points

RIG = StereoRig.from_parameters(640, 480, 600.0, (324.5, 236.0), 0.3, 2.0)


def observe(center, alpha, phi, R=0.2, rig=RIG):
    pts, _ = target_points(np.array([center], float), np.array([alpha]), R, phi)
    return np.concatenate([rig.left.project(pts[0]), rig.right.project(pts[0])], axis=1)


@pytest.mark.parametrize(
    ("center", "alpha", "phi"),
    [((0, 0, 1.8), 0.5, 0.0), ((0, 0, 3.0), -0.7, 0.4), ((0.3, -0.2, 2.5), 0.9, -0.3), ((0, 0, 0.6), 1.2, 1.0)],
)
@pytest.mark.parametrize("cameras", ["left", "right", "both"])
def test_exact_measurement_noise_free(center, alpha, phi, cameras):
    m = measure_stereo(RIG, observe(center, alpha, phi), 0.2, "exact", cameras)
    assert abs(m.alpha - alpha) < 1e-9 and abs(m.distance - center[2]) < 1e-9 and abs(m.axis_angle - phi) < 1e-9
    np.testing.assert_allclose(m.center, center, atol=1e-9)


def test_exact_inversion_of_y_for_any_z():
    R, f = 0.5, 0.5
    for z, a in itertools.product((0.3, 0.5, 2.0, 7.0), (-1.0, -0.2, 0.4, 1.1)):
        if z <= R * abs(math.sin(a)):
            continue
        y1, y3 = f * R * math.cos(a) / (z + R * math.sin(a)), f * R * math.cos(a) / (z - R * math.sin(a))
        ea, ez, flag = alpha_z_from_y(y1, y3, R, f, "exact")
        assert flag == "" and abs(ea - a) < 1e-9 and abs(ez - z) < 1e-9


def test_paper_formula_exact_at_z_equal_f_and_biased_elsewhere():
    R, f = 0.5, 0.5
    for a in (-0.8, 0.3, 1.0):
        y1, y3 = f * R * math.cos(a) / (f + R * math.sin(a)), f * R * math.cos(a) / (f - R * math.sin(a))
        pa, pz, _ = alpha_z_from_y(y1, y3, R, f, "paper")
        assert abs(pa - a) < 1e-9  # eq. (3) exact at z = f
        assert abs(pz - (f * f - R * R * math.sin(a) ** 2) / (f * math.cos(a))) < 1e-9  # eq. (4)'s known bias
    z = 2.0
    y1, y3 = f * R * math.cos(0.5) / (z + R * math.sin(0.5)), f * R * math.cos(0.5) / (z - R * math.sin(0.5))
    pa, pz, _ = alpha_z_from_y(y1, y3, R, f, "paper")
    assert abs(pa - 0.5) > 0.1  # eq. (3) away from z = f
    assert abs(pz - (z * z - R * R * math.sin(0.5) ** 2) / (z * math.cos(0.5))) < 1e-9 and abs(pz - z) > 0.1


def test_riccati_algebraic_and_differential():
    A = block_diag(channel_matrix(-1.0, (1.0, 0.73)), channel_matrix(-0.2))
    GQG = G4 @ np.diag([0.05, 0.05]) @ G4.T
    R = np.diag([0.02**2, 0.01**2]) * 0.05
    _K, P = steady_state_gain(A, C4, GQG, R)
    residual = A @ P + P @ A.T + GQG - P @ C4.T @ np.linalg.inv(R) @ C4 @ P
    assert np.max(np.abs(residual)) < 1e-10
    Pt = np.diag([0.1, 0.5, 0.1, 0.5])
    for _ in range(4000):
        Pt = riccati_step(Pt, 0.05, A, C4, GQG, np.linalg.inv(R), "exact")
    np.testing.assert_allclose(Pt, P, rtol=1e-6, atol=1e-12)


def test_unobservable_model_is_a_clear_error():
    with pytest.raises(StereotrackError, match="not observable"):
        check_model(np.zeros((4, 4)), np.array([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]))
    with pytest.raises(StereotrackError, match=r"stabilising|stable"):
        steady_state_gain(np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0, 1.0]]), np.zeros((2, 2)), np.eye(1))


def test_table1_reproduction():
    """Soifer's Table 1, 60 fixed seeds. With the paper's own settings the π/3 row is the paper's
    to ±15 % in every SNR column (measured 0.92–1.08×); the π/6 row cannot be matched (our filter
    gives 0.34–0.42× the paper's errors here; docs/soifer.md shows the same gap) and is held below 0.5×. Both
    settings decrease with SNR and filter: the raw measurement's error is at least 2× the
    filtered one in every column (measured 2.2–3.5×; a filter that does nothing gives 1×)."""
    from pipeline.evaluation.soifer import BEST_SETTINGS, PAPER, PAPER_SETTINGS, table1

    ours = table1(BEST_SETTINGS, seeds=60)
    theirs = table1(PAPER_SETTINGS, seeds=60)
    for a0, paper in PAPER.items():
        for res in (ours[a0]["filtered"], theirs[a0]["filtered"]):
            assert all(a > b for a, b in itertools.pairwise(res)), res  # decreases with SNR
        assert all(o <= p for o, p in zip(ours[a0]["filtered"], paper, strict=True)), (a0, ours[a0])
        ratio = np.array(theirs[a0]["filtered"]) / np.array(paper)
        if a0 > 1.0:  # π/3
            assert np.all((ratio > 0.85) & (ratio < 1.15)), (a0, ratio)
        else:  # π/6
            assert np.all(ratio < 0.5), (a0, ratio)
        for res in (ours[a0], theirs[a0]):
            assert np.all(np.array(res["raw"]) >= 2.0 * np.array(res["filtered"])), (a0, res)


def test_table1_truth_and_priors():
    """The exact truth is the closed loop's solution; a prior that does not know the start is at rest
    (the two-point start) loses to the oracle prior on the π/3 row, as docs/soifer.md reports."""
    from scipy.integrate import solve_ivp

    from pipeline.evaluation.soifer import A_CL, BEST_SETTINGS, DT, NON_ORACLE_SETTINGS, PAPER, T_END, table1, true_alpha

    t = np.arange(round(T_END / DT) + 1) * DT
    sol = solve_ivp(lambda _t, x: A_CL @ x, (0, T_END), [math.pi / 6, 0.0], t_eval=t, rtol=1e-11, atol=1e-12)
    np.testing.assert_allclose(true_alpha(math.pi / 6, euler=False), sol.y[0], atol=1e-8)
    assert np.abs(true_alpha(math.pi / 6) - sol.y[0]).max() > 1e-3  # Euler differs visibly
    two_point = next(s for s in NON_ORACLE_SETTINGS if s.init == "two_point")
    oracle, blind = table1(BEST_SETTINGS, seeds=40, euler_truth=False), table1(two_point, seeds=40, euler_truth=False)
    a3 = math.pi / 3
    assert all(b > o for b, o in zip(blind[a3]["filtered"], oracle[a3]["filtered"], strict=True))
    assert all(b < r for b, r in zip(blind[a3]["filtered"], blind[a3]["raw"], strict=True))  # still filters
    assert sum(b <= p for b, p in zip(blind[a3]["filtered"], PAPER[a3], strict=True)) < 6


def test_bad_point_sets_are_flagged_never_nan_after_start():
    good = observe((0, 0, 2.0), 0.4, 0.0)
    collinear = good.copy()
    collinear[:, 1] = 236.0
    collinear[:, 3] = 236.0
    m = measure_stereo(RIG, collinear, 0.2)
    assert not m.ok and "degenerate" in m.flag
    swapped = good.copy()
    swapped[[0, 2]] = swapped[[2, 0]]  # 1 and 3 exchanged: y1 + y3 on the wrong side
    assert not measure_stereo(RIG, swapped, 0.2).ok
    y_bad = alpha_z_from_y(0.1, 0.9, 0.5, 5.0, "paper")  # |arcsin argument| > 1
    assert y_bad[2].startswith("arcsin") and math.isfinite(y_bad[0])
    assert measure_camera(np.full((4, 2), np.nan), RIG.left, 0.2).flag == "fewer than four points"
    Y = np.stack([observe((0, 0, 2.0 + 0.01 * k), 0.4 * math.exp(-0.05 * k), 0.0) for k in range(30)])
    Y[10, 2] = np.nan  # a point missing
    Y[12] = collinear
    Y[14, :, :2] = np.nan  # the left camera loses the target
    Y[15] = np.nan
    for method in ("four_point", "kalman_bucy", "pnp_kf"):
        tr = create(method, RIG, 0.05, {"radius": 0.2}).run(Y)
        if method != "four_point":  # filters predict through every bad frame
            assert np.all(np.isfinite(tr.extra["alpha"])) and np.all(np.isfinite(tr.extra["distance"]))
        assert tr.predicted[10] == (method != "four_point") or not np.isfinite(tr.extra["alpha"][10])


@pytest.mark.slow
def test_end_to_end_on_rendered_target(target_clip, tmp_path):
    from detectors.stage import detect_clip
    from pipeline.estimate import estimate_clip

    detect_clip(target_clip, RunSettings(detector="blob"), out_dir=tmp_path)
    res = estimate_clip(target_clip, RunSettings(methods=["four_point", "kalman_bucy", "pnp_kf"]), out_dir=tmp_path)
    metrics = json.loads((tmp_path / "metrics.json").read_text())["methods"]
    for m in ("four_point", "kalman_bucy", "pnp_kf"):
        assert metrics[m]["alpha_rmse_rad"] is not None and metrics[m]["distance_rmse_m"] is not None
    assert metrics["kalman_bucy"]["alpha_rmse_rad"] < metrics["four_point"]["alpha_rmse_rad"]
    assert metrics["pnp_kf"]["alpha_rmse_rad"] < 0.05 and metrics["kalman_bucy"]["distance_rmse_m"] < 0.05
    header = (tmp_path / "estimates" / "kalman_bucy.csv").read_text().splitlines()[0]
    assert header.endswith("alpha,distance")
    assert res.target is not None and res.target.radius == pytest.approx(0.2)


@pytest.mark.parametrize("method", ["kalman_bucy", "pnp_kf"])
def test_the_fused_view_gated_the_other_camera_s_own_view_is_kept(method):
    """A plate mis-detected in one camera: the filter's gate rejects the fused measurement and keeps
    the other camera's own view (what ``views`` gives of it alone); with both cameras' views off, or
    one camera's only, nothing is kept."""
    est = create(method, RIG, 1 / 30, {"gate": 0.9995, "pixel_sigma": 0.5})
    obs = observe(np.array([0.05, 0.0, 1.8]), 0.3, 0.0)
    bad = obs.copy()
    bad[0, 3] -= 40.0  # the right camera's points 1 and 3 apart: its foreshortening, α and z, wrong
    bad[2, 3] += 40.0
    good = est.views(obs)
    assert len(good) == 2 and abs(good[0].alpha - 0.3) < 0.02 and abs(good[1].alpha - 0.3) < 0.02
    predicted, S = np.array([0.3, 1.8]), np.diag([0.05**2, 0.02**2])
    fused = est.measure(bad) if method == "kalman_bucy" else est.pnp(bad)
    assert est.gated_measurement(np.array([fused.alpha, fused.distance]), predicted, S)
    kept = est.kept_view(bad, predicted, S)
    assert kept is not None and kept.alpha == good[0].alpha and kept.distance == good[0].distance  # the left's own
    both = bad.copy()
    both[0, 1] -= 40.0
    both[2, 1] += 40.0
    assert est.kept_view(both, predicted, S) is None
    one = bad.copy()
    one[:, :2] = np.nan  # the left camera missing: the fused view is the right's, nothing else to keep
    assert est.kept_view(one, predicted, S) is None
