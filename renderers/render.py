"""Render a scenario into one clip folder: videos or PNG frames, ``calib.yaml``,
``scenario.yaml``, ``truth.csv`` and, for the four-point target, ``target_truth.csv``.

Like Kubric's workers: one seeded job renders one scene into one folder with all its ground
truth. Scenes the analytic rasteriser draws render each camera on a thread of this process (its
loop, blur, noise and encoding release the GIL); pyrender's render each camera in a process of its
own (one ``OffscreenRenderer`` reused for all frames), so a stereo clip uses both cores of a small
machine either way.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import shutil
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.errors import StereotrackError
from renderers.clipfiles import RIG_FILE, RenderResult, check_ours, finish_clip, staging_dir
from renderers.motion import Truth, simulate_truth
from renderers.scenario import Scenario
from renderers.truth import frame_times
from renderers.writers import BackgroundWriter, Format, FrameWriter, SensorNoise, writer_threaded

__all__ = ["CAMERA_NAMES", "RIG_FILE", "RenderResult", "render_camera", "render_clip", "render_clips"]

CAMERA_NAMES = ("left", "right")


def render_camera(
    scenario: Scenario, cam_index: int, clip_dir: Path, fmt: Format, tick: Callable[[int], None] | None = None,
    renderer=None,  # a pyrender.OffscreenRenderer to reuse (a persistent worker's; any size)
    truth: Truth | None = None,
) -> np.ndarray | None:
    """Render every frame of one camera into ``clip_dir`` at that camera's own times (sync offset,
    jitter, rolling shutter, exposure), skipping the frames it drops. Returns, for scenes with
    objects that can hide a marker (distractors, occluders), each frame's visible pixel count per
    marker (frames × markers, from a segmentation render); else None."""
    rig = scenario.rig.build_any()
    truth = truth if truth is not None else simulate_truth(scenario)
    times = frame_times(scenario)
    scene, renderer, own = _scene(scenario, rig, truth, cam_index, renderer)
    counts = np.zeros((scenario.frames, len(truth.names)), dtype=np.int64) if scenario.distractors else None
    try:
        w, h = size = rig.sizes[cam_index]
        rs = scenario.render
        noise = SensorNoise((h, w, 3), rs.noise_std, scenario.seed, cam_index)
        name = scenario.rig.camera_names()[cam_index]
        writer = BackgroundWriter(lambda: FrameWriter(clip_dir, name, fmt, scenario.fps, size),
                                  rs.blur_sigma, noise, threaded=writer_threaded(renderer))
        try:
            for k in range(scenario.frames):
                if times.present[cam_index, k]:
                    img = _render_frame(scene, renderer, cam_index, k, float(times.t[cam_index, k]))
                    if counts is not None:  # the pose at the frame's mid-exposure time
                        counts[k] = scene.marker_pixels(renderer, cam_index)
                    writer.put(img, k)
                if tick is not None:
                    tick(k)
            writer.close()
        except BaseException:
            writer.abort()
            raise
    finally:
        if own:
            renderer.delete()
    return counts


def _scene(scenario: Scenario, rig, truth: Truth, cam_index: int, renderer):
    """The scene that draws ``scenario`` (analytic, or pyrender's with a renderer: ``renderer``, or
    one of its own, to delete after) and whether the renderer is its own."""
    if scenario.analytic():
        from renderers.raster import AnalyticScene

        return AnalyticScene(scenario, rig, truth), None, False
    from renderers.scene import StereoScene, create_offscreen_renderer, set_multisample

    scene = StereoScene(scenario, rig, truth)
    own = renderer is None
    if own:
        renderer = create_offscreen_renderer(*scene.views[cam_index].size)
    set_multisample(renderer, scenario.render.multisample)
    return scene, renderer, own


def exposure_offsets(scenario: Scenario) -> np.ndarray:
    """Sub-frame render times relative to the frame's mid-exposure (``[0]`` without exposure)."""
    e, n = scenario.render.exposure_s, scenario.render.exposure_samples
    return (np.arange(n) + 0.5) / n * e - e / 2 if e > 0 else np.zeros(1)


def ideal_timing(scenario: Scenario, cam_index: int) -> bool:
    """Whether camera ``cam_index`` exposes frame k at exactly ``k/fps``, all at once, instantly."""
    r = scenario.rig
    return (scenario.render.exposure_s == 0 and r.line_delay_s == 0 and r.jitter_s == 0
            and r.time_offsets()[cam_index] == 0)


def _render_frame(scene, renderer, cam_index: int, k: int, t0: float) -> np.ndarray:
    """One camera's frame k: the scene at the frame's time (the mean of the sub-frame renders over
    the exposure), as the camera's lens records it; the pose is left at mid-exposure."""
    scenario = scene.scenario
    view = scene.views[cam_index]
    if ideal_timing(scenario, cam_index):
        scene.set_frame(k)
        return view.finish(scene.render(renderer, cam_index))
    offsets = exposure_offsets(scenario)
    acc = np.zeros((), np.float32)
    for dt in offsets:
        scene.set_time(cam_index, t0 + dt)
        acc = acc + scene.render(renderer, cam_index).astype(np.float32)
    if len(offsets) > 1:
        scene.set_time(cam_index, t0)
    img = np.clip(acc / len(offsets) + 0.5, 0, 255).astype(np.uint8)
    return view.finish(img)


# -- persistent render workers ------------------------------------------------------------------
# Each worker process keeps one EGL context (one OffscreenRenderer, resized per camera view) across
# every camera of every clip it renders, so a batch of clips pays the start-up (imports, context)
# once per worker instead of once per camera per clip.

_RENDERER: list = []
_PROGRESS: mp.Queue | None = None


def _worker_init(parent_pid: int, progress: mp.Queue | None) -> None:
    """Die with the parent; one OpenCV thread (blur, encoding) per worker, as llvmpipe has one."""
    from pipeline.core.lifeline import die_with_parent, ignore_sigint

    die_with_parent(parent_pid)
    ignore_sigint()
    cv2.setNumThreads(1)
    global _PROGRESS
    _PROGRESS = progress


def _render_job(scenario_json: str, cam_index: int, staging: str, fmt: Format, job: int) -> np.ndarray | None:
    """Worker entry point: one camera of one clip into ``staging``, reusing this process's renderer
    of that size; returns the camera's marker pixel counts (see :func:`render_camera`)."""
    from renderers.scene import create_offscreen_renderer

    scenario = Scenario.model_validate_json(scenario_json)
    if not _RENDERER and not scenario.analytic():
        _RENDERER.append(create_offscreen_renderer(scenario.rig.width, scenario.rig.height))

    def tick(k: int) -> None:
        if _PROGRESS is not None and (k % 5 == 4 or k == scenario.frames - 1):
            _PROGRESS.put((job, cam_index, k + 1))

    return render_camera(scenario, cam_index, Path(staging), fmt, tick, _RENDERER[0] if _RENDERER else None,
                         simulate_truth(scenario))


def render_clips(
    jobs: Sequence[tuple[Scenario, str | Path]],
    fmt: Format = "mp4",
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
) -> list[RenderResult]:
    """Render several clips (scenario, folder) with ``workers`` persistent processes.

    Every camera of every clip is one job; a worker keeps its EGL context across jobs. Each clip
    is rendered into a hidden staging folder and committed only when both cameras and its truth
    are written; workers die with this process. ``progress(done, total)`` counts stereo pairs.
    ``workers=1`` renders here, in this process, one camera after the other. A folder that
    stereotrack did not render (and is not empty) is refused before any work starts.
    """
    from pipeline.core.io import ensure_dir

    dirs = [Path(d) for _, d in jobs]
    for d in dirs:  # before any work: a folder stereotrack did not render is never replaced
        check_ours(d)
        ensure_dir(d.parent)
    stagings: list[Path] = []
    try:  # an interrupt while the staging folders are being made leaves none of them behind
        for d in dirs:
            stagings.append(staging_dir(d))  # named first, made after: the cleanup below sees each
            stagings[-1].mkdir(parents=True)
        if workers <= 1:
            return _render_here(jobs, stagings, dirs, fmt, progress)
        if all(s.analytic() for s, _ in jobs):
            return _render_threads(jobs, stagings, dirs, fmt, workers, progress)
        return _render_pool(jobs, stagings, dirs, fmt, workers, progress)
    except BaseException:
        for st in stagings:
            shutil.rmtree(st, ignore_errors=True)
        raise


def _render_here(jobs: Sequence[tuple[Scenario, str | Path]], stagings: list[Path], dirs: list[Path], fmt: Format,
                 progress: Callable[[int, int], None] | None) -> list[RenderResult]:
    """Every camera of every clip in this process, with one renderer."""
    from renderers.scene import create_offscreen_renderer

    total = sum(s.frames for s, _ in jobs)
    gl = next((s for s, _ in jobs if not s.analytic()), None)
    renderer = create_offscreen_renderer(gl.rig.width, gl.rig.height) if gl is not None else None
    results, done = [], 0
    try:
        for j, (scen, _) in enumerate(jobs):
            truth = simulate_truth(scen)
            counts = []
            cams = scen.rig.n_cameras
            for c in range(cams):

                def tick(k: int, c: int = c, base: int = done, n: int = scen.frames, cams: int = cams) -> None:
                    if progress is not None:
                        progress(base + (k + 1 + c * n) // cams, total)

                counts.append(render_camera(scen, c, stagings[j], fmt, tick, renderer, truth))
            done += scen.frames
            results.append(finish_clip(scen, stagings[j], dirs[j], fmt, counts, truth))
    finally:
        if renderer is not None:
            renderer.delete()
    return results


class _Clips:
    """The clips of a multi-clip render and their cameras' progress: a clip is finished (its files
    written and committed) once all its cameras are. Shared by the thread and the process paths."""

    def __init__(self, jobs: Sequence[tuple[Scenario, str | Path]], stagings: list[Path], dirs: list[Path],
                 fmt: Format, truths: list[Truth] | None = None) -> None:
        self.jobs, self.stagings, self.dirs, self.fmt = jobs, stagings, dirs, fmt
        self.truths: list[Truth | None] = list(truths) if truths is not None else [None] * len(jobs)
        self.counts: list[list] = [[None] * scen.rig.n_cameras for scen, _ in jobs]
        self.cams_done = [0] * len(jobs)
        self.results: list[RenderResult | None] = [None] * len(jobs)
        self.frames_done: dict[tuple[int, int], int] = {}
        self.total = sum(s.frames for s, _ in jobs)

    def camera_done(self, j: int, c: int, count: np.ndarray | None) -> None:
        scen = self.jobs[j][0]
        self.counts[j][c], self.frames_done[(j, c)] = count, scen.frames
        self.cams_done[j] += 1
        if self.cams_done[j] == scen.rig.n_cameras:
            self.results[j] = finish_clip(scen, self.stagings[j], self.dirs[j], self.fmt, self.counts[j], self.truths[j])

    def report(self, progress: Callable[[int, int], None] | None) -> None:
        if progress is not None:
            done = sum(k / self.jobs[j][0].rig.n_cameras for (j, _), k in list(self.frames_done.items()))
            progress(int(done), self.total)

    def finished(self) -> list[RenderResult]:
        return [r for r in self.results if r is not None]


def _render_threads(jobs: Sequence[tuple[Scenario, str | Path]], stagings: list[Path], dirs: list[Path],
                    fmt: Format, workers: int, progress: Callable[[int, int], None] | None) -> list[RenderResult]:
    """Every camera of every clip (all drawn by the analytic rasteriser) on ``workers`` threads of
    this process; a clip is finished when all its cameras are. On an error or an interrupt the
    other cameras stop at their next frame."""
    import concurrent.futures as cf

    stop = threading.Event()
    clips = _Clips(jobs, stagings, dirs, fmt, [simulate_truth(scen) for scen, _ in jobs])

    def one(j: int, c: int) -> np.ndarray | None:
        def tick(k: int) -> None:
            if stop.is_set():
                raise InterruptedError
            clips.frames_done[(j, c)] = k + 1

        return render_camera(jobs[j][0], c, stagings[j], fmt, tick, None, clips.truths[j])

    with cf.ThreadPoolExecutor(max_workers=workers, thread_name_prefix="render") as pool:
        futs = {pool.submit(one, j, c): (j, c) for j, (scen, _) in enumerate(jobs) for c in range(scen.rig.n_cameras)}
        try:
            pending = set(futs)
            while pending:
                finished, pending = cf.wait(pending, timeout=0.2, return_when=cf.FIRST_COMPLETED)
                for f in finished:
                    clips.camera_done(*futs[f], f.result())
                clips.report(progress)
        except BaseException:
            stop.set()
            raise
    return clips.finished()


def _render_pool(jobs: Sequence[tuple[Scenario, str | Path]], stagings: list[Path], dirs: list[Path], fmt: Format,
                 workers: int, progress: Callable[[int, int], None] | None) -> list[RenderResult]:
    """Every camera of every clip as a job of a pool of persistent render workers (one llvmpipe
    thread each, a user's own LP_NUM_THREADS aside); a clip is finished when both its cameras are."""
    import concurrent.futures as cf

    from pipeline.core.interrupts import signals_deferred
    from pipeline.core.lifeline import child_environment, end_pool

    ctx = mp.get_context("spawn")
    q: mp.Queue = ctx.Queue()
    pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init,
                                  initargs=(os.getpid(), q))
    clips = _Clips(jobs, stagings, dirs, fmt)
    try:
        with signals_deferred(), child_environment({"LP_NUM_THREADS": "1"}):  # submitting spawns the workers
            futs = {pool.submit(_render_job, scen.model_dump_json(), c, str(stagings[j]), fmt, j): (j, c)
                    for j, (scen, _) in enumerate(jobs) for c in range(scen.rig.n_cameras)}
        pending = set(futs)
        while pending:
            finished, pending = cf.wait(pending, timeout=0.2, return_when=cf.FIRST_COMPLETED)
            _drain(q, clips.frames_done)
            for f in finished:
                j, c = futs[f]
                try:
                    count = f.result()
                except cf.process.BrokenProcessPool:
                    cam = jobs[j][0].rig.camera_names()[c]
                    raise StereotrackError(f"the render worker for the {cam} camera of {dirs[j]} died "
                                           "(killed, or out of memory)") from None
                clips.camera_done(j, c, count)
            clips.report(progress)
    except BaseException:
        end_pool(pool)
        raise
    pool.shutdown()
    return clips.finished()  # every clip finished (a failure raised above)


def _drain(q: mp.Queue, frames_done: dict[tuple[int, int], int]) -> None:
    """Take the workers' progress messages (job, camera, frames done) off the queue."""
    while True:
        try:
            j, c, k = q.get_nowait()
        except queue.Empty:
            return
        frames_done[(j, c)] = k


def render_clip(
    scenario: Scenario,
    clip_dir: str | Path,
    fmt: Format = "mp4",
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
) -> RenderResult:
    """Render ``scenario`` into ``clip_dir`` (see :func:`render_clips`): ``workers=2`` renders the
    two cameras in two processes, ``workers=1`` one after the other in this one."""
    return render_clips([(scenario, clip_dir)], fmt, min(workers, 2), progress)[0]
