"""Rendering throughput: first the whole `stereotrack render default` command (a fresh process;
the analytic rasteriser, and pyrender) against a bare pyrender loop of the same scene run as a
process of its own (pyrender's own read-back, 4× MSAA, render only), interleaved rounds; then
stereo frame pairs per second of `render_clip` (sensor noise, blur and MP4 encoding included; the
analytic rasteriser where it draws the scene, and pyrender) next to a bare single-process pyrender
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


def scenario(width: int, height: int, shading: str, frames: int, rasteriser: str = "auto"):
    s = load_scenario("default").with_overrides(frames=frames)
    data = s.model_dump(mode="json")
    f = 600.0 * width / 640
    data["rig"].update(width=width, height=height, focal=f, principal_point=None)
    data["render"].update(shading=shading, rasteriser=rasteriser)
    return type(s).model_validate(data)


#: a bare pyrender loop as a program of its own: the default scene, stock OffscreenRenderer
#: (pyrender's read-back of colour and depth, 4× MSAA), both cameras per frame, nothing written;
#: prints the loop's own seconds
BARE_PROGRAM = """
import os, sys, time
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
import pyrender
from renderers.motion import simulate_truth
from renderers.scenario import load_scenario
from renderers.scene import StereoScene
s = load_scenario("default").with_overrides(frames=int(sys.argv[1]))
rig = s.rig.build()
scene = StereoScene(s, rig, simulate_truth(s))
r = pyrender.OffscreenRenderer(*rig.image_size)
t0 = time.perf_counter()
for k in range(s.frames):
    scene.set_frame(k)
    for c in (0, 1):
        scene.render(r, c)
print(time.perf_counter() - t0)
"""


def whole_commands(frames: int, rounds: int = 3) -> dict[str, list[float]]:
    """Wall seconds of fresh processes, interleaved over ``rounds``: ``stereotrack render default``
    (the analytic rasteriser; and pyrender, from a scenario file saying so) and the bare pyrender
    program (its whole run, and its loop alone)."""
    import subprocess
    import sys

    here = Path(__file__).resolve().parent.parent
    env = {**os.environ, "PYTHONPATH": str(here)}
    out: dict[str, list[float]] = {k: [] for k in ("analytic", "pyrender", "bare", "bare loop")}
    with tempfile.TemporaryDirectory() as tmp:
        yaml = Path(tmp) / "pyrender.yaml"
        write_text(yaml, scenario(640, 480, "flat", frames, "pyrender").to_yaml())
        cli = [sys.executable, "-m", "pipeline.app.cli", "render"]
        for _ in range(rounds):
            for key, args in (("analytic", ["default", "--frames", str(frames)]), ("pyrender", [str(yaml)])):
                t0 = time.perf_counter()
                subprocess.run([*cli, *args, "-o", f"{tmp}/{key}"], check=True, capture_output=True, env=env)
                out[key].append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            res = subprocess.run([sys.executable, "-c", BARE_PROGRAM, str(frames)], check=True, capture_output=True,
                                 text=True, env=env)
            out["bare"].append(time.perf_counter() - t0)
            out["bare loop"].append(float(res.stdout.split()[-1]))
    return out


def commands_table(md: LiveDoc, frames_list: list[int]) -> None:
    import statistics

    md += ["| frames | `stereotrack render default` (s) | the same, pyrender (s) | bare pyrender program (s) "
           "| its loop alone (s) | command vs bare program | command vs its loop alone | pyrender command vs bare program |",
           "|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for frames in frames_list:
        t = {k: statistics.median(v) for k, v in whole_commands(frames).items()}
        md.append(f"| {frames} | {t['analytic']:.2f} | {t['pyrender']:.2f} | {t['bare']:.2f} | {t['bare loop']:.2f} "
                  f"| {t['bare'] / t['analytic']:.2f}× | {t['bare loop'] / t['analytic']:.2f}× "
                  f"| {t['bare'] / t['pyrender']:.2f}× |")


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
    md += ["The whole command from a fresh process (imports, truth, blur, noise, MP4 encoding, files) against a bare "
           "pyrender loop of the same scene run as a program of its own, 640×480, flat, 4× MSAA; medians of 3 "
           "interleaved rounds; the speed-ups are the bare program's seconds over the command's:", ""]
    commands_table(md, [args.frames, 4 * args.frames])
    md.append("")
    sizes_table(md, args.frames, cpu, cores)
    readback_table(md, args.frames)
    scen = scenario(640, 480, "flat", args.frames, "pyrender")
    thread, inline = writer_thread(scen)
    md += ["", "| 640×480, flat, `render_clip` in one process | pairs/s |", "|---|---:|",
           f"| blur, noise and encoding on a writer thread (the default on a GPU) | {thread:.1f} |",
           f"| the same on the rendering thread (the default under llvmpipe) | {inline:.1f} |", "",
           f"The writer thread: {thread / inline:.2f}× the pairs per second.", ""]
    md += ["| 640×480, flat: clips at once | render processes | pairs/s, all clips together |", "|---|---:|---:|"]
    for workers in sorted({2, cores}):
        md.append(f"| {workers} | {workers} | {many_clips(scen, workers):.1f} |")
    md += ["", "render_clip, pyrender: one process per camera (one llvmpipe thread each on a CPU), blur, sensor noise, "
           "MP4 encoding and process start-up (about 1 s) included; analytic: one thread per camera in the calling "
           "process; the bare loops only render, both cameras in one process. The writer-thread and many-clips tables "
           "render with pyrender."]
    path = out / ("bench_render.md" if cpu else "bench_render_gpu.md")
    write_text(path, "\n".join(md) + "\n")
    print(f"\nwrote {path}")


def sizes_table(md: LiveDoc, frames: int, cpu: bool, cores: int) -> None:
    md += ["| resolution | shading | bare loop (pairs/s) | bare loop, 1 rasteriser thread | render_clip, analytic "
           "| render_clip, pyrender | analytic / bare loop | pyrender / bare loop |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for w, h in SIZES:
        for shading in ("flat", "lit"):
            scen = scenario(w, h, shading, frames, "pyrender")
            bare = bare_loop(scen)
            bare1 = f"{bare_loop(scen, '1'):.1f}" if cpu else "— (GPU)"
            two = ours(scen, 2)
            ana = ours(scenario(w, h, shading, frames), 2) if shading == "flat" else None
            a, ar = (f"{ana:.1f}", f"{ana / bare:.2f}") if ana else ("— (lit: pyrender)", "—")
            md.append(f"| {w}×{h} | {shading} | {bare:.1f} | {bare1} | {a} | {two:.1f} | {ar} | {two / bare:.2f} |")


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
