"""A user's own rig: real clips (two videos + a calibration, no scenario, no truth) through every
command, calibration units, the checks that catch wrong inputs, and bad inputs as one-line errors."""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from detectors.blob import BlobDetector, MarkerColor
from detectors.stage import detect_clip
from pipeline.core.calibration import load_calibration, save_calibration
from pipeline.core.camera import Camera, StereoRig, triangulate
from pipeline.core.detections import load_detections
from pipeline.core.errors import ClipError
from pipeline.core.frames import StereoFrameSource
from pipeline.core.io import read_csv
from pipeline.core.settings import RunSettings
from pipeline.estimate import estimate_clip
from pipeline.present.report import write_report
from tests.conftest import BALL
from tests.helpers import RED, SAMPLE, assert_one_line_error, cli, failed_checks, real_copy, snapshot

# ---------------------------------------------------------------------------------------------
# Real clips through run and batch
# ---------------------------------------------------------------------------------------------


def test_real_clip_through_run_with_markers_file_and_window(tmp_path, monkeypatch, capsys):
    # --markers
    clip = real_copy(tmp_path / "rig")
    rc, out, err = cli(monkeypatch, capsys, "run", clip, "--markers", RED, "--methods", "triangulation,ekf")
    assert rc == 0, err
    assert (clip / "out" / "report.md").is_file() and (clip / "out" / "run.rrd").stat().st_size > 10_000
    metrics = json.loads((clip / "out" / "metrics.json").read_text())
    assert metrics["has_truth"] is False and set(metrics["methods"]) == {"triangulation", "ekf"}
    assert all(c["ok"] for c in metrics["checks"]), metrics["checks"]
    # markers.yaml in the clip folder, and a window-learned marker on the red ball at frame 0
    clip2 = real_copy(tmp_path / "rig2")
    (clip2 / "markers.yaml").write_text("markers:\n  - red@95,130,16,16\n")
    rc, out, err = cli(monkeypatch, capsys, "run", clip2, "--methods", "triangulation")
    assert rc == 0, err
    assert "learned marker 'red'" in out
    learned = json.loads((clip2 / "out" / "detect.json").read_text())["learned"]["red"]
    lo, hi = (int(v) for v in learned.split(":")[1].split("-"))
    assert lo > 150 and hi < 15, learned  # a red range, wrapping through 0
    # the learned marker finds the ball in both cameras as the scenario's colour does
    a = load_detections(clip / "out" / "detections.csv")["red"]
    b = load_detections(clip2 / "out" / "detections.csv")["red"]
    both = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    assert both.sum() >= 35
    assert np.median(np.abs(a[both] - b[both])) < 0.3


@pytest.mark.slow
def test_real_clips_through_batch_with_root_markers(tmp_path, monkeypatch, capsys):
    root = tmp_path / "clips"
    real_copy(root / "a")
    real_copy(root / "b")
    (root / "markers.yaml").write_text(f"- {RED}\n")
    (root / "b" / "markers.yaml").write_text("- blue=#2840e6\n")  # a clip's own list wins
    rc, _out, err = cli(monkeypatch, capsys, "batch", root, "-o", tmp_path / "out", "--workers", "1",
                       "--methods", "triangulation")
    assert rc == 0, err
    from rerun.chunk import RrdReader

    for name, marker in (("a", "red"), ("b", "blue")):
        res = tmp_path / "out" / name
        assert (res / "report.md").is_file() and (res / "run.rrd").is_file()
        images = sum(c.num_rows for c in RrdReader(res / "run.rrd").stream() if c.entity_path == "/world/left/image")
        assert images == 40  # batch recordings hold the frames unless --no-images
        assert set(read_csv(res / "detections.csv")["marker"]) == {marker}


@pytest.mark.skipif(not BALL.is_file(), reason=f"real footage not present at {BALL}")
def test_window_learned_marker_on_real_footage(tmp_path, ball_reference):
    """ball2.mp4: the range learned from a window on the ball (frame 100) tracks it within 3 px
    (median) of a strict-HSV reference."""
    ref = ball_reference
    res = detect_clip(BALL, RunSettings(detector="blob", markers=["ball@465,95,36,36@100"]), out_dir=tmp_path)
    assert res.learned["ball"].startswith("ball:")
    det = load_detections(tmp_path / "detections.csv", 1004)["ball"]
    err = [np.hypot(det[k, 0] - u, det[k, 1] - v) for k, (u, v) in ref.items() if np.isfinite(det[k, 0])]
    assert len(ref) > 200 and len(err) > 0.9 * len(ref)
    assert np.median(err) <= 3.0, np.median(err)


def test_marker_names_stay_strings(tmp_path):
    clip = real_copy(tmp_path / "rig")
    detect_clip(clip, RunSettings(detector="blob", markers=["0:170-10:99:80"]))
    res = estimate_clip(clip, RunSettings(methods=["triangulation"]))
    assert list(res.tracks["triangulation"]) == ["0"]
    assert set(read_csv(clip / "out" / "estimates" / "triangulation.csv")["marker"]) == {"0"}


# ---------------------------------------------------------------------------------------------
# Units
# ---------------------------------------------------------------------------------------------


def test_triangulation_is_unit_covariant():
    rig = StereoRig.from_parameters(640, 480, 500.0, (331.2, 236.7), baseline=0.3, toe_in_deg=4.0)
    mm = StereoRig(rig.left, Camera(rig.right.K, rig.right.R, rig.right.t * 1000.0, rig.right.D), rig.image_size)
    rng = np.random.default_rng(1)
    X = rng.uniform([-1, -0.5, 1.0], [1, 0.5, 6.0], size=(500, 3))
    Y = rig.project(X) + rng.normal(0, 2.0, size=(500, 4))  # noisy: the solution is a compromise
    Xm, Xmm = triangulate(rig, Y), triangulate(mm, Y)
    np.testing.assert_allclose(Xmm, 1000.0 * Xm, rtol=1e-9)
    # noise-free points come back exactly in either unit
    np.testing.assert_allclose(triangulate(mm, rig.project(X)), 1000.0 * X, rtol=1e-9)


def test_calibration_in_millimetres(tmp_path):
    metre = real_copy(tmp_path / "m", with_truth=True)
    detect_clip(metre, RunSettings(detector="blob", markers=[RED, "blue=#2840e6"]))
    res_m = estimate_clip(metre)
    rig = load_calibration(metre)
    mm = tmp_path / "mm"
    shutil.copytree(metre, mm)
    save_calibration(rig, mm / "calib.yaml", units="mm")
    assert "units: mm" in (mm / "calib.yaml").read_text()
    np.testing.assert_allclose(load_calibration(mm).T, rig.T, rtol=1e-12)
    res_mm = estimate_clip(mm)
    for method, per in res_m.tracks.items():
        for marker, tr in per.items():
            np.testing.assert_allclose(res_mm.tracks[method][marker].position, tr.position, rtol=1e-9, atol=1e-12,
                                       err_msg=method)
    # the same file without its unit: a warning naming the likely unit, or --calib-units mm
    text = (mm / "calib.yaml").read_text().replace("units: mm\n", "")
    (mm / "calib.yaml").write_text(text)
    with pytest.warns(UserWarning, match=r"baseline is 300 .* millimetres \(0.3 m\).*--calib-units mm"):
        load_calibration(mm)
    np.testing.assert_allclose(load_calibration(mm, "mm").T, rig.T, rtol=1e-12)


# ---------------------------------------------------------------------------------------------
# Checks that catch wrong inputs
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_checks_fire_on_bad_clips_and_stay_silent_on_clean(tmp_path, png_clip):
    clean = real_copy(tmp_path / "clean", with_truth=True)
    detect_clip(clean, RunSettings(detector="blob", markers=[RED]))
    estimate_clip(clean, RunSettings(methods=["triangulation"]))
    assert failed_checks(clean / "out") == {}
    assert "All input checks passed." in write_report(clean).read_text()

    # left/right videos swapped against the calibration
    swapped = real_copy(tmp_path / "swapped")
    os.replace(swapped / "left.mp4", swapped / "tmp.mp4")
    os.replace(swapped / "right.mp4", swapped / "left.mp4")
    os.replace(swapped / "tmp.mp4", swapped / "right.mp4")
    detect_clip(swapped, RunSettings(detector="blob", markers=[RED]))
    with pytest.warns(UserWarning, match="look swapped"):
        estimate_clip(swapped, RunSettings(methods=["triangulation"]))
    assert "left_right" in failed_checks(swapped / "out")
    report = write_report(swapped).read_text()
    assert report.index("## Checks") < report.index("## Metrics") and "look swapped" in report

    # a calibration made at twice the resolution (same aspect): K scaled, with a warning, results intact
    big = real_copy(tmp_path / "big", with_truth=True)
    save_calibration(load_calibration(SAMPLE).scaled_to((640, 480)), big / "calib.yaml")
    with pytest.warns(UserWarning, match="640×480 images but the frames are 320×240"):
        detect_clip(big, RunSettings(detector="blob", markers=[RED]))
    with pytest.warns(UserWarning, match="640×480 images but the frames are 320×240"):  # estimate says it too
        res = estimate_clip(big, RunSettings(methods=["triangulation"]))
    assert "image_size" in failed_checks(big / "out")
    assert res.metrics["methods"]["triangulation"]["rmse"] < 0.02

    # a colour range that matches the background
    wall = real_copy(tmp_path / "wall")
    with pytest.warns(UserWarning, match="matches the background"):
        detect_clip(wall, RunSettings(detector="blob", markers=["wall:0-179:0:0"]))

    # a distractor of the marker's colour: a range wide enough to take the magenta cube for red
    with pytest.warns(UserWarning, match="two or more blobs of its colour"):
        res = detect_clip(png_clip, RunSettings(detector="blob", markers=["red:140-10:80:60"]), out_dir=tmp_path / "distractor")
    assert any(c.name == "colour_range" and not c.ok for c in res.checks)

    # detections that do not correspond between the cameras (right camera shifted 25 px down)
    epi = real_copy(tmp_path / "epi")
    detect_clip(epi, RunSettings(detector="blob", markers=[RED]))
    path = epi / "out" / "detections.csv"
    lines = path.read_text().splitlines()
    fixed = [lines[0]] + [",".join([*f[:4], str(float(f[4]) + 25), *f[5:]]) if f[1] == "right" else line
                          for line in lines[1:] for f in [line.split(",")]]
    path.write_text("\n".join(fixed) + "\n")
    with pytest.warns(UserWarning, match="median epipolar distance"):
        estimate_clip(epi, RunSettings(methods=["triangulation"]))


@pytest.mark.filterwarnings("ignore:.*frame number")  # the later error cases still have the gap
def test_png_gap_is_a_missing_frame_not_a_shift(tmp_path, png_clip):
    clip = tmp_path / "gap"
    shutil.copytree(png_clip, clip, ignore=shutil.ignore_patterns("out"))
    (clip / "left" / "000010.png").unlink()
    with pytest.warns(UserWarning, match=r"1 frame number\(s\) missing \(10\)"):
        res = detect_clip(clip, out_dir=tmp_path / "o")
    left = [r for r in res.rows if r[1] == "left"]
    assert {r[0] for r in left} == set(range(24)) - {10}
    assert res.summaries[0].err_max is not None and res.summaries[0].err_max < 2.0  # later frames not shifted
    # a duplicate frame number and a frame of another size are errors naming the file
    shutil.copy(clip / "left" / "000011.png", clip / "left" / "frame_11.png")
    with pytest.raises(ClipError, match=r"000011\.png and frame_11\.png both claim frame 11"):
        detect_clip(clip, out_dir=tmp_path / "o2")
    (clip / "left" / "frame_11.png").unlink()
    cv2.imwrite(str(clip / "left" / "000005.png"), np.zeros((120, 160, 3), np.uint8))
    with pytest.raises(ClipError, match=r"000005.png is 160×120, the folder's frames are 320×240"):
        detect_clip(clip, out_dir=tmp_path / "o3")
    assert not (tmp_path / "o3" / "detections.csv").exists()


def test_truth_shorter_than_clip_is_a_warning(tmp_path):
    clip = real_copy(tmp_path / "short", with_truth=True)
    detect_clip(clip, RunSettings(detector="blob", markers=[RED]))
    lines = (clip / "truth.csv").read_text().splitlines()
    (clip / "truth.csv").write_text("\n".join(lines[: 1 + 2 * 10]) + "\n")
    with pytest.warns(UserWarning, match="truth covers 10 of the clip's 40 frames"):
        res = estimate_clip(clip, RunSettings(methods=["triangulation"]))
    assert res.metrics["methods"]["triangulation"]["frames"] == 10


def test_blob_window_never_loses_the_marker():
    """A small blob of the marker's colour inside the search window while the marker itself has
    moved outside it: the windowed candidate is far smaller than the track's recent ones, so the
    whole frame is searched and the marker found."""
    det = BlobDetector([MarkerColor.parse("ball:50-70:80:60")])
    frame = np.full((480, 640, 3), 40, np.uint8)
    cv2.circle(frame, (400, 300), 30, (0, 200, 0), -1)
    window = {"ball": (60, 60, 80, 80)}
    cv2.circle(frame, (100, 100), 4, (0, 200, 0), -1)  # the small distractor, inside the window
    found = det.detect(frame, rois=window, expected_area={"ball": np.pi * 30**2})
    assert len(found) == 1 and abs(found[0].u - 400) < 0.5 and abs(found[0].v - 300) < 0.5
    # without the track's size the window is trusted (the old behaviour this guards against)
    assert abs(det.detect(frame, rois=window)[0].u - 100) < 0.5


# ---------------------------------------------------------------------------------------------
# Bad inputs: one line, exit 2, the file named, no traceback, nothing changed
# ---------------------------------------------------------------------------------------------


def _edit(path: Path, old: str, new: str) -> None:
    path.write_text(path.read_text().replace(old, new, 1))


def _det_row(clip: Path, row: str) -> None:
    with open(clip / "out" / "detections.csv", "a") as fh:
        fh.write(row + "\n")


def _png_clip(clip: Path) -> None:
    for cam in ("left", "right"):
        (clip / cam).mkdir()
        for fr in StereoFrameSource(clip / f"{cam}.mp4"):
            cv2.imwrite(str(clip / cam / f"{fr.index:06d}.png"), fr.left)
        (clip / f"{cam}.mp4").unlink()


def _calib_with(clip: Path, key: str, value: str) -> None:
    text = (clip / "calib.yaml").read_text()
    start = text.index(f"{key}: !!opencv-matrix")
    data = text.index("data: [", start) + len("data: [")
    end = text.index("]", data)
    (clip / "calib.yaml").write_text(text[:data] + value + text[end:])


BAD_INPUTS = {
    # name: (setup(clip), argv after the command's clip, command, expected text)
    "output under a file": (None, ["-o", "{clip}/left.mp4/out"], "detect", "left.mp4/out"),
    "output in /proc": (None, ["-o", "/proc/stereotrack-out"], "detect", "/proc/stereotrack-out"),
    "text in a numeric field": (lambda c: _det_row(c, "3,left,red,abc,12,50,1"), [], "estimate", "column 'u' is not a number"),
    "NaN observation": (lambda c: _det_row(c, "3,left,red,nan,12,50,1"), [], "estimate", "'u' is nan"),
    "detection past the clip": (lambda c: _det_row(c, "99999,left,red,10,12,50,1"), [], "estimate",
                                "frame 99999 is outside the clip's frames 0..39"),
    "unknown camera": (lambda c: _det_row(c, "3,middle,red,10,12,50,1"), [], "estimate", "unknown camera 'middle'"),
    "truth past the clip": (lambda c: _edit_truth(c), [], "estimate", "truth.csv: line 82: frame 40"),
    "negative focal length": (lambda c: _calib_with(c, "K1", "-300., 0., 162.5, 0., 300., 118., 0., 0., 1. "), [], "estimate",
                              "focal length fx=-300"),
    "NaN in R": (lambda c: _calib_with(c, "R", ".nan, 0., 0., 0., 1., 0., 0., 0., 1. "), [], "estimate", "'R' contains NaN"),
    "malformed calibration": (lambda c: (c / "calib.yaml").write_text("%YAML:1.0\nK1: [1, 2\n"), [], "detect", "calib.yaml"),
    "missing calibration": (lambda c: (c / "calib.yaml").unlink(), [], "estimate", "no calib.yaml"),
    "unknown units": (lambda c: _edit(c / "calib.yaml", "image_width", "units: furlong\nimage_width"), [], "estimate",
                      "field 'units' must be m, cm or mm"),
    "calibration for another aspect": (lambda c: _edit(c / "calib.yaml", "image_height: 240", "image_height: 180"), [],
                                       "detect", "320×180 images but the frames are 320×240"),
    "unreadable video": (lambda c: (c / "left.mp4").write_bytes(np.random.default_rng(0).bytes(4000)), [], "detect",
                         "left.mp4"),
    "unequal frame counts": (lambda c: (_png_clip(c), (c / "right" / "000039.png").unlink()), [], "detect",
                             "left has 40 frames, right has 39"),
    "PNG of another size": (lambda c: (_png_clip(c), cv2.imwrite(str(c / "left" / "000007.png"), np.zeros((10, 10, 3)))), [],
                            "detect", "000007.png is 10×10"),
    "bad markers.yaml": (lambda c: (c / "markers.yaml").write_text("markers: red\n"), [], "run", "markers.yaml"),
    "window outside the frame": (None, ["--markers", "red@300,200,50,50"], "detect", "outside the 320×240 frame"),
    "bad --calib-units": (None, ["--calib-units", "inch"], "estimate", "--calib-units names an unknown length unit 'inch'"),
    "no clips under a batch input": (lambda c: (c / "empty").mkdir(), [], "batch-empty", "no clip folders"),
    "unreachable Dask scheduler": (None, ["--scheduler", "tcp://127.0.0.1:9"], "batch", "cannot reach the Dask scheduler"),
}


def _edit_truth(clip: Path) -> None:
    shutil.copy(SAMPLE / "truth.csv", clip / "truth.csv")
    with open(clip / "truth.csv", "a") as fh:
        fh.write("40,1.3,red,0,0,2,0,0,0,1,1,1,1,1,1\n")


@pytest.mark.slow
@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_is_one_line(case, detected_clip, tmp_path, monkeypatch, capsys):
    setup, extra, command, expected = BAD_INPUTS[case]
    clip = tmp_path / "clip"
    shutil.copytree(detected_clip, clip)
    if setup is not None:
        setup(clip)
    before = snapshot(tmp_path)
    extra = [a.format(clip=clip) for a in extra]
    if command == "batch":
        monkeypatch.setenv("DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT", "2s")
        argv = ["batch", tmp_path, "-o", tmp_path / "batch-out", "--markers", RED, *extra]
    elif command == "batch-empty":
        argv = ["batch", clip / "empty", "-o", tmp_path / "batch-out"]
    else:
        argv = [command, clip, *(["--markers", RED] if command in ("detect",) and "--markers" not in extra else []), *extra]
    assert_one_line_error(*cli(monkeypatch, capsys, *argv), expected, case=case)
    after = snapshot(tmp_path)
    assert {k: v for k, v in after.items() if not k.startswith("batch-out")} == before, case


def test_track_jump_check():
    from pipeline.core.checks import jump_checks

    t = np.arange(60)
    smooth = np.column_stack([100 + 2 * t, 120 + t, 80 + 2 * t, 120 + t]).astype(float)
    assert jump_checks({"ball": smooth}, 320) == []
    jumpy = smooth.copy()
    jumpy[::7, :] += [150, 0, 150, 0]  # every 7th frame on another object of the same colour
    (check,) = jump_checks({"ball": jumpy}, 320)
    assert not check.ok and check.subject == "ball" and "jumps more than 80 px" in check.message
