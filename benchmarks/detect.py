"""Detection throughput: frames per second per camera for blob, meanshift and CamShift at 640×480
and 1280×720, next to the bare decode rate of the same videos (``cv2.VideoCapture.read`` with
each frame discarded, as the stage's own reader does), measured in the same run: one video after
the other from one thread with FFmpeg's default threads, and the fastest plain decode here, both
videos at once, a thread each with the stage's decoder threads. Clips are rendered first (one
marker, the `receding` scene). The process's allocator is set as the CLI sets its own
(:func:`pipeline.core.allocator.tune`), for the decodes and the stage alike.

    python benchmarks/detect.py [--frames 150] [--repeat 5] [--against REV]

``--against REV`` also times the stage with stereotrack as of git revision REV against today's,
each in a fresh interpreter, interleaved, on the same clips. The stage is also timed on the
default scenario (five markers and the four-point target), where detection outweighs decoding.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import cv2
from _common import page, stack_tree

from detectors.blob import BlobDetector, MarkerColor
from detectors.blob_tracker import search_window
from detectors.meanshift import MeanShiftTracker
from detectors.stage import detect_clip
from pipeline.core import allocator
from pipeline.core.frames import decoder_threads
from pipeline.core.settings import RunSettings
from renderers.render import render_clip
from renderers.scenario import load_scenario

SIZES = [(640, 480), (1280, 720)]
MANY = "640×480, default scenario (5 markers, four-point target)"
STAGE_COLUMN = "detect stage, blob (decode + detect + CSV, both cameras; a process per camera)"
THREADS_COLUMN = "the stage in threads (`--workers 1`)"


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


def decode_seconds(path: Path, threads: int | None = None) -> tuple[int, float]:
    """(frames, seconds) of decoding a video with each frame dropped as soon as it is read, with
    ``threads`` decoder threads (None: FFmpeg's default)."""
    cap = (cv2.VideoCapture(str(path)) if threads is None
           else cv2.VideoCapture(str(path), cv2.CAP_ANY, [cv2.CAP_PROP_N_THREADS, threads]))
    n, t0 = 0, time.perf_counter()
    while cap.read()[0]:
        n += 1
    return n, time.perf_counter() - t0


def decode_both_seconds(clip: Path) -> float:
    """Seconds to decode both videos at once, a thread each, with the stage's decoder threads."""
    threads = [threading.Thread(target=decode_seconds, args=(clip / f"{cam}.mp4", decoder_threads(2)))
               for cam in ("left", "right")]
    t0 = time.perf_counter()
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    return time.perf_counter() - t0


class Rates:
    """Frames/s per camera of each run of the bare decode (one video after the other), of both
    videos decoded at once, of the detect stage as the CLI runs it (a process per camera) and of
    the stage in threads, interleaved (the machine's load moves them alike)."""

    def __init__(self, clip: Path, out: Path, repeat: int) -> None:
        self.decode: list[float] = []
        self.both: list[float] = []
        self.stage: list[float] = []
        self.threads: list[float] = []
        for _ in range(repeat):
            (n_l, t_l), (n_r, t_r) = decode_seconds(clip / "left.mp4"), decode_seconds(clip / "right.mp4")
            self.decode.append((n_l + n_r) / (t_l + t_r))
            self.both.append((n_l + n_r) / decode_both_seconds(clip))
            for workers, rates in ((2, self.stage), (1, self.threads)):
                t0 = time.perf_counter()
                detect_clip(clip, RunSettings(detector="blob"), out_dir=out, workers=workers)
                rates.append((n_l + n_r) / (time.perf_counter() - t0))

    def cells(self) -> str:
        """Table cells: the best of each, and the stage against each decode (best against best;
        in brackets the median and range of the ratios within each run)."""
        def ratio(base: list[float]) -> str:
            pairs = sorted(s / b for s, b in zip(self.stage, base, strict=True))
            return (f"{max(self.stage) / max(base):.2f} ({statistics.median(pairs):.2f}; "
                    f"{pairs[0]:.2f}–{pairs[-1]:.2f})")

        return (f"{max(self.decode):.0f} | {max(self.both):.0f} | {max(self.stage):.0f} | {max(self.threads):.0f} "
                f"| {ratio(self.decode)} | {ratio(self.both)}")


def detectors_alone(clip: Path, marker: MarkerColor) -> list[float]:
    """Frames/s of each detector alone on one core over the left video's frames (decoded first):
    blob over the whole frame, blob in search windows (as the stage runs it), meanshift, CamShift."""
    frames = decode_all(clip / "left.mp4")
    cv2.setNumThreads(1)
    try:
        blob = BlobDetector([marker])
        t0 = time.perf_counter()
        for f in frames:
            blob.detect(f)
        rates = [len(frames) / (time.perf_counter() - t0)]
        rois: dict = {}
        t0 = time.perf_counter()
        for f in frames:  # search near the last detection first
            found = blob.detect(f, rois=rois)
            rois = {d.marker: search_window(d, f.shape) for d in found}
        rates.append(len(frames) / (time.perf_counter() - t0))
        for mode in ("meanshift", "camshift"):
            tr = MeanShiftTracker(marker, mode)
            t0 = time.perf_counter()
            for f in frames:
                tr.update(f)
            rates.append(len(frames) / (time.perf_counter() - t0))
        return rates
    finally:
        cv2.setNumThreads(-1)


#: one detect stage in a fresh interpreter with the code in argv[1] (a warm-up run first): seconds
STAGE = ("import sys, time; sys.path.insert(0, sys.argv[1]); from detectors.stage import detect_clip; "
         "exec('try:\\n from pipeline.core import allocator; allocator.tune()\\nexcept ImportError: pass'); "
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
    ap.add_argument("--repeat", type=int, default=5, help="runs of the decodes and of the stage, interleaved")
    ap.add_argument("--against", default=None, help="a git revision whose detect stage to time beside today's")
    args = ap.parse_args()
    allocator.tune()
    marker = MarkerColor.from_rgb("red", (230, 30, 30))
    print(f"# detection throughput, frames/s per camera ({args.frames} frames, one marker, {os.cpu_count()} cores)\n")
    print(f"| resolution | bare decode | bare decode, both at once | {STAGE_COLUMN} | {THREADS_COLUMN} "
          "| stage / bare decode | stage / both at once |\n|---|---|---|---|---|---|---|")
    alone_rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for w, h in SIZES:
            clip = render(Path(tmp), w, h, args.frames)
            rates = Rates(clip, Path(tmp) / f"out{w}", args.repeat)
            print(f"| {w}×{h} | {rates.cells()} |", flush=True)
            alone_rows.append(f"| {w}×{h} | " + " | ".join(f"{r:.0f}" for r in detectors_alone(clip, marker)) + " |")
        many = render_default(Path(tmp), args.frames)
        rates = Rates(many, Path(tmp) / "out_default", args.repeat)
        print(f"\n| clip | bare decode | bare decode, both at once | {STAGE_COLUMN} | {THREADS_COLUMN} "
              "| stage / bare decode | stage / both at once |\n|---|---|---|---|---|---|---|")
        print(f"| {MANY} | {rates.cells()} |", flush=True)
        print("\n| resolution | blob alone, whole frame | blob alone, search window | meanshift alone "
              "| CamShift alone |\n|---|---|---|---|---|")
        print("\n".join(alone_rows), flush=True)
        if args.against:
            print(f"\n| clip | stage, `{args.against}` (s) | stage, today (s) | today's speed / `{args.against}` |")
            print("|---|---:|---:|---:|")
            tree = stack_tree(Path(tmp), args.against)
            clips = [(f"{w}×{h}, one marker", Path(tmp) / f"clip{w}") for w, h in SIZES] + [(MANY, many)]
            for name, clip in clips:
                then, now = stage_against(tree, clip, Path(tmp) / "against", args.repeat)
                print(f"| {name} | {then:.3f} | {now:.3f} | {then / now:.2f}× |", flush=True)
    print(f"\nBare decode: both videos read one after the other from one Python thread; FFmpeg decodes each "
          "with threads of its own (its default), so it already keeps both cores busy part of the time. Both at "
          f"once: a thread per video, {decoder_threads(2)} decoder thread(s) each (the cores shared out, as the "
          "stage's reader does): the fastest plain decode of a stereo clip here. The stage, as the CLI runs it, "
          "decodes and detects each camera in a process of its own while the calling process collects the "
          "detections; in threads (`--workers 1`) the cameras' Python work "
          f"takes turns on the GIL. Decodes and stage run {args.repeat} times, interleaved; each rate is the "
          "best run, each ratio best against best, with the median and the range of the ratios within one run "
          "in brackets (the bare decode with FFmpeg's threads varies most from run to run). The detectors "
          "alone: one run each, on one core. This process's allocator is set as the CLI sets its own "
          "(`pipeline.core.allocator`), for the decodes and the stage alike; in the comparison with an earlier "
          "revision each stage runs as that revision's CLI would (processes where it has them).")


if __name__ == "__main__":
    page("detect", main)
