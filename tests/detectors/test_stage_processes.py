"""The detect stage with each camera in a process of its own (``workers`` ≥ 2, as the CLI runs it):
the same detections and record as in threads, on videos, frame folders with a gap, four-point
targets and cameras of unequal length; a camera's error raised as it was; processes that end with
the stage, and with a killed caller."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import cv2
import numpy as np
import psutil
import pytest

import pipeline.core.frames as frames_mod
from detectors.stage import detect_clip
from pipeline.core.errors import ClipError
from pipeline.core.forked import can_fork
from pipeline.core.frames import StereoFrameSource
from pipeline.core.settings import RunSettings
from tests.conftest import REPO

pytestmark = pytest.mark.skipif(not can_fork(), reason="the platform does not fork (cameras run in threads)")


def _gap(png_clip: Path, tmp: Path) -> Path:
    """The PNG clip with left frame 10 missing (the left detector resets there)."""
    clip = tmp / "gap"
    shutil.copytree(png_clip, clip, ignore=shutil.ignore_patterns("out"))
    (clip / "left" / "000010.png").unlink()
    return clip


def _short_right(png_clip: Path, tmp: Path) -> Path:
    """The PNG clip with the right camera's last two frames gone (truncated, with --allow-unequal)."""
    clip = tmp / "short"
    shutil.copytree(png_clip, clip, ignore=shutil.ignore_patterns("out"))
    for k in (22, 23):
        (clip / "right" / f"{k:06d}.png").unlink()
    return clip


def _spy_processes(monkeypatch) -> list:
    """The cameras handed to a process of their own, recorded as the stage starts them."""
    started: list = []
    real = frames_mod._InProcess

    def spy(reader, work):
        started.append(reader.source)
        return real(reader, work)

    monkeypatch.setattr(frames_mod, "_InProcess", spy)
    return started


@pytest.mark.filterwarnings("ignore:.*frame number", "ignore:.*truncating")
@pytest.mark.parametrize("kind", ["mp4", "gap", "target", "unequal"])
def test_cameras_in_processes_find_what_threads_find(kind, tmp_path, mp4_clip, png_clip, target_clip, monkeypatch):
    clip = {"mp4": lambda: mp4_clip, "gap": lambda: _gap(png_clip, tmp_path), "target": lambda: target_clip,
            "unequal": lambda: _short_right(png_clip, tmp_path)}[kind]()
    settings = RunSettings(allow_unequal=kind == "unequal")
    threads = detect_clip(clip, settings, out_dir=tmp_path / "threads", workers=1)
    started = _spy_processes(monkeypatch)
    procs = detect_clip(clip, settings, out_dir=tmp_path / "procs", workers=2)
    assert sorted(p.name.split(".")[0] for p in started) == ["left", "right"]  # the processes did run
    for name in ("detections.csv", "detect.json"):
        assert (tmp_path / "procs" / name).read_bytes() == (tmp_path / "threads" / name).read_bytes(), name
    assert procs.observations.keys() == threads.observations.keys()
    for m, obs in threads.observations.items():
        np.testing.assert_array_equal(procs.observations[m], obs)
    assert len(threads.rows) > 40 * (kind != "target")  # something was found
    assert [c.as_dict() for c in procs.checks] == [c.as_dict() for c in threads.checks]


def test_a_camera_process_s_error_is_raised_as_in_threads(tmp_path, png_clip):
    """An undecodable frame file in the right camera's folder: the stage fails with the same one-line
    error in both modes, and writes no detections."""
    clip = tmp_path / "bad"
    shutil.copytree(png_clip, clip, ignore=shutil.ignore_patterns("out"))
    (clip / "right" / "000007.png").write_bytes(b"not a png")
    messages = []
    for workers in (1, 2):
        with pytest.raises(ClipError) as err:
            detect_clip(clip, out_dir=tmp_path / f"o{workers}", workers=workers)
        messages.append(str(err.value))
        assert not (tmp_path / f"o{workers}" / "detections.csv").exists()
    assert messages[0] == messages[1] and "cannot decode image 000007.png" in messages[0]


def _count(img) -> int:
    return 0 if img is None else int(img[0, 0, 0])


def test_the_processes_end_when_the_frames_are_left_early(png_clip):
    me = psutil.Process()
    before = {p.pid for p in me.children()}  # what earlier tests left, not the stage's
    frames = StereoFrameSource(png_clip).frames([_count, _count], forked=True)
    first = next(frames)
    assert first.images == (None, None) and len(first.found) == 2
    assert len({p.pid for p in me.children()} - before) == 2
    frames.close()
    assert not [p for p in me.children() if p.pid not in before and p.is_running() and p.status() != psutil.STATUS_ZOMBIE]


@pytest.mark.slow
def test_camera_processes_die_with_a_killed_caller(tmp_path, png_clip):
    """SIGKILL to the stage's process: its camera processes end within a few seconds."""
    script = textwrap.dedent(f"""
        import os, sys, time
        sys.path.insert(0, {str(REPO)!r})
        from pipeline.core.frames import StereoFrameSource
        def work(img):
            open({str(tmp_path)!r} + f"/{{os.getpid()}}", "w").close()
            time.sleep(60)
        list(StereoFrameSource({str(png_clip)!r}).frames([work, work], forked=True))
    """)
    proc = subprocess.Popen([sys.executable, "-c", script])
    deadline = time.time() + 30
    while len(list(tmp_path.iterdir())) < 2 and time.time() < deadline:
        time.sleep(0.05)
    children = [psutil.Process(int(p.name)) for p in tmp_path.iterdir()]
    assert len(children) == 2 and all(c.pid != proc.pid for c in children)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    _gone, alive = psutil.wait_procs(children, timeout=3)
    assert not [p for p in alive if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]


def test_cv2_is_usable_in_a_camera_process_after_the_caller_used_its_threads(png_clip):
    """OpenCV's thread pool started in the caller (a whole-frame conversion) before the fork: the
    camera processes still convert (a pool that did not survive the fork would hang them)."""
    big = np.zeros((1080, 1920, 3), np.uint8)
    cv2.GaussianBlur(big, (9, 9), 2)

    def hue_sum(img):
        return None if img is None else int(cv2.cvtColor(cv2.resize(img, (1280, 960)), cv2.COLOR_BGR2HSV).sum())

    got = [fr.found for fr in StereoFrameSource(png_clip).frames([hue_sum, hue_sum], forked=True)]
    want = [fr.found for fr in StereoFrameSource(png_clip).frames([hue_sum, hue_sum])]
    assert got == want and len(got) == 24


def test_a_detector_that_does_not_say_it_forks_runs_in_threads(tmp_path, mp4_clip, monkeypatch):
    """A registered detector keeps the base's ``forks = False`` (a plugin may hold a GPU context
    that a fork loses): the stage runs it in threads with two workers, with the same detections."""
    from detectors.base import _REGISTRY
    from detectors.blob_tracker import BlobTracker

    class Unforked(BlobTracker):
        name = "unforked_blob"
        forks = False

    monkeypatch.setitem(_REGISTRY, Unforked.name, Unforked)
    started = _spy_processes(monkeypatch)
    res = detect_clip(mp4_clip, RunSettings(detector="unforked_blob"), out_dir=tmp_path / "t", workers=2)
    assert not started and len(res.rows) > 40
    detect_clip(mp4_clip, RunSettings(), out_dir=tmp_path / "b", workers=2)
    assert started  # the built-in blob does fork
    ours, theirs = ((tmp_path / d / "detections.csv").read_text() for d in ("t", "b"))
    assert ours == theirs
