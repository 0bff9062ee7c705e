"""Rendering many short clips: ``render-batch`` with pyrender (persistent render workers that keep
their EGL context across clips) against the bare pyrender loop in the same number of persistent
processes on the same cores, and with the analytic rasteriser (the default for these scenes:
threads of the command), measured in one run; each row is printed as it is measured.

    python benchmarks/render_batch.py [--clips 20] [--frames 30] [--workers 1,2]

Bare: N processes, each one ``OffscreenRenderer`` rendering both cameras of its share of the
frames, render only (no blur, noise, encoding, truth or files). Ours: ``render_clips`` of all clips
with N workers, everything included. On a GPU machine pass ``--workers 4,8,12``.
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
os.environ.setdefault("LP_NUM_THREADS", "1")  # one llvmpipe thread per process, ours and bare alike

from _common import page

from renderers.render import render_clips
from renderers.scenario import load_scenario

BARE = """
import os, sys, time
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
sys.path.insert(0, {repo!r})
from renderers.motion import simulate_truth
from renderers.scenario import load_scenario
from renderers.scene import StereoScene, create_offscreen_renderer
scen = load_scenario("default").with_overrides(frames={frames}, seed={seed})
data = scen.model_dump(mode="json"); data["rig"].update(width={w}, height={h}, focal=600.0 * {w} / 640, principal_point=None)
scen = type(scen).model_validate(data)
rig = scen.rig.build(); scene = StereoScene(scen, rig, simulate_truth(scen)); r = create_offscreen_renderer(*rig.image_size)
scene.set_frame(0); scene.render(r, 0)
sys.stdout.write("ready\\n"); sys.stdout.flush(); sys.stdin.readline()
t0 = time.perf_counter()
for k in range({frames}):
    scene.set_frame(k); scene.render(r, 0); scene.render(r, 1)
print(time.perf_counter() - t0)
"""


def bare(n: int, frames: int, w: int, h: int) -> float:
    """Aggregate pairs/s of ``n`` concurrent bare loops (started, warmed up, then released together)."""
    env = {**os.environ, "LP_NUM_THREADS": "1"}
    repo = str(Path(__file__).resolve().parent.parent)
    procs = [subprocess.Popen([sys.executable, "-c", BARE.format(repo=repo, frames=frames, seed=i, w=w, h=h)],
                              stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env) for i in range(n)]
    for p in procs:
        assert p.stdout.readline().strip() == "ready"
    t0 = time.perf_counter()
    for p in procs:
        p.stdin.write("\n")
        p.stdin.flush()
    for p in procs:
        p.wait()
    return n * frames / (time.perf_counter() - t0)


def ours(n: int, clips: int, frames: int, w: int, h: int, per_clip: bool = False, rasteriser: str = "pyrender") -> float:
    """Pairs/s of ``render_clips`` with ``n`` persistent workers, or (``per_clip``) of a fresh pool
    per clip — start-up paid per clip, as ``render-batch`` did before its workers persisted."""
    base = load_scenario("default").with_overrides(frames=frames)
    data = base.model_dump(mode="json")
    data["rig"].update(width=w, height=h, focal=600.0 * w / 640, principal_point=None)
    data["render"]["rasteriser"] = rasteriser
    base = type(base).model_validate(data)
    with tempfile.TemporaryDirectory() as tmp:
        jobs = [(base.with_overrides(seed=s), Path(tmp) / f"clip{s}") for s in range(clips)]
        t0 = time.perf_counter()
        if per_clip:
            for job in jobs:
                render_clips([job], "mp4", n)
        else:
            render_clips(jobs, "mp4", n)
        return clips * frames / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clips", type=int, default=20)
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--workers", default="1,2")
    ap.add_argument("--size", default="640x480")
    args = ap.parse_args()
    w, h = (int(v) for v in args.size.split("x"))
    print(f"# render-batch: {args.clips} clips × {args.frames} frames at {w}×{h}, flat shading, MP4; "
          f"{os.cpu_count()} cores; stereo pairs/s\n")
    print("| processes (threads) | bare pyrender loop (render only) | render-batch, pyrender, persistent workers "
          "| a new pool per clip | persistent / bare | persistent / per clip | render-batch, analytic | analytic / bare |")
    print("|---|---|---|---|---|---|---|---|", flush=True)
    for n in (int(v) for v in args.workers.split(",")):
        b = bare(n, args.clips * args.frames // n, w, h)
        o = ours(n, args.clips, args.frames, w, h)
        p = ours(n, args.clips, args.frames, w, h, per_clip=True)
        a = ours(n, args.clips, args.frames, w, h, rasteriser="analytic")
        print(f"| {n} | {b:.1f} | {o:.1f} | {p:.1f} | {o / b:.2f} | {o / p:.2f} | {a:.1f} | {a / b:.2f} |", flush=True)


if __name__ == "__main__":
    page("render_batch", main)
