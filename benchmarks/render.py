"""Rendering throughput: stereo frame pairs per second of `render_clip` (both cameras in two
processes, sensor noise, blur and MP4 encoding included) next to a bare single-process pyrender
loop over the same scene (render only), measured in the same run, at three resolutions and with
flat and lit shading; then, at 640×480, the bare loop with pyrender's own read-back (colour and
depth) against the colour-only read-back, with and without multisampling.

    python benchmarks/render.py [--frames 60]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from renderers.motion import simulate_truth
from renderers.render import render_clip
from renderers.scenario import load_scenario
from renderers.scene import StereoScene, create_offscreen_renderer

SIZES = [(320, 240), (640, 480), (1280, 720)]


def scenario(width: int, height: int, shading: str, frames: int):
    s = load_scenario("default").with_overrides(frames=frames)
    data = s.model_dump(mode="json")
    f = 600.0 * width / 640
    data["rig"].update(width=width, height=height, focal=f, principal_point=None)
    data["render"]["shading"] = shading
    return type(s).model_validate(data)


def bare_loop(scen, threads: str | None = None) -> float:
    """Pairs/s of a plain pyrender loop: one renderer, both cameras, no post-processing or I/O.
    ``threads``: Mesa llvmpipe rasteriser threads (None: its default, one per core)."""
    if threads is not None:
        import subprocess
        import sys

        code = (f"import os; os.environ['LP_NUM_THREADS']='{threads}'; import sys; sys.path.insert(0, {str(os.getcwd())!r}); "
                f"from benchmarks.render import scenario, bare_loop; "
                f"print(bare_loop(scenario({scen.rig.width}, {scen.rig.height}, {scen.render.shading!r}, {scen.frames})))")
        return float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout)
    rig = scen.rig.build()
    scene = StereoScene(scen, rig, simulate_truth(scen))
    r = create_offscreen_renderer(*rig.image_size)
    scene.set_frame(0)
    scene.render(r, 0)  # warm-up (shader compilation)
    t0 = time.perf_counter()
    for k in range(scen.frames):
        scene.set_frame(k)
        scene.render(r, 0)
        scene.render(r, 1)
    dt = time.perf_counter() - t0
    r.delete()
    return scen.frames / dt


def readback(scen, rounds: int = 3) -> dict[str, float]:
    """Pairs/s of the bare loop (one process, llvmpipe's default threads) three ways, interleaved
    over ``rounds`` rounds (median): pyrender's own read-back (colour and depth), stereotrack's
    colour-only read-back, and colour-only without multisampling."""
    import statistics

    from renderers.scene import set_multisample

    rig = scen.rig.build()
    scene = StereoScene(scen, rig, simulate_truth(scen))
    r = create_offscreen_renderer(*rig.image_size)
    inner = r._renderer
    ours_read, pyrender_read = inner._read_main_framebuffer, type(inner)._read_main_framebuffer.__get__(inner)
    ways = {"pyrender read-back (colour + depth), 4× MSAA": (pyrender_read, 4),
            "colour only, 4× MSAA (the default)": (ours_read, 4), "colour only, no MSAA (multisample: 0)": (ours_read, 0)}
    out: dict[str, list[float]] = {k: [] for k in ways}
    for _ in range(rounds):
        for name, (read, samples) in ways.items():
            inner._read_main_framebuffer = read
            set_multisample(r, samples)
            scene.set_frame(0)
            scene.render(r, 0)  # warm-up after a framebuffer change
            t0 = time.perf_counter()
            for k in range(scen.frames):
                scene.set_frame(k)
                scene.render(r, 0)
                scene.render(r, 1)
            out[name].append(scen.frames / (time.perf_counter() - t0))
    r.delete()
    return {k: statistics.median(v) for k, v in out.items()}


def ours(scen, workers: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        render_clip(scen, tmp, fmt="mp4", workers=workers)
        return scen.frames / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150)
    args = ap.parse_args()
    print(f"# render throughput, stereo pairs/s ({args.frames} frames of the default scenario, {os.cpu_count()} cores)\n")
    print("| resolution | shading | bare loop, llvmpipe on 2 cores | bare loop, 1 core | render_clip, 2 workers "
          "| ours / bare (both on 2 cores) | ours per core / bare 1 core |")
    print("|---|---|---|---|---|---|---|")
    for w, h in SIZES:
        for shading in ("flat", "lit"):
            scen = scenario(w, h, shading, args.frames)
            bare2 = bare_loop(scen)
            bare1 = bare_loop(scen, "1")
            two = ours(scen, 2)
            print(f"| {w}×{h} | {shading} | {bare2:.1f} | {bare1:.1f} | {two:.1f} | {two / bare2:.2f} | "
                  f"{two / 2 / bare1:.2f} |", flush=True)
    print("\n| 640×480 | read-back and anti-aliasing | bare loop (pairs/s, median of 3 interleaved rounds) | "
          "vs pyrender's read-back |")
    print("|---|---|---|---|")
    for shading in ("flat", "lit"):
        res = readback(scenario(640, 480, shading, args.frames))
        base = next(iter(res.values()))
        for name, v in res.items():
            print(f"| {shading} | {name} | {v:.1f} | {v / base:.2f}× |", flush=True)
    print("\nrender_clip: one process per camera with one llvmpipe thread each, blur, sensor noise, MP4 encoding and "
          "process start-up (about 1 s) included; the bare loops only render, both cameras in one process.")


if __name__ == "__main__":
    main()
