"""Detectors on rendered clips (measured against truth), on real footage, and on bad input."""

from __future__ import annotations

import shutil

import cv2
import numpy as np
import pytest

from detectors.blob import BlobDetector, MarkerColor
from detectors.blob_tracker import label_four_points
from detectors.meanshift import MeanShiftTracker
from detectors.stage import detect_clip
from pipeline.core.detections import load_detections
from pipeline.core.errors import ClipError, StereotrackError
from pipeline.core.frames import StereoFrameSource
from pipeline.core.io import read_csv
from pipeline.core.settings import RunSettings
from renderers.render import render_clip
from renderers.scenario import parse_scenario
from tests.conftest import BALL, needs_ball, small_multi_marker


def _errors(result, clip):
    return {s.camera: s for s in result.summaries}


def test_blob_subpixel_on_lossless_clip(png_clip, tmp_path):
    res = detect_clip(png_clip, RunSettings(detector="blob"), out_dir=tmp_path)
    tr = read_csv(png_clip / "truth.csv")
    visible = int(tr["visible_left"].sum() + tr["visible_right"].sum())
    errs, found = [], 0
    det = load_detections(tmp_path / "detections.csv", 24)
    for k, name, *uv, vl, vr in zip(tr["frame"].astype(int), tr["marker"], tr["u_left"], tr["v_left"], tr["u_right"],
                                    tr["v_right"], tr["visible_left"], tr["visible_right"], strict=True):
        for c, vis in enumerate((vl, vr)):
            if vis and np.all(np.isfinite(det[name][k, 2 * c : 2 * c + 2])):
                found += 1
                errs.append(np.hypot(*(det[name][k, 2 * c : 2 * c + 2] - uv[2 * c : 2 * c + 2])))
    errs = np.array(errs)
    assert found >= 0.99 * visible
    assert np.median(errs) <= 0.15 and np.percentile(errs, 95) <= 0.5, (np.median(errs), np.percentile(errs, 95))
    assert all(s.err_median is not None for s in res.summaries)


@pytest.mark.slow
def test_blob_on_mp4_clip(mp4_clip, tmp_path):
    res = detect_clip(mp4_clip, RunSettings(detector="blob"), out_dir=tmp_path)
    for s in res.summaries:
        assert s.err_median <= 0.5 and s.misses <= 0.01 * s.frames * 3


def test_distractors_never_reported(png_clip, tmp_path):
    detect_clip(png_clip, RunSettings(detector="blob"), out_dir=tmp_path)
    cols = read_csv(tmp_path / "detections.csv")
    assert set(cols["marker"]) <= {"red", "green", "blue"}
    # the magenta cube's projection never hosts a detection
    rig_cube = np.array([0.5, -0.3, 3.0])
    from pipeline.core.calibration import load_calibration

    rig = load_calibration(png_clip)
    cube_uv = rig.left.project(rig_cube[None])[0]
    left = cols["camera"] == "left"
    d = np.hypot(cols["u"][left] - cube_uv[0], cols["v"][left] - cube_uv[1])
    assert d.min() > 5


def test_no_detection_when_out_of_view(tmp_path):
    data = small_multi_marker(frames=30)
    data["objects"] = [{"name": "red", "color": [230, 30, 30], "radius": 0.05,
                        "motion": {"type": "constant_velocity", "start": [-1.6, 0.0, 2.0], "velocity": [3.2, 0.0, 0.0]}}]
    data["distractors"] = []
    clip = tmp_path / "clip"
    render_clip(parse_scenario(data), clip, fmt="png", workers=1)
    res = detect_clip(clip, RunSettings(detector="blob"), out_dir=tmp_path / "out")
    tr = read_csv(clip / "truth.csv")
    det = load_detections(tmp_path / "out" / "detections.csv", 30)["red"]
    for c, cam in enumerate(("left", "right")):
        u = tr[f"u_{cam}"]
        fully_out = (u < -20) | (u > 320 + 20)  # centre beyond the border by more than the radius
        assert fully_out.any()
        assert np.all(np.isnan(det[fully_out, 2 * c]))
    assert all(s.misses <= 2 for s in res.summaries)


@pytest.mark.parametrize("mode", ["meanshift", "camshift"])
def test_meanshift_camshift_on_rendered_clip(png_clip, tmp_path, mode):
    res = detect_clip(png_clip, RunSettings(detector=mode), out_dir=tmp_path)
    for s in res.summaries:
        assert s.err_median <= 2.0


def _leaving_clip(tmp_path, frames=60):
    """A marker that leaves the left edge and comes back, receding as it goes."""
    data = small_multi_marker(frames=frames)
    data["objects"] = [{"name": "red", "color": [230, 30, 30], "radius": 0.05,
                        "motion": {"type": "sinusoid", "center": [-0.2, 0.0, 2.2], "amplitude": [1.1, 0.0, 0.8],
                                   "frequency_hz": [0.5, 0.0, 0.25], "phase": [0.0, 0.0, -1.57]}}]
    data["distractors"] = []
    clip = tmp_path / "leave"
    render_clip(parse_scenario(data), clip, fmt="png", workers=1)
    return clip


@pytest.mark.slow
@pytest.mark.parametrize("mode", ["meanshift", "camshift"])
def test_tracker_reacquires_after_leaving_view(tmp_path, mode):
    clip = _leaving_clip(tmp_path)
    detect_clip(clip, RunSettings(detector=mode), out_dir=tmp_path / "out")
    tr = read_csv(clip / "truth.csv")
    vis = tr["visible_left"].astype(bool)
    det = load_detections(tmp_path / "out" / "detections.csv", 60)["red"][:, :2]
    assert (~vis).any() and vis.any()
    # re-entries: first visible frame after an invisible run
    re_entries = [k for k in range(1, 60) if vis[k] and not vis[k - 1]]
    assert re_entries
    for k in re_entries:
        window = range(k, min(k + 4, 60))
        assert any(np.isfinite(det[j, 0]) for j in window), f"not re-acquired within 3 frames of frame {k}"
    err = np.hypot(det[vis, 0] - tr["u_left"][vis], det[vis, 1] - tr["v_left"][vis])
    assert np.nanmedian(err) <= 2.0


def test_camshift_window_follows_apparent_size(tmp_path):
    data = small_multi_marker(frames=40)
    data["objects"] = [{"name": "red", "color": [230, 30, 30], "radius": 0.06,
                        "motion": {"type": "constant_velocity", "start": [0.0, 0.0, 0.8], "velocity": [0.0, 0.0, 1.5]}}]
    data["distractors"] = []
    clip = tmp_path / "recede"
    render_clip(parse_scenario(data), clip, fmt="png", workers=1)
    tracker = MeanShiftTracker(MarkerColor.from_rgb("red", (230, 30, 30)), "camshift")
    sizes = []
    for fr in StereoFrameSource(clip):
        tracker.update(fr.left)
        sizes.append(tracker.size)
    # apparent diameter shrinks ~ 1/z from 0.8 m to 2.75 m: the window must shrink by > 2×
    assert sizes[2] > 2 * sizes[-1]


@pytest.mark.slow
def test_four_point_labels_never_swap(tmp_path):
    from renderers.scenario import load_scenario

    scen = load_scenario("four_point").with_overrides(frames=100)
    data = scen.model_dump(mode="json")
    data["objects"][0]["point_colors"] = None  # one colour: labelling by geometry
    data["objects"][0]["color"] = [230, 30, 30]
    data["objects"][0]["motion"]["alpha_noise"] = 0.6  # keep it turning
    data["rig"]["width"], data["rig"]["height"], data["rig"]["focal"] = 320, 240, 300
    clip = tmp_path / "fp"
    render_clip(parse_scenario(data), clip, fmt="png", workers=1)
    detect_clip(clip, RunSettings(detector="blob"), out_dir=tmp_path / "out")
    tr = read_csv(clip / "truth.csv")
    det = load_detections(tmp_path / "out" / "detections.csv", 100)
    for j in range(1, 5):
        name = f"target_{j}"
        sel = tr["marker"] == name
        for c, cam in enumerate(("left", "right")):
            d = det[name][:, 2 * c : 2 * c + 2]
            truth_uv = np.column_stack([tr[f"u_{cam}"][sel], tr[f"v_{cam}"][sel]])
            err = np.hypot(*(d - truth_uv).T)
            assert np.nanmax(err) < 2.0, (name, cam, np.nanmax(err))


def test_label_four_points_geometry():
    pts = np.array([[100.0, 80.0], [150.0, 100.0], [100.0, 130.0], [50.0, 100.0]])  # 1 up, 2 right, 3 down, 4 left
    rng = np.random.default_rng(0)
    perm = rng.permutation(4)
    np.testing.assert_allclose(label_four_points(pts[perm], None), pts)


@pytest.mark.slow
@needs_ball
def test_real_footage_blob_meanshift_camshift(tmp_path, ball_reference):
    ref = ball_reference
    assert len(ref) > 200
    for mode in ("blob", "meanshift", "camshift"):
        out = tmp_path / mode
        detect_clip(BALL, RunSettings(detector=mode, markers=["ball:30-60:60:60"]), out_dir=out)
        det = load_detections(out / "detections.csv", 1004)["ball"]
        err = [np.hypot(det[k, 0] - u, det[k, 1] - v) for k, (u, v) in ref.items() if np.isfinite(det[k, 0])]
        assert len(err) > 0.9 * len(ref), mode
        assert np.median(err) <= 5.0, (mode, np.median(err))
        # out of view somewhere, and found again afterwards
        have = np.isfinite(det[:, 0])
        gaps = [k for k in range(1, 1004) if have[k] and not have[k - 1]]
        assert gaps, mode


def test_real_stereo_clip_with_distortion(tmp_path, png_clip):
    """Two videos + a stereo_calib-layout calibration with distortion, no truth, no scenario."""
    clip = tmp_path / "real"
    clip.mkdir()
    K = np.array([[300.0, 0, 160], [0, 300, 120], [0, 0, 1]])
    D = np.array([[-0.25, 0.08, 0.001, -0.001, 0.0]])
    fs = cv2.FileStorage(str(clip / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    for k, v in dict(M1=K, D1=D, M2=K, D2=D).items():
        fs.write(k, v)
    fs.release()
    fs = cv2.FileStorage(str(clip / "extrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    fs.write("R", np.eye(3))
    fs.write("T", np.array([[-0.3], [0.0], [0.0]]))
    fs.release()
    for cam in ("left", "right"):
        w = cv2.VideoWriter(str(clip / f"{cam}.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 30, (320, 240))
        for f in sorted((png_clip / cam).glob("*.png")):
            w.write(cv2.imread(str(f)))
        w.release()
    res = detect_clip(clip, RunSettings(detector="blob", markers=["red=#e61e1e"]), out_dir=tmp_path / "out")
    cols = read_csv(tmp_path / "out" / "detections.csv")
    assert len(cols["u"]) > 30 and res.summaries[0].err_median is None
    # detections are undistorted: compare with cv2.undistortPoints of the raw blob centroid
    raw = BlobDetector([MarkerColor.parse("red=#e61e1e")]).detect(next(iter(StereoFrameSource(clip))).left)[0]
    und = cv2.undistortPoints(np.array([[[raw.u, raw.v]]]), K, D, P=K).ravel()
    first = (cols["frame"] == 0) & (cols["camera"] == "left")
    np.testing.assert_allclose([cols["u"][first][0], cols["v"][first][0]], und, atol=1e-6)
    assert np.hypot(*(und - [raw.u, raw.v])) > 0.1


def test_bad_inputs(tmp_path, png_clip):
    # empty video
    (tmp_path / "empty.mp4").write_bytes(b"")
    with pytest.raises(ClipError, match="empty video"):
        StereoFrameSource(tmp_path / "empty.mp4")
    # corrupt bytes
    (tmp_path / "corrupt.mp4").write_bytes(np.random.default_rng(0).bytes(5000))
    with pytest.raises(ClipError, match="corrupt"):
        StereoFrameSource(tmp_path / "corrupt.mp4")
    # missing right video
    clip = tmp_path / "noright"
    shutil.copytree(png_clip, clip)
    shutil.rmtree(clip / "right")
    with pytest.raises(ClipError, match="no right video"):
        detect_clip(clip)
    # zero-length PNG folder
    (clip / "right").mkdir()
    with pytest.raises(ClipError, match="no images"):
        detect_clip(clip)
    # unequal lengths: error by default, truncation with a warning when allowed
    shutil.rmtree(clip / "right")
    shutil.copytree(png_clip / "right", clip / "right")
    (clip / "right" / "000023.png").unlink()
    res = detect_clip(clip, out_dir=tmp_path / "stamped")  # with timestamps.csv both cameras are read whole
    assert res.summaries[0].frames == 24
    (clip / "timestamps.csv").unlink()  # without: unequal lengths are an error
    with pytest.raises(ClipError, match="left has 24 frames, right has 23"):
        detect_clip(clip)
    with pytest.warns(UserWarning, match="truncating"):
        res = detect_clip(clip, RunSettings(allow_unequal=True), out_dir=tmp_path / "o")
    assert res.summaries[0].frames == 23
    # ROI outside the frame
    with pytest.raises(StereotrackError, match="outside"):
        detect_clip(png_clip, RunSettings(detector="meanshift", roi=(400, 10, 20, 20)), out_dir=tmp_path / "o2")
    # no marker colours for a single video without a scenario (written here: no ../shared needed)
    video = tmp_path / "alone" / "ball.mp4"
    video.parent.mkdir()
    frames = [cv2.imread(str(p)) for p in sorted((png_clip / "left").glob("*.png"))[:5]]
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"mp4v"), 30.0, frames[0].shape[1::-1])
    for f in frames:
        writer.write(f)
    writer.release()
    with pytest.raises(StereotrackError, match="--markers"):
        detect_clip(video)


def test_blob_quantile_is_numpys():
    """The centroid's chroma quantile from a partial sort is numpy's linear quantile, the same float:
    on chroma values (whole numbers in float32, as the detector has them) and on arbitrary ones."""
    from detectors.centroid import _quantile

    rng = np.random.default_rng(3)
    for trial in range(3000):
        n = int(rng.integers(1, 300))
        a = rng.integers(0, 256, n).astype(np.float32) if trial % 2 else rng.normal(0, 50, n).astype(np.float32)
        for q in (0.2, 0.5, 0.73):
            assert _quantile(a, q) == float(np.quantile(a, q))


def _gap_copy(png_clip, tmp_path):
    """The three-marker PNG clip with left frame 10 missing."""
    clip = tmp_path / "gap"
    shutil.copytree(png_clip, clip, ignore=shutil.ignore_patterns("out"))
    (clip / "left" / "000010.png").unlink()
    return clip


@pytest.mark.filterwarnings("ignore:.*frame number")
def test_frames_work_runs_per_camera_in_frame_order_in_decode_threads(tmp_path, png_clip):
    """``StereoFrameSource.frames(work)``: each camera's work sees every frame of that camera in
    order (None for a gap), in a thread of its own, and each pair carries both results."""
    import threading

    calls: dict[int, list] = {0: [], 1: []}

    def work(c: int):
        def f(img):
            calls[c].append((threading.get_ident(), img is None))
            return len(calls[c]) - 1
        return f

    got = [(fr.index, fr.found) for fr in StereoFrameSource(_gap_copy(png_clip, tmp_path)).frames([work(0), work(1)])]
    assert got == [(k, (k, k)) for k in range(24)]
    assert [k for k, (_, gap) in enumerate(calls[0]) if gap] == [10] and not any(g for _, g in calls[1])
    threads = [{t for t, _ in calls[c]} for c in (0, 1)]
    assert all(len(t) == 1 for t in threads) and threads[0] != threads[1]
    assert threading.get_ident() not in threads[0] | threads[1]


@pytest.mark.filterwarnings("ignore:.*frame number", "ignore:.*colour range")
@pytest.mark.parametrize("detector", ["blob", "camshift"])
def test_detecting_in_decode_threads_equals_one_loop(tmp_path, png_clip, monkeypatch, detector):
    """Each camera detects in its own decode thread: the detections, the colour checks and their
    order equal one loop over the pairs on the calling thread (``prefetch=False``), a gap and a
    colour range that matches the background included."""
    import functools

    import detectors.stage

    clip = _gap_copy(png_clip, tmp_path)
    specs = ["red:170-10:120:80", "green:50-70:120:60", "everything:0-179:0:0"]
    threaded = detect_clip(clip, RunSettings(detector=detector, markers=specs), out_dir=tmp_path / "threaded")
    monkeypatch.setattr(detectors.stage, "StereoFrameSource", functools.partial(StereoFrameSource, prefetch=False))
    serial = detect_clip(clip, RunSettings(detector=detector, markers=specs), out_dir=tmp_path / "serial")
    assert len(threaded.rows) > 40 and list(threaded.rows) == list(serial.rows)
    failed = [c.message for c in threaded.checks if not c.ok]
    assert failed == [c.message for c in serial.checks if not c.ok]
    broad = [m for m in failed if "marker 'everything'" in m]
    assert len(broad) == 2 and "left frame" in broad[0] and "right frame" in broad[1]  # left reported first
    for name in ("detections.csv", "detect.json"):
        a, b = ((tmp_path / o / name).read_text() for o in ("threaded", "serial"))
        assert a.replace("threaded", "serial") == b, name


def _whole_mask(monkeypatch) -> None:
    """Label connected components over the whole mask again (the reference for :func:`occupied`)."""
    import detectors.blob

    monkeypatch.setattr(detectors.blob, "occupied", lambda mask: (0, 0, mask.shape[1], mask.shape[0]))


def _scattered_frames(rng, n: int = 60) -> list[np.ndarray]:
    """Grey frames with red and green discs, rings and specks anywhere (edges and corners
    included), some with none of a colour."""
    frames = []
    for _ in range(n):
        img = np.full((240, 320, 3), 90, np.uint8)
        img += rng.integers(0, 20, img.shape, dtype=np.uint8)
        for _ in range(int(rng.integers(0, 6))):
            colour = (30, 30, 230) if rng.random() < 0.6 else (30, 220, 40)
            centre = (int(rng.integers(-5, 325)), int(rng.integers(-5, 245)))
            radius = int(rng.integers(1, 30))
            cv2.circle(img, centre, radius, colour, -1 if rng.random() < 0.8 else 2, cv2.LINE_AA)
        frames.append(img)
    return frames


def test_labelling_where_the_colour_is_equals_labelling_the_whole_mask(monkeypatch):
    """Components are labelled only inside the bounding box of the colour's pixels: the same count,
    label numbers and stats as labelling the whole mask, and so the same detections (search
    windows, the coarse whole-frame search) and colour-check samples, on frames with blobs at the
    edges, rings, specks and no blob at all."""
    from detectors import create_detector
    from detectors.blob import _components
    from detectors.stage import _sample_colours

    rng = np.random.default_rng(11)
    for trial in range(1000):  # a search window's mask, a whole frame's (labelled in parallel stripes)
        mask = np.zeros((148, 148) if trial % 2 else (360, 640), np.uint8)
        for _ in range(int(rng.integers(0, 8))):
            cv2.circle(mask, (int(rng.integers(0, mask.shape[1])), int(rng.integers(0, mask.shape[0]))),
                       int(rng.integers(1, 12)), 255, -1)
        n, labels, stats = _components(mask)
        n_, labels_, stats_, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
        assert n == n_ and np.array_equal(labels, labels_) and np.array_equal(stats[1:], stats_[1:]), trial
    markers = [MarkerColor.from_rgb("red", (230, 30, 30)), MarkerColor.from_rgb("green", (40, 220, 30))]
    frames = _scattered_frames(rng)

    def run() -> tuple[list, list, dict]:
        blob, sampler, samples = BlobDetector(markers), BlobDetector(markers, max_per_marker=2), {}
        coarse = [blob._detect_coarse(mk, np.ascontiguousarray(np.tile(f, (2, 2, 1)))) for f in frames for mk in markers]
        tracker = create_detector("blob", markers)
        tracked = [tracker.detect(f) for f in frames for _ in range(2)]  # the second time in search windows
        for f in frames:
            _sample_colours(sampler, f, "left", set(), samples)
        return coarse, tracked, samples

    cropped = run()
    _whole_mask(monkeypatch)
    whole = run()
    assert sum(len(c) for c in whole[0]) > 100 and cropped[0] == whole[0]
    assert sum(len(c) for c in whole[1]) > 100 and cropped[1] == whole[1]
    assert cropped[2] == whole[2]
    sampled = [s for ss in whole[2].values() for s in ss]
    assert any(s[1] == 0 for s in sampled) and any(s[2] > 0 for s in sampled)  # empty masks and blobs both seen


def test_stage_decoders_share_the_cores(mp4_clip):
    """The stage decodes both cameras at once, each decoder with its share of the cores
    (:func:`decoder_threads`), and the frames are those of a decoder left to FFmpeg's default."""
    from pipeline.core.frames import CameraReader, decoder_threads

    source = StereoFrameSource(mp4_clip)
    assert [r.cap.get(cv2.CAP_PROP_N_THREADS) for r in source.readers] == [decoder_threads(2)] * 2
    default = CameraReader(mp4_clip / "left.mp4")
    one = CameraReader(mp4_clip / "left.mp4", threads=1)
    assert one.cap.get(cv2.CAP_PROP_N_THREADS) == 1
    pairs = list(zip(default, one, strict=True))
    assert len(pairs) == 24 and all(np.array_equal(a, b) for a, b in pairs)
    source.readers[0].close(), source.readers[1].close(), default.close(), one.close()


def test_one_colour_target_labelled_by_geometry_over_1000_frames():
    """Four identical corners, told apart by the plane's geometry at the first frame (the axis is
    the pair 2R apart) and by continuity after: the `four_point` scenario's 1,000 frames projected
    into both cameras with 0.3 px noise and shuffled every frame are labelled correctly in every
    frame (the blob tracker's labelling, without rendering)."""
    from detectors.blob_tracker import label_order
    from pipeline.core.camera import StereoRig
    from renderers.motion import simulate_truth
    from renderers.scenario import load_scenario

    scen = load_scenario("four_point").with_overrides(frames=1000)
    X = simulate_truth(scen).positions  # frames × 4 corners (target_1..4) × 3
    r = scen.rig
    rig = StereoRig.from_parameters(r.width, r.height, (r.focal, r.focal), None, r.baseline)
    rng = np.random.default_rng(5)
    for c, cam in enumerate(rig.cameras):
        previous = None
        for k in range(len(X)):
            truth = cam.project(X[k]) + rng.normal(0, 0.3, (4, 2))
            shuffle = rng.permutation(4)
            order = label_order(truth[shuffle], previous)
            labelled = truth[shuffle][order]
            assert np.array_equal(shuffle[order], np.arange(4)), (c, k)
            previous = labelled


def test_a_marker_that_left_is_not_refound_as_a_speck_of_its_colour():
    """#39 (size continuity): after a 4,000 px ball left the view, a 13 px speck of its colour on
    the wall was "detected" in every remaining frame. A blob 20× smaller (or larger) than the
    marker's recent size is not the marker: it is reported missing, and found again when a blob of
    its size comes back."""
    from detectors.blob_tracker import BlobTracker

    red = MarkerColor.from_rgb("red", (230, 30, 30))
    tracker = BlobTracker([red])

    def frame(ball: tuple[int, int] | None) -> np.ndarray:
        img = np.full((240, 320, 3), 80, np.uint8)
        cv2.circle(img, (260, 40), 2, (30, 30, 230), -1)  # the speck on the wall, always there
        if ball is not None:
            cv2.circle(img, ball, 35, (30, 30, 230), -1)
        return img

    seen = [tracker.detect(frame((80 + 4 * k, 120))) for k in range(8)]
    assert all(len(d) == 1 and d[0].area > 3000 for d in seen)
    gone = [tracker.detect(frame(None)) for _ in range(10)]
    assert gone == [[]] * 10  # missing, not the speck
    back = tracker.detect(frame((150, 150)))
    assert len(back) == 1 and abs(back[0].u - 150) < 1 and abs(back[0].v - 150) < 1
    fresh = BlobTracker([red])  # with no sizes known yet, the speck is the only candidate there is
    assert len(fresh.detect(frame(None))) == 1
