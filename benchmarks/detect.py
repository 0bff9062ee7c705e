"""Detection throughput: frames per second per camera for blob, meanshift and CamShift at 640×480
and 1280×720, next to the bare decode rate of the same videos (``cv2.VideoCapture.read`` with
each frame discarded, as the stage's own reader does), measured in the same run. Clips are
rendered first (one marker, the `receding` scene).

    python benchmarks/detect.py [--frames 150] [--repeat 5] [--against REV]

``--against REV`` also times the stage with stereotrack as of git revision REV against today's,
each in a fresh interpreter, interleaved, on the same clips. The stage is also timed on the
default scenario (five markers and the four-point target), where detection outweighs decoding.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2
from _common import page, stack_tree

from detectors.blob import BlobDetector, MarkerColor
from detectors.blob_tracker import search_window
from detectors.meanshift import MeanShiftTracker
from detectors.stage import detect_clip
from renderers.render import render_clip
from renderers.scenario import load_scenario

SIZES = [(640, 480), (1280, 720)]
MANY = "640×480, default scenario (5 markers, four-point target)"


def render(tmp: Path, w: int, h: int, frames: int) -> Path:
    s = load_scenario("receding").with_overrides(frames=frames)
    data = s.model_dump(mode="json")
    data["rig"].update(width=w, height=h, focal=600.0 * w / 640, principal_point=None)
    clip = tmp / f"clip{w}"
    render_clip(type(s).model_validate(data), clip, fmt="mp4")
    return clip


def render_default(tmp: Path, frames: int) -> Path:
    """The default scenario (five markers and the four-point target) at 640×480."""
    clip = tmp / "default640"
    render_clip(load_scenario("default").with_overrides(frames=frames), clip, fmt="mp4")
    return clip


def decode_all(path: Path) -> list:
    """Every frame of a video, kept (for the detector-only loops; not timed)."""
    cap = cv2.VideoCapture(str(path))
    frames = []
    while (got := cap.read())[0]:
        frames.append(got[1])
    return frames


def decode_seconds(path: Path) -> tuple[int, float]:
    """(frames, seconds) of decoding a video with each frame dropped as soon as it is read."""
    cap = cv2.VideoCapture(str(path))
    n, t0 = 0, time.perf_counter()
    while cap.read()[0]:
        n += 1
    return n, time.perf_counter() - t0


def decode_and_stage(clip: Path, out: Path, repeat: int) -> tuple[float, float]:
    """Frames/s per camera of the bare decode (both videos) and of the detect stage, each the
    best of ``repeat`` runs, interleaved (the machine's load moves both alike)."""
    decode, stage = [], []
    for _ in range(repeat):
        (n_l, t_l), (n_r, t_r) = decode_seconds(clip / "left.mp4"), decode_seconds(clip / "right.mp4")
        decode.append((n_l + n_r) / (t_l + t_r))
        t0 = time.perf_counter()
        detect_clip(clip, "blob", out_dir=out)
        stage.append((n_l + n_r) / (time.perf_counter() - t0))
    return max(decode), max(stage)


#: one detect stage in a fresh interpreter with the code in argv[1] (a warm-up run first): seconds
STAGE = ("import sys, time; sys.path.insert(0, sys.argv[1]); from detectors.stage import detect_clip; "
         "detect_clip(sys.argv[2], out_dir=sys.argv[3]); t = time.perf_counter(); "
         "detect_clip(sys.argv[2], out_dir=sys.argv[3]); print(time.perf_counter() - t)")


def stage_against(tree: Path, clip: Path, out: Path, repeat: int) -> tuple[float, float]:
    """Seconds of the stage with the code in ``tree`` and with today's, each the best of ``repeat``
    fresh interpreters, interleaved."""
    here = Path(__file__).resolve().parent.parent
    times: dict[Path, list[float]] = {tree: [], here: []}
    for _ in range(repeat):
        for root in times:
            res = subprocess.run([sys.executable, "-c", STAGE, str(root), str(clip), str(out)], capture_output=True,
                                 text=True, cwd=root, env={**os.environ, "PYTHONPATH": str(root)}, check=True)
            times[root].append(float(res.stdout.strip().splitlines()[-1]))
    return min(times[tree]), min(times[here])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--repeat", type=int, default=5, help="runs of the decode and of the stage, interleaved (best kept)")
    ap.add_argument("--against", default=None, help="a git revision whose detect stage to time beside today's")
    args = ap.parse_args()
    marker = MarkerColor.from_rgb("red", (230, 30, 30))
    print(f"# detection throughput, frames/s per camera ({args.frames} frames, one marker, {os.cpu_count()} cores)\n")
    print("| resolution | bare decode | blob alone, whole frame (1 core) | blob alone, search window (1 core) "
          "| meanshift alone | CamShift alone | detect stage, blob (decode + detect + CSV, both cameras) "
          "| stage / bare decode |")
    print("|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for w, h in SIZES:
            clip = render(Path(tmp), w, h, args.frames)
            frames = decode_all(clip / "left.mp4")
            decode_fps, stage_fps = decode_and_stage(clip, Path(tmp) / f"out{w}", args.repeat)
            cv2.setNumThreads(1)  # "alone on one core"
            blob = BlobDetector([marker])
            t0 = time.perf_counter()
            for f in frames:
                blob.detect(f)
            blob_fps = len(frames) / (time.perf_counter() - t0)
            rois: dict = {}
            t0 = time.perf_counter()
            for f in frames:  # as the detect stage runs it: search near the last detection first
                found = blob.detect(f, rois=rois)
                rois = {d.marker: search_window(d, f.shape) for d in found}
            blob_win_fps = len(frames) / (time.perf_counter() - t0)
            rates = {}
            for mode in ("meanshift", "camshift"):
                tr = MeanShiftTracker(marker, mode)
                t0 = time.perf_counter()
                for f in frames:
                    tr.update(f)
                rates[mode] = len(frames) / (time.perf_counter() - t0)
            cv2.setNumThreads(-1)
            print(f"| {w}×{h} | {decode_fps:.0f} | {blob_fps:.0f} | {blob_win_fps:.0f} | {rates['meanshift']:.0f} "
                  f"| {rates['camshift']:.0f} "
                  f"| {stage_fps:.0f} | {stage_fps / decode_fps:.2f} |", flush=True)
        many = render_default(Path(tmp), args.frames)
        decode_fps, stage_fps = decode_and_stage(many, Path(tmp) / "out_default", args.repeat)
        print("\n| clip | bare decode | detect stage, blob | stage / bare decode |\n|---|---|---|---|")
        print(f"| {MANY} | {decode_fps:.0f} | {stage_fps:.0f} | {stage_fps / decode_fps:.2f} |", flush=True)
        if args.against:
            print(f"\n| clip | stage, `{args.against}` (s) | stage, today (s) | today's speed / `{args.against}` |")
            print("|---|---:|---:|---:|")
            tree = stack_tree(Path(tmp), args.against)
            clips = [(f"{w}×{h}, one marker", Path(tmp) / f"clip{w}") for w, h in SIZES] + [(MANY, many)]
            for name, clip in clips:
                then, now = stage_against(tree, clip, Path(tmp) / "against", args.repeat)
                print(f"| {name} | {then:.3f} | {now:.3f} | {then / now:.2f}× |", flush=True)
    print("\nBare decode: both videos read one after the other from one Python thread; FFmpeg decodes each with "
          "threads of its own, so the bare decode already keeps both cores busy part of the time. The stage decodes "
          "and detects each camera in a thread of its own (OpenCV releases the GIL in both), while the calling "
          "thread collects the detections; they share the cores with the decoder's threads. Both are "
          f"the best of {args.repeat} runs, interleaved; the detectors alone, one run.")


if __name__ == "__main__":
    page("detect", main)
