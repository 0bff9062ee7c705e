"""Imperfect rigs, rendered with exact truth: rigs from calibration files and in any layout, lens
distortion, sync offset, rolling shutter, exposure blur, drops and jitter, calibration error,
occluders. Truth is checked against closed-form motion and OpenCV's own projection (independent of
stereotrack's motion code), and the rendered pixels against the truth through the blob detector."""

from __future__ import annotations

import hashlib
import math
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from detectors.stage import detect_clip
from pipeline.core.calibration import load_calibration
from pipeline.core.errors import ScenarioError
from pipeline.core.io import read_csv
from renderers.render import render_clip
from renderers.scenario import load_scenario, parse_scenario
from tests.conftest import REPO

FPS = 30.0
RED = {"type": "sinusoid", "center": [0.05, 0.0, 1.7], "amplitude": [0.4, 0.2, 0.25], "frequency_hz": 0.7,
       "phase": [0.3, 1.1, 0.0]}
BLUE = {"type": "constant_velocity", "start": [-0.45, 0.25, 1.4], "velocity": [0.9, -0.45, 0.6]}


def closed_form(motion: dict, t: np.ndarray) -> np.ndarray:
    """The marker's position at times ``t`` written out from the scenario (not stereotrack's code)."""
    if motion["type"] == "sinusoid":
        w = 2 * math.pi * motion["frequency_hz"]
        return np.array(motion["center"]) + np.array(motion["amplitude"]) * np.sin(np.outer(t, [w] * 3) + motion["phase"])
    return np.array(motion["start"]) + np.outer(t, motion["velocity"])


def scenario(rig: dict, render: dict | None = None, frames: int = 12, size=(640, 480), **extra) -> dict:
    return {"name": "imperfect", "frames": frames, "fps": FPS, "seed": 5,
            "rig": {"width": size[0], "height": size[1], "focal": 600.0 * size[0] / 640, "baseline": 0.3, **rig},
            "render": {"shading": "flat", "noise_std": 0.0, "blur_sigma": 0.0, **(render or {})},
            "objects": [{"name": "red", "color": [230, 30, 30], "radius": 0.04, "motion": RED},
                        {"name": "blue", "color": [40, 60, 230], "radius": 0.04, "motion": BLUE}], **extra}


DISTORTED = {"distortion": [-0.28, 0.09, 0.0007, -0.0005, 0.0], "distortion_right": [-0.24, 0.07, -0.0003, 0.0004, 0.0]}
TIMED = {"sync_offset_s": 0.0113, "line_delay_s": 0.00005, "jitter_s": 0.0008}
LAYOUT = {"right": {"position": [-0.28, 0.06, 0.02], "rotation_deg": [1.0, 3.0, -2.0]}}  # second camera on the left


@pytest.fixture(scope="module")
def imperfect_clip(tmp_path_factory) -> Path:
    """Lossless 640×480 frames of a distorted, left-handed, offset, rolling-shutter, jittered rig."""
    out = tmp_path_factory.mktemp("imperfect") / "clip"
    render_clip(parse_scenario(scenario({**DISTORTED, **TIMED, **LAYOUT})), out, fmt="png", workers=1)
    return out


def _rows(clip: Path) -> dict[str, dict[str, np.ndarray]]:
    cols = read_csv(clip / "truth.csv")
    return {m: {k: v[cols["marker"] == m] for k, v in cols.items()} for m in ("red", "blue")}


def test_truth_pixels_are_opencv_projections_at_each_cameras_time(imperfect_clip):
    rig = load_calibration(imperfect_clip)
    ts = read_csv(imperfect_clip / "timestamps.csv")
    for cam, c in (("left", 0), ("right", 1)):
        t_row0 = ts["t"][ts["camera"] == cam]
        nominal = np.arange(12) / FPS + (TIMED["sync_offset_s"] if c else 0.0)
        assert np.all(np.abs(t_row0 - nominal) < 5 * TIMED["jitter_s"]) and np.any(t_row0 != nominal)  # jittered
        K, D, R, T = rig.cameras[c].K, rig.cameras[c].D, rig.cameras[c].R, rig.cameras[c].t
        for marker, motion in (("red", RED), ("blue", BLUE)):
            rows = _rows(imperfect_clip)[marker]
            t_seen = rows[f"t_{cam}"]
            X = closed_form(motion, t_seen)
            uv, _ = cv2.projectPoints(X, cv2.Rodrigues(R)[0], T, K, D)
            uv = uv.reshape(-1, 2)
            np.testing.assert_allclose(np.column_stack([rows[f"u_{cam}"], rows[f"v_{cam}"]]), uv, atol=1e-6, rtol=0)
            # rolling shutter: seen when the row that images it is exposed
            np.testing.assert_allclose(t_seen, t_row0 + uv[:, 1] * TIMED["line_delay_s"], atol=1e-9, rtol=0)
            # without the lens: the pinhole projection of the same point
            pin = X @ (K @ np.hstack([R, T.reshape(3, 1)]))[:, :3].T + (K @ T)
            np.testing.assert_allclose(np.column_stack([rows[f"u_{cam}_pinhole"], rows[f"v_{cam}_pinhole"]]),
                                       pin[:, :2] / pin[:, 2:], atol=1e-6, rtol=0)
    # the 3-D truth is at the left camera's frame time
    for marker, motion in (("red", RED), ("blue", BLUE)):
        rows = _rows(imperfect_clip)[marker]
        np.testing.assert_allclose(np.column_stack([rows["x"], rows["y"], rows["z"]]), closed_form(motion, rows["t"]),
                                   atol=1e-12)


@pytest.mark.parametrize("rig", [{}, DISTORTED, {"sync_offset_s": 0.0113, "line_delay_s": 0.00005}, LAYOUT],
                         ids=["ideal", "distorted", "offset+rolling shutter", "left-handed"])
def test_blob_detections_match_truth_on_lossless_frames(rig, tmp_path):
    """The rendered pixels agree with the truth as well on an imperfect rig as on an ideal one."""
    clip = tmp_path / "clip"
    render_clip(parse_scenario(scenario(rig, frames=10)), clip, fmt="png", workers=1)
    res = detect_clip(clip, out_dir=tmp_path / "out")
    for s in res.summaries:
        assert s.misses == 0 and s.err_median is not None
        assert s.err_median <= 0.25, (rig, s)


@pytest.mark.slow
def test_exposure_blur_integrates_the_motion(tmp_path):
    """A 25 ms exposure smears a fast marker along its path (the blob grows), and its centroid is
    still the truth at mid-exposure; n sub-frame renders, not a Gaussian."""
    scen = parse_scenario(scenario({}, {"exposure_s": 0.025, "exposure_samples": 10}, frames=8))
    clip, sharp = tmp_path / "blur", tmp_path / "sharp"
    render_clip(scen, clip, fmt="png", workers=1)
    render_clip(parse_scenario(scenario({}, frames=8)), sharp, fmt="png", workers=1)
    a = detect_clip(clip, out_dir=tmp_path / "o1")
    b = detect_clip(sharp, out_dir=tmp_path / "o2")
    assert all(s.err_median <= 0.25 for s in a.summaries), a.summaries
    area = {r[2]: [] for r in a.rows}
    for rows, key in ((b.rows, 0), (a.rows, 1)):
        for r in rows:
            if r[2] == "blue":
                area[r[2]].append((key, r[5]))
    sharp_area = np.median([v for k, v in area["blue"] if k == 0])
    blur_area = np.median([v for k, v in area["blue"] if k == 1])
    assert blur_area > 1.1 * sharp_area, (sharp_area, blur_area)  # ~1 m/s at 1.5 m: ~10 px of smear over 25 ms


def test_rig_from_calibration_file(tmp_path):
    """rig.calibration: the clip is rendered by exactly that rig, at its size (T converted to metres)."""
    scen = load_scenario("rig_from_file").with_overrides(frames=3)
    clip = tmp_path / "clip"
    render_clip(scen, clip, fmt="png", workers=1)
    src = load_calibration(REPO / "data" / "scenarios" / "rigs" / "left_rig_mm.yaml")
    got = load_calibration(clip)
    for a, b in zip(src.cameras, got.cameras, strict=True):
        np.testing.assert_allclose(a.K, b.K, atol=1e-12)
        np.testing.assert_allclose(a.D, b.D, atol=1e-12)
    np.testing.assert_allclose(got.R, src.R, atol=1e-12)
    np.testing.assert_allclose(got.T, src.T, atol=1e-12)
    assert got.image_size == src.image_size == (640, 480)
    assert src.right.center[0] < -0.2  # the file's second camera is on the left
    assert cv2.imread(str(clip / "left" / "000000.png")).shape[:2] == (480, 640)


def test_calibration_error_is_what_the_user_gets(tmp_path):
    spec = {"focal": 0.01, "principal_point": 2.0, "baseline": 0.01, "rotation_deg": 0.2}
    clip = tmp_path / "clip"
    render_clip(parse_scenario(scenario({}, frames=3, calibration_error=spec)), clip, fmt="png", workers=1)
    user, true = load_calibration(clip / "calib.yaml"), load_calibration(clip / "calib_true.yaml")
    assert 0 < abs(user.baseline / true.baseline - 1) < 0.05
    assert 0 < abs(user.left.K[0, 0] / true.left.K[0, 0] - 1) < 0.05
    assert 0 < np.abs(user.left.K[:2, 2] - true.left.K[:2, 2]).max() < 10
    angle = np.degrees(np.arccos(np.clip((np.trace(user.R @ true.R.T) - 1) / 2, -1, 1)))
    assert 0 < angle < 1.0
    # truth pixels are the true rig's
    rows = _rows(clip)["blue"]
    np.testing.assert_allclose(true.left.project(closed_form(BLUE, rows["t"]))[:, 0], rows["u_left"], atol=1e-6)


def test_drops_leave_gaps_that_timestamps_name(tmp_path):
    clip = tmp_path / "clip"
    render_clip(parse_scenario(scenario({"drop_rate": [0.0, 0.3]}, frames=20, size=(320, 240))), clip, fmt="png",
                workers=1)
    ts = read_csv(clip / "timestamps.csv")
    right = sorted(int(f) for f in ts["frame"][ts["camera"] == "right"])
    files = sorted(int(p.stem) for p in (clip / "right").glob("*.png"))
    assert right == files and 10 < len(files) < 20 and files[0] == 0
    truth = read_csv(clip / "truth.csv")
    vis = {int(k) for k, v in zip(truth["frame"], truth["visible_right"], strict=True) if v}
    assert vis <= set(files)
    mp4 = tmp_path / "mp4"
    render_clip(parse_scenario(scenario({"drop_rate": [0.0, 0.3]}, frames=20, size=(320, 240))), mp4, fmt="mp4",
                workers=1)
    ts4 = read_csv(mp4 / "timestamps.csv")
    assert sorted(int(f) for f in ts4["frame"][ts4["camera"] == "right"]) == list(range(len(files)))  # video positions
    np.testing.assert_array_equal(ts4["t"], ts["t"])


def test_occluder_hides_markers_in_the_truth(tmp_path):
    """A bar that covers the blue marker in some frames: truth says hidden exactly where the image
    shows too little of it, and no detection is reported there as the marker."""
    bar = {"shape": "box", "color": [128, 128, 120], "extents": [0.12, 1.5, 0.03], "size": 1.5,
           "motion": {"type": "constant_velocity", "start": [-1.1, 0.0, 1.0], "velocity": [2.2, 0.0, 0.0]}}
    clip = tmp_path / "clip"
    render_clip(parse_scenario(scenario({}, frames=24, size=(320, 240), distractors=[bar])), clip, fmt="png", workers=1)
    truth = read_csv(clip / "truth.csv")
    hidden = (truth["visible_left"] == 0) | (truth["visible_right"] == 0)
    assert 0 < hidden.sum() < len(hidden) / 2
    res = detect_clip(clip, out_dir=tmp_path / "out")
    for s in res.summaries:
        assert s.err_median < 0.35 and s.false is not None and s.false <= 1, s


def test_same_scenario_same_frames_and_truth_bit_for_bit(tmp_path):
    data = scenario({**DISTORTED, **TIMED, **LAYOUT, "drop_rate": 0.1}, {"exposure_s": 0.01, "exposure_samples": 3,
                                                                           "noise_std": 2.0, "blur_sigma": 0.5},
                    frames=6, size=(320, 240), calibration_error={"focal": 0.01, "baseline": 0.01})
    digests = []
    for run in ("a", "b"):
        clip = tmp_path / run
        render_clip(parse_scenario(data), clip, fmt="png", workers=1)
        digests.append({str(p.relative_to(clip)): hashlib.sha256(p.read_bytes()).hexdigest()
                        for p in sorted(clip.rglob("*")) if p.is_file()})
    assert digests[0] == digests[1]
    assert {"calib.yaml", "calib_true.yaml", "timestamps.csv", "truth.csv"} <= set(digests[0])


@pytest.mark.slow
@pytest.mark.parametrize("layout", ["rig_left", "rig_above"])
def test_vertical_and_left_handed_rigs_through_run(layout, tmp_path):
    import json
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "run", layout, "--frames", "30", "-o", str(tmp_path / "c"),
                          "--methods", "triangulation,ekf,kf3d"], capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert res.returncode == 0, res.stderr
    metrics = json.loads((tmp_path / "c" / "out" / "metrics.json").read_text())
    assert all(c["ok"] for c in metrics["checks"]), metrics["checks"]
    for m in ("triangulation", "ekf", "kf3d"):
        assert metrics["methods"][m]["rmse"] < 0.03, (m, metrics["methods"][m]["rmse"])


BAD = {
    "negative exposure": ({"render": {"exposure_s": -0.01}}, "render.exposure_s"),
    "negative line delay": ({"rig": {"line_delay_s": -1e-5}}, "rig.line_delay_s"),
    "exposure longer than the frame": ({"render": {"exposure_s": 0.05}}, "longer than the frame period"),
    "drop rate of 1": ({"rig": {"drop_rate": 1.0}}, "rig.drop_rate"),
    "drop rate below 0": ({"rig": {"drop_rate": [0.0, -0.1]}}, "rig.drop_rate"),
    "calibration that does not load": ({"rig": {"calibration": "nope.yaml"}}, "rig.calibration"),
    "distortion of 6 coefficients": ({"rig": {"distortion": [0.1] * 6}}, "rig.distortion"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_imperfection_is_one_line_naming_file_and_field(case, tmp_path):
    import yaml

    change, field = BAD[case]
    data = scenario({})
    for key, val in change.items():
        data[key] = {**data[key], **val}
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(data))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    msg = str(err.value)
    assert str(path) in msg and field in msg and "\n" not in msg, msg


def test_builtin_imperfect_suite_loads_and_shows_its_markers():
    from renderers.motion import simulate_truth
    from renderers.truth import project_truth

    for name in ("rig_left", "rig_above", "rig_below", "rig_diagonal", "rig_from_file", "distortion", "sync_offset",
                 "rolling_shutter", "exposure_blur", "drops_jitter", "calibration_error", "occlusion", "lookalike",
                 "skin_wall", "realistic"):
        s = load_scenario(name)
        assert s.imperfections or s.distractors, name
        proj = project_truth(s.rig.build(), s, simulate_truth(s), distractors=False)
        assert proj.visible.mean(axis=0).min() > 0.8, name


def test_clip_json_records_the_imperfections(imperfect_clip):
    import json

    info = json.loads((imperfect_clip / "clip.json").read_text())["imperfections"]
    assert info["sync_offset_s"] == TIMED["sync_offset_s"] and info["line_delay_s"] == TIMED["line_delay_s"]
    assert info["distortion"]["D1"][0] == DISTORTED["distortion"][0] and info["layout"]["right_center_m"][0] < 0
    shutil.rmtree(imperfect_clip / "out", ignore_errors=True)
