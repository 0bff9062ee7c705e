"""More than two cameras, end to end: a clip rendered from a Qualisys rig file, its truth against
OpenCV's projection in every camera, and the run a user makes on it."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
import yaml

from pipeline.app.run import process_clip
from pipeline.core.camera import Camera
from pipeline.core.clip import Clip, read_csv
from pipeline.core.rig import Rig, look_at
from pipeline.core.rigfiles import load_rig, save_rig
from pipeline.core.settings import RunSettings
from renderers.render import render_clip
from renderers.scenario import load_scenario

CENTRE_LAB = np.array([0.1, -0.2, 0.9])  # the working volume's centre in the lab (z up), m


def _lab_rig() -> Rig:
    """Four cameras of a real rig's magnitude (3–3.5 m from the volume, 1.9–2.4 m high, f ≈ 1000 px
    at 1280×720, k1 ≈ −0.2 with k3), in the lab frame a Qualisys calibration uses."""
    cams = []
    for k, a in enumerate(np.deg2rad([30, 125, 210, 300])):
        centre = np.array([3.0 * np.cos(a) + 0.1, 3.2 * np.sin(a), 1.9 + 0.15 * k])
        R, t = look_at(centre, CENTRE_LAB, up=(0.0, 0.0, 1.0))
        K = np.array([[1000.0 + 30 * k, 0.0, 639.5 + 3 * k], [0.0, 1000.0 + 30 * k, 359.5 - 2 * k], [0.0, 0.0, 1.0]])
        cams.append(Camera(K, R, t, np.array([-0.2 + 0.01 * k, 0.06, 2e-4, -1e-4, -0.01])))
    return Rig(tuple(cams), tuple(f"Miqus_{k + 1}" for k in range(4)), ((1280, 720),) * 4)


@pytest.fixture(scope="module")
def qualisys_clip(tmp_path_factory):
    """A 4-camera clip rendered from a .qca.txt: three markers around the volume's centre."""
    root = tmp_path_factory.mktemp("qualisys")
    lab = _lab_rig()
    save_rig(lab, root / "lab.qca.txt")
    c0 = lab.cameras[0]
    centre = c0.R @ CENTRE_LAB + c0.t  # scenarios are written in the first camera's frame
    objects = [{"name": name, "color": color, "radius": 0.03,
                "motion": {"type": "sinusoid", "center": (centre + offset).tolist(), "amplitude": [0.25, 0.15, 0.2],
                           "frequency_hz": [0.5, 0.4, 0.3], "phase": [k, 2 * k, 0.5 * k]}}
               for k, (name, color, offset) in enumerate([("red", [230, 30, 30], [0.0, 0.0, 0.0]),
                                                          ("blue", [40, 60, 230], [0.2, 0.1, 0.0]),
                                                          ("green", [30, 200, 40], [-0.2, 0.0, 0.1])])]
    scenario = {"frames": 24, "fps": 30, "seed": 2, "rig": {"calibration": "lab.qca.txt"},
                "render": {"noise_std": 2.0, "blur_sigma": 0.6, "background": "plain"}, "objects": objects}
    (root / "mocap.yaml").write_text(yaml.safe_dump(scenario))
    clip = root / "clip"
    render_clip(load_scenario(root / "mocap.yaml"), clip, fmt="mp4", workers=2)
    return root, clip


def test_truth_pixels_equal_opencv_in_every_camera(qualisys_clip):
    """Acceptance: truth.csv's pixels are cv2.projectPoints of its points through the Qualisys rig
    (lab frame, distortion with k3) in every camera, to 1e-6 px."""
    root, clip = qualisys_clip
    lab = load_rig(root / "lab.qca.txt")
    info = json.loads((clip / "clip.json").read_text())
    assert info["cameras"] == list(lab.names)
    assert sorted(p.name for p in clip.glob("*.mp4")) == [f"{n}.mp4" for n in lab.names]
    cols = [f"{c}_{n}" for n in lab.names for c in "uv"]
    truth = read_csv(clip / "truth.csv", ["x", "y", "z", *cols], numeric=["x", "y", "z", *cols])
    X0 = np.column_stack([truth["x"], truth["y"], truth["z"]])  # the first camera's frame
    c0 = lab.cameras[0]
    X_lab = (X0 - c0.t) @ c0.R  # back to the lab: X = Rᵀ (X₀ − t)
    for n, cam in zip(lab.names, lab.cameras, strict=True):
        ref = cv2.projectPoints(X_lab, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.D)[0].reshape(-1, 2)
        np.testing.assert_allclose(np.column_stack([truth[f"u_{n}"], truth[f"v_{n}"]]), ref, atol=1e-6)


@pytest.mark.slow
def test_a_four_camera_clip_runs_end_to_end(qualisys_clip):
    """`run` with its defaults: every camera detected, the methods that take N cameras run beside
    their predict-only baseline, each marker within a few millimetres of the truth."""
    _, clip = qualisys_clip
    res = process_clip(clip, settings=RunSettings(images=False))  # `run` with its defaults (no frames in the recording)
    assert Clip(clip).cameras == ("Miqus_1", "Miqus_2", "Miqus_3", "Miqus_4")
    det = read_csv(res.out_dir / "detections.csv", ["camera"])
    assert set(det["camera"]) == set(Clip(clip).cameras)
    methods = res.estimate.metrics["methods"]
    assert set(methods) == {"triangulation", "ekf", "ekf_rts", "kf3d", "kf3d_rts", "ukf", "predict_only"}
    for m, entry in methods.items():
        if m != "predict_only":  # the baseline drifts, as it should
            assert entry["rmse"] < 0.004, (m, entry["rmse"])
    assert methods["predict_only"]["rmse"] > 10 * methods["ekf"]["rmse"]
    per_camera = methods["ekf"]["reprojection_per_camera_px"]
    assert set(per_camera) == set(Clip(clip).cameras)
    est = res.estimate  # a camera that sees a wrong blob stands out (a marker hidden behind another: 2–4 px off)
    wrong = sum((np.linalg.norm((Y - est.rig.project(est.truth.positions[m])).reshape(len(Y), -1, 2), axis=2) > 2).sum(axis=0)
                for m, Y in est.aligned.items())
    assert max(per_camera, key=per_camera.get) == est.rig.names[int(np.argmax(wrong))], (per_camera, wrong)
    assert all(v < 0.5 for name, v in per_camera.items() if wrong[est.rig.names.index(name)] == 0), (per_camera, wrong)
    assert (res.out_dir / "run.rrd").is_file() and (res.out_dir / "report.html").is_file()
    from tests.pipeline.test_pipeline import read_recording

    cols, static, _ = read_recording(res.out_dir / "run.rrd")
    rig = res.estimate.rig
    for name, cam in zip(rig.names, rig.cameras, strict=True):  # every camera's pinhole and pose, logged once
        assert f"/world/{name}" in static
        K = np.array(cols[f"/world/{name}"]["Pinhole:image_from_camera"][0]).reshape(3, 3).T
        np.testing.assert_allclose(K, cam.K, rtol=1e-6)
        assert f"/world/{name}/detections" in cols


def test_the_ring_scenario_names_its_cameras():
    scen = load_scenario("ring")
    rig = scen.rig.build_any()
    assert scen.rig.camera_names() == ("cam0", "cam1", "cam2", "cam3")
    np.testing.assert_allclose(rig.cameras[0].R, np.eye(3), atol=1e-12)  # the world: the first camera's frame
    centre = np.array([0.0, 0.0, 2.15])
    assert np.all(rig.depths(centre) > 1.5)  # every camera sees the volume from 2 m
    for c in range(rig.n):
        assert rig.in_image(rig.cameras[c].project(centre), camera=c)


def test_a_batch_finds_n_camera_clips_beside_stereo_ones(qualisys_clip, tmp_path):
    import shutil

    from pipeline.app.batch import find_clips

    _, clip = qualisys_clip
    shutil.copytree(clip, tmp_path / "mocap", ignore=shutil.ignore_patterns("out"))
    (tmp_path / "pair").mkdir()
    for name in ("left.mp4", "right.mp4"):
        (tmp_path / "pair" / name).write_bytes(b"")
    assert find_clips(tmp_path) == [tmp_path / "mocap", tmp_path / "pair"]


def test_stereo_only_methods_are_refused_on_n_cameras_by_name(qualisys_clip):
    from pipeline.core.errors import StereotrackError

    _, clip = qualisys_clip
    with pytest.raises(StereotrackError, match="spsa_stereo takes a stereo pair; with 4 cameras use one of ekf"):
        process_clip(clip, clip / "out_spsa", settings=RunSettings(methods=("spsa_stereo",), images=False,
                                                                  recording=False, figures=False))


@pytest.mark.slow
@pytest.mark.parametrize("n", [3, 4])
def test_calibrate_recovers_a_rendered_ring(tmp_path, n):
    """Acceptance: `stereotrack calibrate` on a rendered board set of a ring of 3 and 4 cameras —
    20 views around the volume (each seen by the cameras it faces) and 20 close to each camera —
    recovers every focal length within 0.2 % and every camera centre within 0.5 % of the rig's
    size; the report names each camera's leave-one-camera-out error."""
    from typer.testing import CliRunner

    from pipeline.app.cli import app
    from pipeline.core.board import Board
    from pipeline.core.rig import ring_rig
    from renderers.board import render_board_views

    truth = ring_rig(n).in_frame_of(0)
    render_board_views(truth, Board("chessboard", 9, 6, 0.06), tmp_path / "boards", views=20, spread=0.4, seed=n,
                       close=20)
    res = CliRunner().invoke(app, ["calibrate", str(tmp_path / "boards"), "--board", "chessboard:9x6", "--square", "6cm",
                                   "-o", str(tmp_path / "rig.json")])
    assert res.exit_code == 0, res.output
    rig = load_rig(tmp_path / "rig.json")
    assert rig.names == truth.names
    for est, cam in zip(rig.cameras, truth.cameras, strict=True):
        np.testing.assert_allclose(np.diag(est.K)[:2], np.diag(cam.K)[:2], rtol=0.002)
        assert np.linalg.norm(est.center - cam.center) < 0.005 * truth.baseline
    report = (tmp_path / "rig_report.md").read_text()
    assert "leave-one-camera-out" in report and all(f"| {name} |" in report for name in truth.names)
    again = CliRunner().invoke(app, ["calibrate", str(tmp_path / "boards"), "--board", "chessboard:9x6", "--square",
                                     "6cm", "-o", str(tmp_path / "rig.json")])
    assert again.exit_code != 0 and load_rig(tmp_path / "rig.json").names == truth.names  # never replaced


def test_leave_one_camera_out_shows_a_wrong_pose():
    """The report's leave-one-camera-out error: ~0 for exact poses, and the moved camera's
    grows most when its pose is 1 cm off (the others place the board where it is)."""
    from pipeline.calibrate.rig import _leave_one_out
    from pipeline.core.rig import ring_rig

    rig = ring_rig(4).in_frame_of(0)
    grid = np.mgrid[0:9, 0:6].T.reshape(-1, 2) * 0.06
    obj = np.column_stack([grid, np.zeros(len(grid))])
    found = [[], [], [], []]
    for k in range(6):
        a = 2 * np.pi * k / 6  # the board turned to face the cameras in turn
        R = cv2.Rodrigues(np.array([0.0, a, 0.0]))[0]
        X = (obj - obj.mean(axis=0)) @ R.T + [0.0, 0.0, 2.15]
        for c, cam in enumerate(rig.cameras):
            seen = (R[:, 2] @ (cam.center - [0.0, 0.0, 2.15])) < 0
            found[c].append(cam.project(X).astype(np.float32) if seen else None)
    exact = _leave_one_out(rig, found, obj.astype(np.float32))
    assert max(exact.values()) < 1e-3
    moved = Camera(rig.cameras[2].K, rig.cameras[2].R, rig.cameras[2].t + np.array([0.01, 0.0, 0.0]))
    wrong = _leave_one_out(Rig((*rig.cameras[:2], moved, *rig.cameras[3:]), rig.names, rig.sizes), found,
                           obj.astype(np.float32))
    assert wrong["cam2"] > 1.0 and wrong["cam2"] == max(wrong.values())


@pytest.mark.slow
def test_cameras_out_of_sync_are_aligned_by_their_timestamps(tmp_path):
    """A ring whose cameras are 12, −8 and 20 ms off the first, rendered: the run aligns every
    camera by timestamps.csv (or, without it, by the offsets it finds) and tracks as if in sync;
    with the offsets ignored (--time-offset off) it does not."""
    from pipeline.estimate import estimate_clip
    from renderers.scenario import parse_scenario

    ring = load_scenario("ring")
    views = [v.model_dump() for v in ring.rig.views]
    for v, off in zip(views, (0.0, 0.012, -0.008, 0.02), strict=True):
        v["time_offset_s"] = off
    data = ring.model_dump(mode="json")
    data["rig"] = {**{k: v for k, v in data["rig"].items() if k != "ring"}, "views": views}
    data.update(frames=90, objects=data["objects"][:2])
    clip = tmp_path / "clip"
    render_clip(parse_scenario(data), clip, fmt="mp4", workers=2)
    fast = RunSettings(methods=("triangulation", "ekf"), images=False, recording=False, figures=False)
    res = process_clip(clip, settings=fast)
    cams = res.estimate.metrics["sync_cameras"]
    assert [round(cams[n]["offset_s"], 4) for n in ("cam1", "cam2", "cam3")] == [0.012, -0.008, 0.02]
    off = estimate_clip(clip, fast.model_copy(update={"time_offset": "off"}), tmp_path / "off", in_dir=res.out_dir)
    (clip / "timestamps.csv").rename(tmp_path / "timestamps.csv")
    found = estimate_clip(clip, fast, tmp_path / "found", in_dir=res.out_dir)
    for m in ("triangulation", "ekf"):
        synced = res.estimate.metrics["methods"][m]["rmse"]
        assert synced < 0.002 and off.metrics["methods"][m]["rmse"] > 5 * synced
        assert found.metrics["methods"][m]["rmse"] < 2 * synced


def _filtered_with_and_without_the_check(clip, methods=("ekf", "ukf", "kf3d")):
    """(pooled 3-D RMSE of each method as `run` gives it — σ estimated, the joint check on —, the same
    with the check off, the estimate result) on a rendered clip's detections."""
    from pipeline.estimators import create

    res = process_clip(clip, settings=RunSettings(images=False, recording=False, figures=False,
                                                 methods=("triangulation", *methods)))
    est, sigma = res.estimate, res.estimate.metrics["pixel_sigma_estimate"]
    with_check, without = {}, {}
    for m in methods:
        sq_on, sq_off = [], []
        for marker, Y in est.aligned.items():
            X = est.truth.positions[marker]
            on = create(m, est.rig, est.dt, {"pixel_sigma": sigma})
            t = on.run(Y)
            np.testing.assert_allclose(on.run_batch(np.stack([Y, Y]))[1], t.position, atol=1e-9)
            off = create(m, est.rig, est.dt, {"pixel_sigma": sigma})
            off.joint_check = False
            sq_on.append(np.linalg.norm(t.position - X, axis=1) ** 2)
            sq_off.append(np.linalg.norm(off.run(Y).position - X, axis=1) ** 2)
        with_check[m], without[m] = (float(np.sqrt(np.nanmean(np.concatenate(sq)))) for sq in (sq_on, sq_off))
        assert abs(with_check[m] - est.metrics["methods"][m]["rmse"]) < 1e-5 * with_check[m]  # what `run` reports
    return with_check, without, est


@pytest.mark.slow
def test_the_joint_check_drops_a_camera_that_sees_a_wrong_blob(qualisys_clip):
    """#38, measured on this clip (its 9 detections 2–4 px off are markers hidden from a camera
    behind another): with three cameras or more a failed joint check drops the camera the others
    agree without (:meth:`~pipeline.estimators.gating.ViewCheck.odd_one`), not the one of largest
    own NIS. The EKF, UKF and kf3d with the check: at most half their RMSE without it (0.35 against
    1.51 mm, kf3d 0.36 against 1.63)."""
    _, clip = qualisys_clip
    with_check, without, _ = _filtered_with_and_without_the_check(clip)
    for m in with_check:
        assert with_check[m] <= 0.5 * without[m], (m, with_check[m], without[m])


def _held_out_ring(cameras: int, radius: float, height: float, fps: int, seed: int):
    """The ring scenario on another ring, its sinusoids 1.3× faster and 0.9 rad later, its straight
    mover 1.5× faster (90 frames)."""
    from renderers.scenario import parse_scenario

    data = load_scenario("ring").model_dump(mode="json")
    data["rig"]["ring"] = {"cameras": cameras, "radius": radius, "height": height}
    data["rig"].pop("views")  # made from the ring
    for obj in data["objects"]:
        motion = obj["motion"]
        if motion["type"] == "sinusoid":
            motion["frequency_hz"] = [1.3 * f for f in motion["frequency_hz"]]
            motion["phase"] = [p + 0.9 for p in (motion.get("phase") or [0.0] * 3)]
        else:
            motion["velocity"] = [1.5 * v for v in motion["velocity"]]
    data.update(frames=90, fps=fps, seed=seed)
    return parse_scenario(data)


@pytest.mark.slow
@pytest.mark.parametrize(("cameras", "radius", "height", "fps", "seed"), [(5, 2.2, -1.0, 60, 8), (3, 2.2, 0.4, 30, 9)],
                         ids=["ring5_60fps", "ring3_below"])
def test_the_joint_check_helps_on_rings_it_was_not_chosen_on(cameras, radius, height, fps, seed, tmp_path):
    """Held out: the rule for three cameras or more was chosen on the ring scenario's markers on
    eight rings (3–6 cameras, two with timestamps) and the Qualisys clip (better than no check on
    all but one, a ring of three, 6 % worse); these scenes were written before they were measured:
    the markers' motions changed, a ring of five at 60 fps and a ring of three below the volume.
    With the check the EKF, UKF and kf3d are at most 0.85× their RMSE without it (measured EKF
    0.44 against 0.66 mm and 0.51 against 1.11)."""
    clip = tmp_path / "clip"
    render_clip(_held_out_ring(cameras, radius, height, fps, seed), clip, fmt="mp4", workers=2)
    with_check, without, est = _filtered_with_and_without_the_check(clip)
    assert est.rig.n == cameras
    for m in with_check:
        assert with_check[m] <= 0.85 * without[m], (m, with_check[m], without[m])
