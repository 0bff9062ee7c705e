"""The IMM EKF (pipeline.estimators.imm): one model is the EKF; on a marker that cruises and then
turns hard it follows where the single-q EKF overshoots, without costing the smooth case, and its
manoeuvre model takes over during the turns. Held out: the rigs (second camera above, left) and
the seeds (10–14); the motions (renderers.paths) were made for this test, the IMM's defaults set
before it ran."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.core.camera import Camera, StereoRig
from pipeline.estimators import create
from pipeline.estimators.base import Estimator
from renderers.paths import observed, sinusoid, turning

RIG = StereoRig.from_parameters(640, 480, (600.0, 600.0), (319.5, 239.5), 0.3)
LAYOUTS = {"above": StereoRig(RIG.left, Camera(RIG.left.K, np.eye(3), np.array([0.0, 0.3, 0.0])), RIG.image_size),
           "left": StereoRig(RIG.left, Camera(RIG.left.K, np.eye(3), np.array([0.3, 0.0, 0.0])), RIG.image_size)}
DT = 1 / 30


def manoeuvring(n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    return turning(n, seed, DT)


def smooth(n: int, seed: int) -> np.ndarray:
    return sinusoid(n, seed, DT)


def observe(rig: StereoRig, X: np.ndarray, seed: int) -> np.ndarray:
    """1 px noise; a camera that does not see the marker (outside its image) gives nothing."""
    return observed(rig, X, seed)


def rmse(track, X: np.ndarray) -> float:
    e = np.linalg.norm(track.position[5:] - X[5:], axis=1)
    return float(np.sqrt(np.nanmean(e**2)))


def nees_per_dof(track, X: np.ndarray) -> float:
    """Median position NEES over 3 degrees of freedom, over χ²₃'s median (1 for a consistent filter)."""
    e, C = track.position - X, track.covariance[:, :3, :3]
    ok = np.isfinite(e).all(axis=1) & np.isfinite(C).all(axis=(1, 2))
    return float(np.median([d @ np.linalg.solve(c, d) for d, c in zip(e[ok][5:], C[ok][5:], strict=True)]) / 2.366)


def test_with_one_model_it_is_the_ekf():
    """``manoeuvre_q_scale = 1``: both models are the EKF, and so is the mixture (to 1e-9), through
    gaps, a camera's outliers (gated) and the restarts they bring."""
    X, _ = manoeuvring(200, 3)
    Y = observe(RIG, X, 3)
    Y[60:75] = np.nan
    Y[100:108, 2:] += 40.0
    imm = create("ekf_imm", RIG, DT, {"manoeuvre_q_scale": 1.0}).run(Y)
    ekf = Estimator.run(create("ekf", RIG, DT), Y)  # the EKF step by step (its compiled run is tested equal)
    np.testing.assert_allclose(imm.position, ekf.position, atol=1e-9)
    np.testing.assert_array_equal(imm.predicted, ekf.predicted)


def test_run_steps_and_batch_agree():
    X, _ = manoeuvring(120, 4)
    Y = observe(RIG, X, 4)
    est = create("ekf_imm", RIG, DT)
    track = est.run(Y)
    est.reset()
    steps = np.array([est.step(y).position for y in Y])
    np.testing.assert_array_equal(track.position, steps)
    batch = create("ekf_imm", RIG, DT).run_batch(np.stack([Y, observe(RIG, X, 5)]))
    np.testing.assert_array_equal(batch[0], track.position)


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_it_follows_hard_turns_without_costing_smooth_motion(layout):
    """Five seeds per held-out layout: on the turning marker the IMM's RMSE is at most 0.85× the
    EKF's (median; the EKF's one q lags every turn) and below triangulation's, no seed more than 5 %
    over the EKF, far below the predict-only baseline's, and its NEES per degree of freedom nearer 1
    than the EKF's; on smooth motion the IMM is within 2 % of the EKF (each seed)."""
    rig = LAYOUTS[layout]
    turn: dict[str, list[float]] = {m: [] for m in ("ekf", "ekf_imm", "triangulation", "predict_only")}
    nees: dict[str, list[float]] = {"ekf": [], "ekf_imm": []}
    for seed in range(10, 15):
        X, _ = manoeuvring(300, seed)
        Y = observe(rig, X, seed)
        for m in turn:
            tr = create(m, rig, DT).run(Y)
            turn[m].append(rmse(tr, X))
            if m in nees:
                nees[m].append(nees_per_dof(tr, X))
        assert turn["ekf_imm"][-1] <= 1.05 * turn["ekf"][-1], (seed, turn)
        Xs = smooth(300, seed)
        Ys = observe(rig, Xs, seed)
        assert rmse(create("ekf_imm", rig, DT).run(Ys), Xs) <= 1.02 * rmse(create("ekf", rig, DT).run(Ys), Xs)
    med = {m: float(np.median(v)) for m, v in turn.items()}
    assert med["ekf_imm"] <= 0.85 * med["ekf"] and med["ekf_imm"] < med["triangulation"], med
    assert med["ekf_imm"] < 0.2 * med["predict_only"], med
    assert abs(np.median(nees["ekf_imm"]) - 1) < abs(np.median(nees["ekf"]) - 1), nees


def test_the_manoeuvre_model_takes_over_in_the_turns():
    """The manoeuvre model's probability (``extra``) is on average at least twice as high in the
    frames of a turn (and the three after it) as while the marker cruises."""
    ratios = []
    for seed in range(10, 15):
        X, burst = manoeuvring(300, seed)
        mu = create("ekf_imm", RIG, DT).run(observe(RIG, X, seed)).extra["manoeuvre_probability"]
        turning = np.convolve(burst, np.ones(4), "full")[: len(burst)] > 0
        ratios.append(np.nanmean(mu[turning]) / np.nanmean(mu[~turning]))
    assert np.median(ratios) >= 2.0, ratios


def test_estimate_runs_it_only_when_named(tmp_path):
    """Not among the methods ``estimate`` runs by default; named, it runs through the pipeline."""
    import shutil
    from pathlib import Path

    from pipeline.app.run import process_clip
    from pipeline.core.settings import RunSettings
    from pipeline.estimators import default_methods

    assert "ekf" in default_methods() and "ekf_imm" not in default_methods()
    clip = tmp_path / "clip"
    shutil.copytree(Path(__file__).resolve().parents[2] / "data" / "clips" / "sample_small", clip)
    res = process_clip(clip, settings=RunSettings(methods=("ekf", "ekf_imm"), images=False, recording=False))
    ms = res.estimate.metrics["methods"]
    assert ms["ekf_imm"]["rmse"] < 2 * ms["ekf"]["rmse"] and (clip / "out" / "estimates" / "ekf_imm.csv").is_file()


def test_more_cameras():
    """A ring of four cameras (2N-wide observations, one camera missing now and then): with one
    model it is the EKF there too, and with two it follows the turning marker at least as well."""
    from pipeline.core.rig import ring_rig

    rig = ring_rig(4).in_frame_of(0)
    X, _ = manoeuvring(150, 21)
    X = X - [0.0, 0.0, 2.2] + rig.cameras[0].center + 2.0 * rig.cameras[0].R[2]  # in front of the ring
    rng = np.random.default_rng(21)
    Y = rig.project(X) + rng.normal(0, 1.0, (150, 8))
    Y[rng.random((150, 4)).repeat(2, axis=1) < 0.1] = np.nan
    one = create("ekf_imm", rig, DT, {"manoeuvre_q_scale": 1.0}).run(Y)
    np.testing.assert_allclose(one.position, Estimator.run(create("ekf", rig, DT), Y).position, atol=1e-9)
    assert rmse(create("ekf_imm", rig, DT).run(Y), X) <= 1.05 * rmse(create("ekf", rig, DT).run(Y), X)


def _with_lookalike(rig: StereoRig, X: np.ndarray, Y: np.ndarray, camera: int, k0: int = 60, n: int = 12) -> np.ndarray:
    """``Y`` with one camera's detections of frames k0…k0+n−1 taken by a static look-alike 0.3 m
    behind the marker on that camera's ray at k0: there it covers the marker's image, then stays
    while the marker moves on (each detection inside the camera's own gate at first)."""
    cam = rig.cameras[camera]
    ray = X[k0] - cam.center
    Z = X[k0] + 0.3 * ray / np.linalg.norm(ray)
    out = Y.copy()
    uv = rig.project(Z[None])[0, 2 * camera : 2 * camera + 2]
    out[k0 : k0 + n, 2 * camera : 2 * camera + 2] = uv + np.random.default_rng(k0).normal(0, 1, (n, 2))
    return out


def test_a_lookalike_in_one_camera_does_not_send_it_far_further_off_than_the_ekf():
    """Held out: a look-alike in one camera for 12 frames, on each layout, each camera, seeds
    10–12 (18 runs): the IMM's median RMSE within 1.5× the EKF's (1.12× here; 3.2× without the joint
    check, :func:`~pipeline.estimators.gating.joint_gate`, where the look-alike's pairs, each camera
    inside its own gate, hand the manoeuvre model the likelihood and its wider gates keep the
    look-alike). The check's probability was set on the rendered clips (below) and the turns above,
    before this scene was written; a slowly separating look-alike still costs the IMM more than
    the EKF in some runs."""
    rmses: dict[str, list[float]] = {"ekf": [], "ekf_imm": []}
    for rig in (RIG, *LAYOUTS.values()):
        for seed in range(10, 13):
            X = smooth(150, seed)
            Y = observe(rig, X, seed)
            for camera in (0, 1):
                Yl = _with_lookalike(rig, X, Y, camera)
                for m in rmses:
                    rmses[m].append(rmse(create(m, rig, DT).run(Yl), X))
    med = {m: float(np.median(v)) for m, v in rmses.items()}
    assert med["ekf_imm"] <= 1.5 * med["ekf"], med


def _lookalike_runs():
    """The 18 look-alike runs above: (rig, X, observations)."""
    for rig in (RIG, *LAYOUTS.values()):
        for seed in range(10, 13):
            X = smooth(150, seed)
            Y = observe(rig, X, seed)
            for camera in (0, 1):
                yield rig, X, _with_lookalike(rig, X, Y, camera)


@pytest.mark.parametrize("method", ["ekf", "ukf", "kf3d"])
def test_the_joint_check_keeps_a_lookalike_from_the_filters(method):
    """The same look-alike runs (#38 item 5): the EKF, UKF and kf3d check the cameras each gate
    keeps together, as the IMM does (the same probability, :data:`~pipeline.estimators.gating.JOINT_GATE`,
    not set on this scene). Their worst run is at most 0.7× the same filter's without the check
    (EKF 190 against 344 mm, UKF 190/343, kf3d 142/215), the median no worse; and the check gives
    the same numbers on every path (``step``, ``run`` compiled or not, ``run_batch``)."""
    with_check, without = [], []
    for i, (rig, X, Y) in enumerate(_lookalike_runs()):
        est = create(method, rig, DT)
        t = est.run(Y)
        with_check.append(rmse(t, X))
        off = create(method, rig, DT)
        off.joint_check = False
        without.append(rmse(off.run(Y), X))
        if i % 6 == 0:
            np.testing.assert_allclose(est.run_batch(np.stack([Y, Y]))[1], t.position, atol=1e-9)
            np.testing.assert_allclose(Estimator.run(create(method, rig, DT), Y).position, t.position, atol=1e-9)
    assert max(with_check) <= 0.7 * max(without), (max(with_check), max(without))
    assert np.median(with_check) <= 1.01 * np.median(without), (np.median(with_check), np.median(without))


@pytest.fixture(scope="module")
def lookalike_clip(tmp_path_factory):
    """The ``lookalike`` scenario as the failure was found (90 frames, PNG), rendered and detected."""
    from detectors.stage import detect_clip
    from renderers.render import render_clip
    from renderers.scenario import load_scenario

    clip = tmp_path_factory.mktemp("lookalike") / "lookalike"
    render_clip(load_scenario("lookalike").with_overrides(frames=90), clip, fmt="png", workers=1)
    detect_clip(clip)
    return clip


def _lookalike_rmse(clip, methods: list[str], gate: bool, out) -> dict[str, float]:
    """Each method's 3-D RMSE on the clip, estimated at the defaults (σ estimated), gates on or off."""
    from pipeline.core.settings import RunSettings
    from pipeline.estimate import estimate_clip

    configs = {} if gate else {m: {"gate": 0.0} for m in methods}
    res = estimate_clip(clip, RunSettings(methods=methods, configs=configs), out_dir=out, in_dir=clip / "out")
    return {m: res.metrics["methods"][m]["rmse"] for m in methods}


@pytest.mark.slow
def test_the_rendered_lookalike_clip_as_a_user_runs_it(lookalike_clip, tmp_path):
    """Estimated at the defaults (σ estimated): the IMM no further off than the EKF. Without the
    joint check it ran 3.9 m off after the red cube crossed the marker (RMSE 979 mm against the
    EKF's 49 mm). Not held out: the check was set on it."""
    got = _lookalike_rmse(lookalike_clip, ["ekf", "ekf_imm"], True, tmp_path)
    assert got["ekf_imm"] <= got["ekf"], got


@pytest.mark.slow
@pytest.mark.parametrize("method", ["kf3d", "kf3d_rts", "alphabetagamma", "alphabeta"])
def test_on_the_rendered_lookalike_clip_the_3d_filters_gated_are_no_worse_than_ungated(method, lookalike_clip, tmp_path):
    """#38 (item 5): kf3d and the 3-D alpha-betas gated are no further off than ungated. Before
    the joint check and the update from one kept camera, kf3d coasted eight frames on a velocity
    the merging blobs had corrupted: 58.5 mm gated against 47.6 ungated (22.9 after). Before the
    detector found the marker's own disc in a blob merged with the cube (detectors.merged), both
    cameras agreed on the merged blobs for five frames and alphabeta followed them: 38.6 mm gated
    against 36.2 ungated (now 2.2 both; kf3d 1.6 against 2.3). Not held out: the detector's merge
    thresholds were set on this clip."""
    gated = _lookalike_rmse(lookalike_clip, [method], True, tmp_path / "gated")[method]
    ungated = _lookalike_rmse(lookalike_clip, [method], False, tmp_path / "ungated")[method]
    assert gated <= ungated, (gated, ungated)
