"""Rendering throughput: stereo frame pairs per second of `render_clip` (both cameras in two
processes, sensor noise, blur and MP4 encoding included) next to a bare single-process pyrender
loop over the same scene (render only), measured in the same run, at three resolutions and with
flat and lit shading; then, at 640×480, the bare loop with pyrender's own read-back (colour and
depth) against the colour-only read-back, with and without multisampling; the writer thread
against writing on the rendering thread; and many clips at once on every core.

    python benchmarks/render.py [--frames 150] [--out DIR | --write-docs]

``--write-docs`` writes docs/bench_render.md (docs/bench_render_gpu.md when OpenGL is a GPU's).
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from _common import LiveDoc, add_output_args, command, output_dir

from pipeline.core.io import write_text
from renderers.motion import simulate_truth
from renderers.render import render_clip, render_clips
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

        here = os.path.dirname(os.path.abspath(__file__))
        paths = [here, os.path.dirname(here)]
        code = (f"import os; os.environ['LP_NUM_THREADS']='{threads}'; import sys; sys.path[:0] = {paths!r}; "
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


def gl_renderer() -> str:
    """The OpenGL renderer's name (llvmpipe on a CPU; the GPU's otherwise)."""
    from OpenGL import GL

    r = create_offscreen_renderer(64, 48)
    name = GL.glGetString(GL.GL_RENDERER).decode()
    r.delete()
    return name


def writer_thread(scen, rounds: int = 3) -> tuple[float, float]:
    """Pairs/s of ``render_clip`` in this process (``workers=1``: both cameras one after the other)
    with blur, noise and encoding on the writer thread, and with them on the rendering thread,
    interleaved, median of ``rounds`` (the renderer's own choice, :func:`writer_threaded`, aside)."""
    import statistics

    import renderers.render as rr

    real, out = rr.writer_threaded, {True: [], False: []}
    try:
        for _ in range(rounds):
            for threaded in (True, False):
                rr.writer_threaded = lambda renderer, t=threaded: t
                out[threaded].append(ours(scen, 1))
    finally:
        rr.writer_threaded = real
    return statistics.median(out[True]), statistics.median(out[False])


def many_clips(scen, workers: int) -> float:
    """Pairs/s of ``render_clips`` rendering ``workers`` clips with ``workers`` processes (each
    process renders two cameras' frames, one after the other, in its one EGL context)."""
    n = workers
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        render_clips([(scen, Path(tmp) / f"clip{i}") for i in range(n)], "mp4", workers)
        return n * scen.frames / (time.perf_counter() - t0)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=150)
    add_output_args(ap)
    args = ap.parse_args()
    out = output_dir(args, "render")
    name = gl_renderer()
    cpu = "llvmpipe" in name.lower()
    cores = os.cpu_count() or 1
    md = LiveDoc(["# Rendering throughput" + ("" if cpu else " on a GPU"), "",
                  f"Generated by `{command()}` ({args.frames} frames of the default scenario; "
                  f"OpenGL renderer: {name}; {cores} cores). Ratios compare alternatives measured in the same run.", ""])
    sizes_table(md, args.frames, cpu, cores)
    readback_table(md, args.frames)
    scen = scenario(640, 480, "flat", args.frames)
    thread, inline = writer_thread(scen)
    md += ["", "| 640×480, flat, `render_clip` in one process | pairs/s |", "|---|---:|",
           f"| blur, noise and encoding on a writer thread (the default on a GPU) | {thread:.1f} |",
           f"| the same on the rendering thread (the default under llvmpipe) | {inline:.1f} |", "",
           f"The writer thread: {thread / inline:.2f}× the pairs per second.", ""]
    md += ["| 640×480, flat: clips at once | render processes | pairs/s, all clips together |", "|---|---:|---:|"]
    for workers in sorted({2, cores}):
        md.append(f"| {workers} | {workers} | {many_clips(scen, workers):.1f} |")
    md += ["", "render_clip: one process per camera (one llvmpipe thread each on a CPU), blur, sensor noise, MP4 encoding "
           "and process start-up (about 1 s) included; the bare loops only render, both cameras in one process."]
    path = out / ("bench_render.md" if cpu else "bench_render_gpu.md")
    write_text(path, "\n".join(md) + "\n")
    print(f"\nwrote {path}")


def sizes_table(md: LiveDoc, frames: int, cpu: bool, cores: int) -> None:
    md += ["| resolution | shading | bare loop (pairs/s) | bare loop, 1 rasteriser thread | render_clip, 2 workers "
           "| render_clip / bare loop |", "|---|---|---:|---:|---:|---:|"]
    for w, h in SIZES:
        for shading in ("flat", "lit"):
            scen = scenario(w, h, shading, frames)
            bare = bare_loop(scen)
            bare1 = f"{bare_loop(scen, '1'):.1f}" if cpu else "— (GPU)"
            two = ours(scen, 2)
            md.append(f"| {w}×{h} | {shading} | {bare:.1f} | {bare1} | {two:.1f} | {two / bare:.2f} |")


def readback_table(md: LiveDoc, frames: int) -> None:
    md += ["", "| 640×480 | read-back and anti-aliasing | bare loop (pairs/s, median of 3 interleaved rounds) | "
           "vs pyrender's read-back |", "|---|---|---:|---:|"]
    for shading in ("flat", "lit"):
        res = readback(scenario(640, 480, shading, frames))
        base = next(iter(res.values()))
        for label, v in res.items():
            md.append(f"| {shading} | {label} | {v:.1f} | {v / base:.2f}× |")


if __name__ == "__main__":
    main()
