"""Surviving imperfect rigs: χ² gating against outliers in every method that updates (each camera on
its own), and the cameras' time offset found from the detections and applied. Observations are
simulated from each scenario's exact truth; layouts and trajectories are held out of the tuning
(the gates' probabilities are textbook, not fitted): the second camera right and above, a
receding and a manoeuvring marker."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from pipeline.core.detections import Detections
from pipeline.core.settings import RunSettings
from pipeline.core.sync import estimate_offset, resolve_sync
from pipeline.estimators import create
from pipeline.evaluation.noise import estimate_pixel_sigma
from renderers.motion import simulate_truth
from renderers.scenario import load_scenario, parse_scenario

GATED = ["kf3d", "ekf", "ukf", "kf3d_rts", "ekf_rts", "alphabeta", "alphabetagamma", "spsa_stereo"]


def scene(name: str, layout: str, frames: int = 200):
    s = load_scenario(name).with_overrides(frames=frames)
    d = s.model_dump(mode="json")
    if layout == "above":
        d["rig"]["right"] = {"position": [0.0, -0.3, 0.0]}
        d["rig"]["toe_in_deg"] = 0.0
    s = parse_scenario(d)
    return s, simulate_truth(s), s.rig.build()


def rmse(track, X) -> float:
    return float(np.sqrt(np.nanmean(np.sum((track.position - X) ** 2, axis=1))))


@pytest.fixture(scope="module")
def outlier_runs() -> list:
    """(rig, dt, truth, clean observations, with outliers, outlier mask) for 20 seeds × 2
    trajectories × 2 layouts; 5 % of frames have one camera's detection replaced by a random pixel."""
    runs = []
    for name in ("receding", "maneuvering"):
        for layout in ("right", "above"):
            s, tr, rig = scene(name, layout)
            X = tr.positions[:, 0]
            w, h = rig.image_size
            for seed in range(20):
                rng = np.random.default_rng(seed)
                Y = rig.project(X) + rng.normal(0, 1.0, (len(X), 4))
                Yo = Y.copy()
                bad = rng.random(len(X)) < 0.05
                cam = rng.integers(0, 2, len(X))
                for k in np.flatnonzero(bad):
                    Yo[k, 2 * cam[k] : 2 * cam[k] + 2] = rng.uniform([0, 0], [w, h])
                runs.append((rig, s.dt, X, Y, Yo, bad))
    return runs


@pytest.mark.slow
@pytest.mark.parametrize("method", GATED)
def test_gated_methods_ignore_outliers(method, outlier_runs):
    clean, dirty, rejected, injected, false, observed = [], [], 0.0, 0, 0.0, 0
    cfg = {"pixel_sigma": 1.0}  # every method at its default gate
    for rig, dt, X, Y, Yo, bad in outlier_runs:
        a = create(method, rig, dt, cfg).run(Y)
        b = create(method, rig, dt, cfg).run(Yo)
        clean.append(rmse(a, X))
        dirty.append(rmse(b, X))
        rejected += np.nansum(b.extra["gated"][bad])
        injected += int(bad.sum())
        false += np.nansum(a.extra["gated"])
        observed += 2 * len(X)
    clean, dirty = np.array(clean), np.array(dirty)
    assert dirty.mean() <= 1.3 * clean.mean(), (dirty.mean(), clean.mean())
    assert np.all(dirty <= 5 * clean), (dirty / clean).max()  # no run diverges
    assert rejected >= 0.9 * injected, (rejected, injected)
    assert false < 0.02 * observed, (false, observed)


@pytest.mark.slow
def test_the_same_filter_without_its_gate_fails_that_bound(outlier_runs):
    """The bound above is one a filter can fail: the EKF with gating off."""
    clean, dirty = [], []
    for rig, dt, X, Y, Yo, _bad in outlier_runs[::4]:
        clean.append(rmse(create("ekf", rig, dt, {"pixel_sigma": 1.0, "gate": 0}).run(Y), X))
        dirty.append(rmse(create("ekf", rig, dt, {"pixel_sigma": 1.0, "gate": 0}).run(Yo), X))
    assert np.mean(dirty) > 1.3 * np.mean(clean)


def test_gating_is_the_same_on_every_path():
    """step, run and run_batch gate identically (outliers included)."""
    s, tr, rig = scene("maneuvering", "above", 120)
    X = tr.positions[:, 0]
    rng = np.random.default_rng(3)
    Y = np.stack([rig.project(X) + rng.normal(0, 1.0, (len(X), 4)) for _ in range(3)])
    Y[:, 40:60:4, :2] = rng.uniform(0, 400, (3, 5, 2))
    for m in ("kf3d", "ekf"):
        est = create(m, rig, s.dt, {"pixel_sigma": 1.0, "restart_after": 3})
        batch = est.run_batch(Y)
        for i in range(3):
            run = create(m, rig, s.dt, {"pixel_sigma": 1.0, "restart_after": 3}).run(Y[i])
            np.testing.assert_allclose(batch[i], run.position, atol=1e-9, err_msg=m)
            assert np.nansum(run.extra["gated"]) >= 4


KALMAN = ["kf3d", "ekf", "ukf", "kf3d_rts", "ekf_rts"]
FIXED_GAIN = ["alphabeta", "alphabetagamma", "spsa_stereo"]


@pytest.mark.parametrize("method", KALMAN)
def test_a_track_gated_too_long_restarts(method):
    """A marker that jumps 40 cm (another object of its colour taking over): every camera is gated,
    and after restart_after frames the track restarts from the detections and says so; ``step``
    gives the same restart as ``run``."""
    s, tr, rig = scene("receding", "right", 100)
    X = tr.positions[:, 0].copy()
    X[50:] += [0.4, 0.0, 0.0]
    Y = rig.project(X) + np.random.default_rng(0).normal(0, 0.5, (len(X), 4))
    est = create(method, rig, s.dt, {"pixel_sigma": 0.5, "restart_after": 5})
    t = est.run(Y)
    restarts = np.flatnonzero(t.extra["restart"] > 0)
    assert list(restarts) == [54], restarts
    assert np.linalg.norm(t.position[-1] - X[-1]) < 0.05
    est.reset()
    streamed = est.finish([est.step(y) for y in Y], Y)
    np.testing.assert_allclose(streamed.position, t.position, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(np.nan_to_num(streamed.extra["restart"]), np.nan_to_num(t.extra["restart"]))


@pytest.mark.parametrize("method", FIXED_GAIN)
def test_fixed_gain_gates_tell_one_wrong_camera_from_lag(method):
    """Filters whose gains ignore their lag cannot tell lag from a jump by the innovation alone;
    both cameras agreeing on one point can: the same 40 cm jump is followed (not gated away), while
    a wrong blob stuck in one camera for 12 frames is gated on every one of them and never restarts
    the track (its detections do not triangulate); ``step`` gives what ``run`` gives."""
    s, tr, rig = scene("receding", "right", 100)
    X = tr.positions[:, 0].copy()
    X[50:] += [0.4, 0.0, 0.0]
    Y = rig.project(X) + np.random.default_rng(0).normal(0, 0.5, (len(X), 4))
    est = create(method, rig, s.dt, {"pixel_sigma": 0.5})
    t = est.run(Y)
    gated = np.nansum(t.extra["gated"][45:])  # at most a camera for a frame or two while the gains catch up
    assert gated < 8 and np.nansum(t.extra["restart"]) == 0 and np.linalg.norm(t.position[-1] - X[-1]) < 0.05
    Ys = rig.project(tr.positions[:, 0]) + np.random.default_rng(1).normal(0, 0.5, (len(X), 4))
    Ys[30:42, :2] = [100.0, 400.0]  # the left camera locked on something else
    t = est.run(Ys)
    assert np.all(t.extra["gated"][30:42] == 1) and np.nansum(t.extra["restart"]) == 0
    est.reset()
    streamed = est.finish([est.step(y) for y in Ys], Ys)
    np.testing.assert_allclose(streamed.position, t.position, rtol=1e-9, atol=1e-9)


# -- the time offset ------------------------------------------------------------------------------


def offset_clip(name: str, layout: str, frac: float, seed: int, frames: int = 150):
    """Observations of a rig whose right camera is ``frac`` frames late, and the same synchronised."""
    s, tr, rig = scene(name, layout, frames)
    X = tr.positions[:, 0]
    Xr = tr.at(tr.t + frac * s.dt, [0])[0][:, 0]
    rng = np.random.default_rng(seed)
    late = np.column_stack([rig.left.project(X), rig.right.project(Xr)]) + rng.normal(0, 1.0, (frames, 4))
    synced = rig.project(X) + rng.normal(0, 1.0, (frames, 4))
    return rig, s.dt, X, late, synced


@pytest.mark.slow
@pytest.mark.parametrize("layout", ["right", "above"])
def test_offset_recovered_and_applied(layout):
    """Offsets of 0.1–0.6 frame on a marker that moves across the epipolar lines are recovered
    within 0.05 frame (median over seeds), and the EKF with the offset applied is within 1.2× (median)
    of its RMSE on the synchronised clip; without the offset it is not."""
    errors, ratios, unmodelled = [], [], []
    for frac in (0.1, 0.3, 0.6):
        for seed in range(8):
            rig, dt, X, late, synced = offset_clip("sine", layout, frac, seed)
            est = estimate_offset(rig, {"m": late}, 1 / dt)
            errors.append(abs(est.offset_s / dt - frac))
            sync, _ = resolve_sync("auto", rig, {"m": late}, 1 / dt)
            base = rmse(create("ekf", rig, dt, {"pixel_sigma": 1.0}).run(synced), X)
            fixed = create("ekf", rig, dt, {"pixel_sigma": 1.0}, time_offset=sync.offset_s if sync.applied else 0.0)
            ratios.append(rmse(fixed.run(late), X) / base)
            if frac == 0.6:
                unmodelled.append(rmse(create("ekf", rig, dt, {"pixel_sigma": 1.0}).run(late), X) / base)
    assert np.median(errors) <= 0.05, np.median(errors)
    assert np.median(ratios) <= 1.2, np.median(ratios)
    assert np.median(unmodelled) > 1.2, np.median(unmodelled)  # the bound is one the EKF fails without it


def _manoeuvring_late(layout: str, trajectory: int, delta: float, seed: int):
    """(rig, dt, truth, late, synchronised): the manoeuvring scenario's random accelerations of seed
    ``trajectory``, 300 frames, the second camera at ``layout``, its frames ``delta`` frames late;
    both clips with the same 1 px noise."""
    d = load_scenario("maneuvering").with_overrides(frames=300, seed=trajectory).model_dump(mode="json")
    d["rig"]["right"], d["rig"]["toe_in_deg"] = LAYOUTS[layout], 0.0
    s = parse_scenario(d)
    tr, rig = simulate_truth(s), s.rig.build()
    X, Xr = tr.positions[:, 0], tr.at(tr.t + delta * s.dt, [0])[0][:, 0]
    noise = np.random.default_rng(seed).normal(0, 1.0, (len(X), 4))
    return rig, s.dt, X, np.column_stack([rig.left.project(X), rig.right.project(Xr)]) + noise, rig.project(X) + noise


def _ekf_rmse(rig, dt, Y, X) -> float:
    """The EKF as `stereotrack estimate` runs it: σ estimated from the observations."""
    return rmse(create("ekf", rig, dt, {"pixel_sigma": estimate_pixel_sigma(rig, {"m": Y})}).run(Y), X)


@pytest.mark.slow
def test_an_offset_on_a_manoeuvring_marker_is_found_well_enough_for_the_ekf():
    """#38: a manoeuvring marker seen by a rig whose second camera is to the right crosses the
    epipolar lines only by its random vertical motion, so its detections hold little of the offset.
    Held out: the four trajectories (the scenario's random accelerations) of seeds 1–30 whose
    Cramér–Rao bound (``benchmarks/sync.py``) is 0.1 frame or more, chosen by that bound alone (the
    smoothing was chosen on seed 0's), and the noise seeds. With ±½ and ±1 frame offsets, the EKF
    after the offset found and applied as `estimate` does is within 1.2× its RMSE on the same clip
    synchronised (median per offset), and no offset is applied to the synchronised clips. With the
    tracks unsmoothed (``SMOOTH_HALF`` 0: the detections, blocks of 10, √2) the medians are
    1.13–1.34× per offset: the interval then often holds 0 and nothing is applied."""
    ratios: dict[float, list[float]] = {}
    applied_synced = 0
    for trajectory in (5, 13, 26, 30):
        for delta in (0.5, -0.5, 1.0, -1.0):
            for seed in range(3):
                rig, dt, X, late, synced = _manoeuvring_late("right", trajectory, delta, seed)
                _, aligned = resolve_sync("auto", rig, {"m": late}, 1 / dt)
                ratios.setdefault(delta, []).append(_ekf_rmse(rig, dt, aligned["m"], X) / _ekf_rmse(rig, dt, synced, X))
                applied_synced += resolve_sync("auto", rig, {"m": synced}, 1 / dt)[0].applied if delta == 0.5 else 0
    medians = {d: float(np.median(r)) for d, r in ratios.items()}
    assert max(medians.values()) <= 1.2, medians
    assert applied_synced == 0


@pytest.mark.slow
def test_clean_clips_keep_zero_in_the_interval():
    covered, applied = [], []
    for layout in ("right", "above"):
        for seed in range(15):
            rig, dt, _X, _late, synced = offset_clip("sine", layout, 0.0, seed)
            sync, _ = resolve_sync("auto", rig, {"m": synced}, 1 / dt)
            covered.append(sync.ci_s[0] <= 0.0 <= sync.ci_s[1])
            applied.append(sync.applied)
    assert np.mean(covered) >= 0.9, np.mean(covered)
    assert applied == [not c for c in covered]  # applied only where the interval excludes 0


@pytest.mark.slow
def test_rendered_offset_found_from_detections_and_from_timestamps(tmp_path):
    """The sync_offset scenario (right camera half a frame late), rendered: from the detections
    alone the offset is found within 0.05 frame and applied; with timestamps.csv it is taken from
    there; both bring triangulation to a few millimetres from ~9 cm unsynchronised."""
    from detectors.stage import detect_clip
    from pipeline.estimate import estimate_clip
    from renderers.render import render_clip

    clip = tmp_path / "clip"
    render_clip(load_scenario("sync_offset").with_overrides(frames=90), clip, fmt="png", workers=1)
    detect_clip(clip)
    stamped = estimate_clip(clip, RunSettings(methods=["triangulation", "ekf"]), out_dir=tmp_path / "a", in_dir=clip / "out")
    (clip / "timestamps.csv").rename(tmp_path / "timestamps.csv")
    found = estimate_clip(clip, RunSettings(methods=["triangulation", "ekf"]), out_dir=tmp_path / "b", in_dir=clip / "out")
    off = estimate_clip(clip, RunSettings(methods=["triangulation"], time_offset="off"),
                        out_dir=tmp_path / "c", in_dir=clip / "out")
    assert stamped.metrics["sync"]["source"] == "timestamps"
    sync = found.metrics["sync"]
    assert sync["source"] == "detections" and sync["applied"]
    assert abs(sync["offset_s"] * 30 - 0.5) <= 0.05, sync
    tri = {k: r.metrics["methods"]["triangulation"]["rmse"] for k, r in (("stamped", stamped), ("found", found),
                                                                         ("off", off))}
    assert tri["off"] > 0.05 and tri["stamped"] < 0.01 and tri["found"] < 0.01, tri
    check = next(c for c in found.metrics["checks"] if c["name"] == "sync")
    assert not check["ok"] and "applied" in check["message"]
    shutil.rmtree(tmp_path / "a")
    assert json.loads((tmp_path / "b" / "metrics.json").read_text())["sync"]["applied"] is True


def _rendered_without_stamps(tmp_path, offset_s: float, frames: int, still: bool = False):
    """The sync_offset scenario with the right camera ``offset_s`` late (markers standing still when
    ``still``), rendered, detected, its timestamps.csv removed: the offset must come from the images."""
    from detectors.stage import detect_clip
    from renderers.render import render_clip

    spec = load_scenario("sync_offset").model_dump()
    spec["frames"], spec["rig"]["sync_offset_s"] = frames, offset_s
    if still:
        spec["objects"] = [{**o, "motion": {"type": "constant_velocity", "start": start, "velocity": [0.0, 0.0, 0.0]}}
                           for o, start in zip(spec["objects"], ([-0.3, 0.1, 1.6], [0.1, -0.3, 2.2]), strict=True)]
    clip = tmp_path / "clip"
    render_clip(parse_scenario(spec), clip, fmt="png", workers=1)
    detect_clip(clip)
    (clip / "timestamps.csv").unlink()
    return clip


@pytest.mark.slow
def test_a_rendered_offset_of_seconds_is_found_from_the_images(tmp_path):
    """#39 (sync): a 1.5 s (45-frame) offset lay outside the ±10-frame search. Rendered (right camera
    1.5 s late, 200 frames, no timestamps.csv): found from the detections within 0.05 frame and applied.
    Unit tests of the coarse search use synthetic tracks; this one goes through render, detect, estimate."""
    from pipeline.estimate import estimate_clip

    clip = _rendered_without_stamps(tmp_path, 1.5, 200)
    sync = estimate_clip(clip, RunSettings(methods=["triangulation"]), out_dir=tmp_path / "est",
                         in_dir=clip / "out").metrics["sync"]
    assert sync["source"] == "detections" and sync["applied"], sync
    assert abs(sync["offset_s"] * 30 - 45.0) <= 0.05, sync


@pytest.mark.slow
def test_a_rendered_offset_is_found_with_a_quarter_of_the_detections_missed(tmp_path, monkeypatch):
    """The sync_offset scenario (right camera half a frame late, 150 frames), rendered and detected,
    no timestamps.csv, and a quarter of each camera's detections dropped from detections.csv at random
    (a detector that misses): `estimate` finds the offset within 0.1 frame and applies it. The search
    before its narrowing found nothing here ("too few frames"), which the second half checks."""
    import pipeline.core.sync as sync_module
    from pipeline.estimate import estimate_clip

    clip = _rendered_without_stamps(tmp_path, 1 / 60, 150)
    path = clip / "out" / "detections.csv"
    lines = path.read_text().splitlines()
    keep = np.random.default_rng(5).random(len(lines) - 1) >= 0.25
    path.write_text("\n".join([lines[0], *(ln for ln, k in zip(lines[1:], keep, strict=True) if k)]) + "\n")
    sync = estimate_clip(clip, RunSettings(methods=["triangulation"]), out_dir=tmp_path / "est",
                         in_dir=clip / "out").metrics["sync"]
    assert sync["source"] == "detections" and sync["applied"], sync
    assert abs(sync["offset_s"] * 30 - 0.5) <= 0.1, sync
    monkeypatch.setattr(sync_module, "NARROW_KEEPS", 0.0)
    before = estimate_clip(clip, RunSettings(methods=["triangulation"]), out_dir=tmp_path / "before",
                           in_dir=clip / "out").metrics["sync"]
    assert not before["applied"] and before["ci_s"] is None, before


@pytest.mark.slow
def test_rendered_still_pairs_get_no_offset(tmp_path):
    """#39 (sync): still image pairs had a spurious offset applied, which worsened them. Rendered
    markers that stand still (the right camera 0.5 frame "late", which nothing in the images shows):
    no offset applied, saying why, and triangulation equals the run with the offset turned off."""
    from pipeline.estimate import estimate_clip

    clip = _rendered_without_stamps(tmp_path, 1 / 60, 40, still=True)
    auto = estimate_clip(clip, RunSettings(methods=["triangulation"]), out_dir=tmp_path / "a", in_dir=clip / "out")
    estimate_clip(clip, RunSettings(methods=["triangulation"], time_offset="off"), out_dir=tmp_path / "b",
                  in_dir=clip / "out")
    sync = auto.metrics["sync"]
    assert not sync["applied"] and "barely move" in sync["note"], sync
    assert (tmp_path / "a" / "estimates" / "triangulation.csv").read_bytes() == \
        (tmp_path / "b" / "estimates" / "triangulation.csv").read_bytes()


# -- every rig layout ---------------------------------------------------------------------------

LAYOUTS = {"right": {"position": [0.3, 0, 0]}, "left": {"position": [-0.3, 0, 0]}, "above": {"position": [0, -0.3, 0]},
           "below": {"position": [0, 0.3, 0]}, "diagonal": {"position": [0.25, -0.2, 0.02], "rotation_deg": [0, -3, 4]}}


def layout_scene(name: str, layout: str, frames: int = 200):
    s = load_scenario(name).with_overrides(frames=frames)
    d = s.model_dump(mode="json")
    d["rig"]["right"] = LAYOUTS[layout]
    d["rig"]["toe_in_deg"] = 0.0
    s = parse_scenario(d)
    return s, simulate_truth(s), s.rig.build()


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_spsa_stereo_in_every_layout(layout):
    """Within 1.5× of the EKF's RMSE and below triangulation's, never diverging, whichever side
    the second camera is on (before: hundreds of metres with the second camera on the left)."""
    for name in ("receding", "sine"):
        s, tr, rig = layout_scene(name, layout)
        X = tr.positions[:, 0]
        r = {m: [] for m in ("triangulation", "ekf", "spsa_stereo")}
        for seed in range(4):
            Y = rig.project(X) + np.random.default_rng(seed).normal(0, 1.0, (len(X), 4))
            for m in r:
                t = create(m, rig, s.dt, {"pixel_sigma": 1.0}).run(Y)
                r[m].append(rmse(t, X))
                if m == "spsa_stereo":
                    assert np.all(np.isfinite(t.position[2:])) and np.nanmax(np.linalg.norm(t.position - X, axis=1)) < 1.0
        mean = {m: float(np.mean(v)) for m, v in r.items()}
        assert mean["spsa_stereo"] <= 1.5 * mean["ekf"], (name, layout, mean)
        assert mean["spsa_stereo"] < mean["triangulation"], (name, layout, mean)


@pytest.mark.parametrize("layout", ["right", "left", "above"])
def test_one_camera_step_sideways_moves_no_depth(layout):
    """A point at rest at 3 m steps 10 cm sideways on a frame only one camera sees: spsa_stereo's
    depth moves no more than the EKF's (it jumped to 5.3 m before)."""
    s, _, rig = layout_scene("receding", layout, 10)
    X = np.tile([0.0, 0.0, 3.0], (60, 1))
    X[40:] += [0.1, 0.0, 0.0]
    Y = rig.project(X) + np.random.default_rng(1).normal(0, 0.3, (60, 4))
    for cam in (0, 1):
        Yc = Y.copy()
        Yc[40, 2 * (1 - cam) : 2 * (1 - cam) + 2] = np.nan  # only camera `cam` sees the step's first frame
        jump = {}
        for m in ("ekf", "spsa_stereo"):
            t = create(m, rig, s.dt, {"pixel_sigma": 0.3}).run(Yc)
            depth = t.position[:, 2]
            jump[m] = abs(depth[40] - depth[39])
        assert jump["spsa_stereo"] <= max(jump["ekf"], 0.02), (layout, cam, jump)


@pytest.mark.parametrize(("which", "column"), [("target_clip", 3), ("target_clip_analytic", 3), ("target_clip_analytic", 1)])
def test_target_filters_gate_a_corrupted_frame(which, column, request, tmp_path):
    """Three frames of the four-point target with one camera's points 1 and 3 moved 40 px apart
    (``column``: the right camera's v, or the left's; a mis-detected plate: its foreshortening,
    hence α and z, is wrong by ~0.2 rad; kalman_bucy's own α uncertainty is ~0.05 rad, so its gate
    catches only errors this gross): with the gate on, kalman_bucy's and pnp_kf's α and z stay
    within 1.3× of their errors on the clean detections, and the frames are counted as gated; the
    same filters without the gate are thrown off further. The fused measurement fails the gate and
    the other camera's own view is used (measured, analytic render: kalman_bucy's α 1.00× its
    clean error, pnp_kf's 0.99×; coasting on the model instead, as before, gave kalman_bucy 1.50×;
    the left camera's corruption is held out: written after the fix, never tuned on)."""
    from detectors.stage import detect_clip
    from pipeline.estimate import estimate_clip

    target_clip = request.getfixturevalue(which)
    det = detect_clip(target_clip, RunSettings(detector="blob"), out_dir=tmp_path / "clean")
    obs = {k: v.copy() for k, v in det.observations.items()}
    dirty = {k: v.copy() for k, v in obs.items()}
    for k in (15, 22, 29):
        dirty["target_1"][k, column] -= 40.0
        dirty["target_3"][k, column] += 40.0
    gate_on = {m: {"gate": 0.9995, "pixel_sigma": 0.5} for m in ("kalman_bucy", "pnp_kf")}
    gate_off = {m: {"gate": 0.0, "pixel_sigma": 0.5} for m in ("kalman_bucy", "pnp_kf")}
    runs = {}
    for name, o, cfg in (("clean", obs, gate_on), ("gated", dirty, gate_on), ("ungated", dirty, gate_off)):
        res = estimate_clip(target_clip, RunSettings(methods=["kalman_bucy", "pnp_kf"], configs=cfg), out_dir=tmp_path / name,
                            detections=Detections(o, det.footage))
        runs[name] = res.metrics["methods"]
    for m in ("kalman_bucy", "pnp_kf"):
        for q in ("alpha_rmse_rad", "distance_rmse_m"):
            assert runs["gated"][m][q] <= 1.3 * runs["clean"][m][q], (m, q, runs["gated"][m][q],
                                                                      runs["clean"][m][q])
        assert runs["gated"][m]["gated"] >= 3 and runs["clean"][m]["gated"] == 0
        assert runs["ungated"][m]["alpha_rmse_rad"] > 1.3 * runs["clean"][m]["alpha_rmse_rad"], m


@pytest.mark.slow
def test_videos_that_dropped_frames_are_paired_by_time(tmp_path):
    """MP4 footage whose cameras dropped different frames (the videos have different lengths):
    with timestamps.csv every frame of both is kept and paired by time, so the estimates match the
    same clip rendered as numbered PNGs (where a dropped frame is a missing file) and the truth.
    Before, the clip was refused ("left has N frames, right has M")."""
    from detectors.stage import detect_clip
    from pipeline.estimate import estimate_clip
    from renderers.render import render_clip

    scen = load_scenario("drops_jitter").with_overrides(frames=60)
    rmse_of = {}
    for fmt in ("png", "mp4"):
        clip = tmp_path / fmt
        render_clip(scen, clip, fmt=fmt, workers=1)
        detect_clip(clip)
        res = estimate_clip(clip, RunSettings(methods=["triangulation", "ekf"]), in_dir=clip / "out")
        rmse_of[fmt] = {m: res.metrics["methods"][m]["rmse"] for m in ("triangulation", "ekf")}
        assert res.metrics["sync"]["source"] == "timestamps"
    import cv2

    lengths = [int(cv2.VideoCapture(str(tmp_path / "mp4" / f"{c}.mp4")).get(cv2.CAP_PROP_FRAME_COUNT)) for c in ("left", "right")]
    assert lengths[0] != lengths[1] and max(lengths) < 60, lengths  # both dropped frames, not the same number
    for m in ("triangulation", "ekf"):
        assert rmse_of["mp4"][m] < 0.01 and rmse_of["mp4"][m] < 2 * rmse_of["png"][m] + 0.002, rmse_of


def test_a_track_back_from_a_long_gap_restarts_at_once():
    """The sine trajectory with a 60-frame gap: the marker comes back 3 m from where the filter
    predicts. The EKF restarts at the first gated frame back (it used to wait restart_after frames,
    1.5–2.9 m off meanwhile) and is within 10 cm five frames after the return; step, run and
    run_batch agree; the smoother does not carry the restart across the gap (ekf_rts within 10 cm
    there too)."""
    s, tr, rig = scene("sine", "right", 300)
    X = tr.positions[:, 0]
    Y = rig.project(X) + np.random.default_rng(3).normal(0, 1.0, (len(X), 4))
    Y[120:180] = np.nan
    est = create("ekf", rig, s.dt, {"pixel_sigma": 1.0})
    t = est.run(Y)
    restarts = np.flatnonzero(np.nan_to_num(t.extra["restart"]) > 0)
    assert len(restarts) and 180 <= restarts[0] <= 182, restarts
    assert np.linalg.norm(t.position[185] - X[185]) < 0.1
    est.reset()
    np.testing.assert_allclose(est.finish([est.step(y) for y in Y], Y).position, t.position, atol=1e-9)
    np.testing.assert_allclose(est.run_batch(Y[None])[0], t.position, atol=1e-9)
    smooth = create("ekf_rts", rig, s.dt, {"pixel_sigma": 1.0}).run(Y)
    assert np.linalg.norm(smooth.position[185] - X[185]) < 0.1


@pytest.mark.slow
def test_a_one_camera_stretch_leaves_no_error_behind():
    """#38 item 4: one camera loses the marker for 60 frames. The depth drifts along the kept
    camera's ray and its uncertainty grows with it, so the returning camera passed the gate and an
    update linearised metres off did not bring the depth back: on the manoeuvring marker the EKF's
    and UKF's peak error after the return was 64–72× their clean RMSE (median of four seeds,
    held-out layouts left and below; up to 89×). A camera back from such a stretch now restarts
    the track from the returning pair when the prediction is outside the pair's own triangulation
    gate: over the 40 frames after the
    return, the peak error is within 1.5× of the same clip's clean run's peak (median over seeds)
    for every Kalman-family method, step, run and run_batch agreeing."""
    for name in ("maneuvering", "sine"):
        for layout in ("left", "below"):
            s, tr, rig = layout_scene(name, layout, 300)
            X = tr.positions[:, 0]
            for m in ("kf3d", "ekf", "ukf", "kf3d_rts", "ekf_rts"):
                gap, clean = [], []
                for seed in range(4):
                    Y = rig.project(X) + np.random.default_rng(seed).normal(0, 1.0, (len(X), 4))
                    Yg = Y.copy()
                    Yg[100:160, 2 * (seed % 2) : 2 * (seed % 2) + 2] = np.nan
                    est = create(m, rig, s.dt, {"pixel_sigma": 1.0})
                    t = est.run(Yg)
                    gap.append(np.max(np.linalg.norm(t.position[160:200] - X[160:200], axis=1)))
                    clean.append(np.max(np.linalg.norm(est.run(Y).position[160:200] - X[160:200], axis=1)))
                    if m == "ekf" and seed < 2:
                        est.reset()
                        stepped = est.finish([est.step(y) for y in Yg], Yg).position
                        np.testing.assert_allclose(stepped, t.position, atol=1e-9)
                        np.testing.assert_allclose(est.run_batch(Yg[None])[0], t.position, atol=1e-9)
                assert np.median(gap) <= 1.5 * np.median(clean), (name, layout, m, gap, clean)


@pytest.mark.parametrize("method", ["alphabeta", "alphabetagamma", "kf3d"])
def test_a_3d_filter_with_one_camera_updates_from_it(method):
    """#38 item 5: the 3-D-space filters triangulate, so a frame with one camera (the other gated
    or missing) gave them nothing to update from; now the kept camera's pixel updates them through
    the measurement model (kf3d: its 2 rows, linearised at the prediction; the α-βs: the point of
    its ray nearest the prediction), and such frames are updates. The estimate reprojects nearer
    that camera's detections than the same filter coasting through the frames (no camera at all),
    whose frames are predictions."""
    s, tr, rig = layout_scene("receding", "right", 80)
    X = tr.positions[:, 0]
    Y = rig.project(X) + np.random.default_rng(0).normal(0, 1.0, (len(X), 4))
    one, none = Y.copy(), Y.copy()
    one[50:53, 2:], none[50:53] = np.nan, np.nan
    t = create(method, rig, s.dt, {"pixel_sigma": 1.0}).run(one)
    coast = create(method, rig, s.dt, {"pixel_sigma": 1.0}).run(none)
    assert not t.predicted[45:60].any() and coast.predicted[50:53].all()
    miss = {name: np.linalg.norm(rig.project(tt.position[50:53])[:, :2] - Y[50:53, :2], axis=1).sum()
            for name, tt in (("updated", t), ("coasting", coast))}
    assert miss["updated"] < 0.8 * miss["coasting"], miss


@pytest.mark.slow
@pytest.mark.parametrize("rasteriser", ["pyrender", "analytic"])
def test_a_rendered_clip_a_second_and_a_half_late(rasteriser, tmp_path):
    """#39 (sync) and #38 item 2, rendered: the right camera 1.5 s (45 frames) late, no
    timestamps.csv. The offset is found from the detections to within 0.05 frame and applied; every
    filter then sees the right camera's detections re-timed to the left camera's instants (the
    EKF's own offset model, the right camera at p + v·δ, put it 2.5 m off at this offset)."""
    from detectors.stage import detect_clip
    from pipeline.core.settings import RunSettings
    from pipeline.estimate import estimate_clip
    from renderers.render import render_clip

    d = load_scenario("sync_offset").model_dump(mode="json")
    d["rig"]["sync_offset_s"], d["frames"] = 1.5, 200  # the search reaches a quarter of the clip: 50 frames
    d["render"]["rasteriser"] = rasteriser
    render_clip(parse_scenario(d), tmp_path / "clip", fmt="png", workers=1)
    (tmp_path / "clip" / "timestamps.csv").unlink()  # the offset must come from the detections
    detect_clip(tmp_path / "clip")
    res = estimate_clip(tmp_path / "clip", RunSettings(methods=("triangulation", "ekf", "ukf")))
    sync = res.metrics["sync"]
    assert sync["applied"] and sync["source"] == "detections" and abs(sync["offset_s"] * 30 - 45) < 0.05, sync
    from pipeline.core.clip import read_positions

    truth, _ = read_positions(tmp_path / "clip" / "truth.csv")
    both = slice(50, 200)  # the frames both cameras see once re-timed (the right camera's first 45 are earlier)
    rmse = {}
    for m in ("triangulation", "ekf", "ukf"):
        est, _ = read_positions(res.out_dir / "estimates" / f"{m}.csv")
        e = np.concatenate([np.linalg.norm(est[k][both] - truth[k][both], axis=1) for k in truth])
        rmse[m] = float(np.sqrt(np.nanmean(e**2)))
    assert rmse["ekf"] < rmse["triangulation"] and rmse["ukf"] < rmse["triangulation"] < 0.05, rmse


@pytest.mark.parametrize("method", ["alphabeta", "alphabetagamma"])
def test_a_depth_drift_along_the_kept_camera_s_ray_restarts_the_alpha_beta(method):
    """#38 (item 5): a look-alike merging with the marker for four frames pulls both cameras'
    detections 0.25 m deeper (both agree: no gate can tell); the 3-D α-β takes the false depth
    velocity, and its depth then drifts along one camera's ray, which cannot see it, while the
    other camera's right detections fall outside the gate: it drifted for the eight frames the
    gate allows (up to 0.48 m). Three frames with one camera gated although the pair is one point
    now restart it: from four frames after the merge's end it stays within 0.15 m (the α-β-γ's own
    settling after a restart reaches 0.10 m), in both layouts and every seed (receding path, 1 px
    noise, σ estimated from the detections as the pipeline does); before, 0.35–0.48 m four frames after."""
    for layout in ("right", "above"):
        s, tr, rig = scene("receding", layout, 80)
        X = tr.positions[:, 0]
        for seed in range(4):
            rng = np.random.default_rng(seed)
            Y = rig.project(X) + rng.normal(0, 1.0, (len(X), 4))
            pulled = X[40:44] + np.outer(np.linspace(0.3, 1.0, 4), [0.0, 0.0, 0.25])
            Y[40:44] = rig.project(pulled) + rng.normal(0, 1.0, (4, 4))
            sigma = estimate_pixel_sigma(rig, {"red": Y})  # as `stereotrack estimate` hands it in: not the truth's 1 px
            err = np.linalg.norm(create(method, rig, s.dt, {"pixel_sigma": sigma}).run(Y).position - X, axis=1)
            assert err[47:60].max() < 0.15, (layout, seed, np.round(err[44:60], 3))
