"""Render a scenario into one clip folder (SPEC §3): videos or PNG frames, ``calib.yaml``,
``scenario.yaml``, ``truth.csv`` and, for the four-point target, ``target_truth.csv``.

Like Kubric's workers: one seeded job renders one scene into one folder with all its ground
truth. Each camera is rendered by its own process (one ``OffscreenRenderer`` reused for all
frames), so a stereo clip uses both cores of a small machine.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import shutil
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from pipeline.camera import save_calibration
from pipeline.clip import CLIP_INFO
from pipeline.errors import ClipError, StereotrackError
from pipeline.io import write_json, write_text
from renderers.motion import Truth, simulate_truth
from renderers.scenario import Scenario, clip_description
from renderers.truth import project_truth, write_target_truth, write_truth

CAMERA_NAMES = ("left", "right")
Format = Literal["mp4", "png"]


@dataclass
class RenderResult:
    """What a render produced."""

    clip_dir: Path
    frames: int
    warnings: list[str]


class SensorNoise:
    """Additive Gaussian sensor noise (σ in grey levels), seeded per clip and camera.

    Drawing a fresh normal deviate per pixel per frame costs more than rendering the frame, so a
    bank of eight noise fields slightly larger than the image is drawn once and each frame takes
    one of them at a random offset (both chosen from ``default_rng([seed, camera, frame])``):
    still white in space, independent enough in time for tracking, and the same bits every run.
    """

    MARGIN = 64

    def __init__(self, shape: tuple[int, int, int], sigma: float, seed: int, camera: int, bank: int = 8) -> None:
        self.shape, self.sigma, self.seed, self.camera = shape, sigma, seed, camera
        if sigma > 0:
            h, w, c = shape
            self.bank = np.empty((bank, h + self.MARGIN, w + self.MARGIN, c), np.int16)
            for i in range(bank):  # OpenCV's generator is several times faster than numpy's here
                cv2.setRNGSeed(int(np.random.SeedSequence([seed, 30_000 + camera, i]).generate_state(1)[0]) & 0x7FFFFFFF)
                cv2.randn(self.bank[i], (0.0,) * c, (float(sigma),) * c)  # per channel

    def apply(self, img: np.ndarray, frame: int) -> np.ndarray:
        if self.sigma <= 0:
            return img
        rng = np.random.default_rng([self.seed, 20_000 + self.camera, frame])
        i, dy, dx = rng.integers(len(self.bank)), *rng.integers(0, self.MARGIN, 2)
        h, w, _ = self.shape
        return cv2.add(img, self.bank[i, dy : dy + h, dx : dx + w], dtype=cv2.CV_8U)


def postprocess(img: np.ndarray, blur_sigma: float, noise: SensorNoise, frame: int) -> np.ndarray:
    """Optical blur (Gaussian, σ in px), then sensor noise."""
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    return noise.apply(img, frame)


class FrameWriter:
    """Writes one camera's frames to ``<name>.mp4`` or a ``<name>/`` folder of PNGs, atomically:
    into a hidden partial file/folder first, moved into place by :meth:`close`."""

    def __init__(self, clip_dir: Path, name: str, fmt: Format, fps: float, size: tuple[int, int]) -> None:
        self.final = clip_dir / (f"{name}.mp4" if fmt == "mp4" else name)
        self.fmt = fmt
        self.tmp = clip_dir / f".{name}.partial{'.mp4' if fmt == 'mp4' else ''}"
        if self.tmp.is_dir():
            shutil.rmtree(self.tmp)
        self.count = 0
        if fmt == "mp4":
            self.writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter_fourcc(*"mp4v"), fps, size)
            if not self.writer.isOpened():
                raise ClipError("OpenCV cannot open an MP4 writer (mp4v); use --format png", self.final)
        else:
            self.tmp.mkdir(parents=True)

    def write(self, rgb: np.ndarray) -> None:
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        if self.fmt == "mp4":
            self.writer.write(bgr)
        else:
            cv2.imwrite(str(self.tmp / f"{self.count:06d}.png"), bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        self.count += 1

    def close(self) -> None:
        if self.fmt == "mp4":
            self.writer.release()
            self.tmp.replace(self.final)
        else:
            if self.final.is_dir():
                shutil.rmtree(self.final)
            self.tmp.rename(self.final)

    def abort(self) -> None:
        if self.fmt == "mp4":
            self.writer.release()
            self.tmp.unlink(missing_ok=True)
        elif self.tmp.is_dir():
            shutil.rmtree(self.tmp, ignore_errors=True)


def render_camera(
    scenario: Scenario, cam_index: int, clip_dir: Path, fmt: Format, tick: Callable[[int], None] | None = None,
    renderer=None,  # a pyrender.OffscreenRenderer of the rig's size to reuse (a persistent worker's)
    truth: Truth | None = None,
) -> int:
    """Render every frame of one camera into ``clip_dir``; returns the number of frames."""
    from renderers.scene import StereoScene, create_offscreen_renderer

    rig = scenario.rig.build()
    truth = truth if truth is not None else simulate_truth(scenario)
    own = renderer is None
    if own:
        renderer = create_offscreen_renderer(*rig.image_size)
    try:
        scene = StereoScene(scenario, rig, truth)
        writer = FrameWriter(clip_dir, CAMERA_NAMES[cam_index], fmt, scenario.fps, rig.image_size)
        try:
            rs = scenario.render
            w, h = rig.image_size
            noise = SensorNoise((h, w, 3), rs.noise_std, scenario.seed, cam_index)
            for k in range(scenario.frames):
                scene.set_frame(k)
                img = scene.render(renderer, cam_index)
                writer.write(postprocess(img, rs.blur_sigma, noise, k))
                if tick is not None:
                    tick(k)
            writer.close()
        except BaseException:
            writer.abort()
            raise
    finally:
        if own:
            renderer.delete()
    return scenario.frames


# -- persistent render workers ------------------------------------------------------------------
# Each worker process keeps its EGL context(s) — one OffscreenRenderer per image size — across
# every camera of every clip it renders, so a batch of clips pays the start-up (imports, context)
# once per worker instead of once per camera per clip.

_RENDERERS: dict[tuple[int, int], object] = {}
_PROGRESS: mp.Queue | None = None


def _worker_init(parent_pid: int, progress: mp.Queue | None) -> None:
    """Die with the parent; one OpenCV thread (blur, encoding) per worker, as llvmpipe has one."""
    from pipeline.lifeline import die_with_parent, ignore_sigint

    die_with_parent(parent_pid)
    ignore_sigint()
    cv2.setNumThreads(1)
    global _PROGRESS
    _PROGRESS = progress


def _render_job(scenario_json: str, cam_index: int, staging: str, fmt: Format, job: int) -> list[str]:
    """Worker entry point: one camera of one clip into ``staging``, reusing this process's renderer;
    the left camera's job also writes the clip's truth and calibration (the parent only commits)."""
    from renderers.scene import create_offscreen_renderer

    scenario = Scenario.model_validate_json(scenario_json)
    size = (scenario.rig.width, scenario.rig.height)
    if size not in _RENDERERS:
        _RENDERERS[size] = create_offscreen_renderer(*size)

    def tick(k: int) -> None:
        if _PROGRESS is not None and (k % 5 == 4 or k == scenario.frames - 1):
            _PROGRESS.put((job, cam_index, k + 1))

    truth = simulate_truth(scenario)
    render_camera(scenario, cam_index, Path(staging), fmt, tick, _RENDERERS[size], truth)
    return _write_clip_files(scenario, Path(staging), truth) if cam_index == 0 else []


def _staging_dir(clip_dir: Path) -> Path:
    """A fresh hidden folder beside ``clip_dir`` for one attempt at rendering it (stale ones of
    killed attempts are removed)."""
    import uuid

    for stale in clip_dir.parent.glob(f".{clip_dir.name}.partial-*"):
        shutil.rmtree(stale, ignore_errors=True)
    staging = clip_dir.parent / f".{clip_dir.name}.partial-{uuid.uuid4().hex[:12]}"
    staging.mkdir(parents=True)
    return staging


#: The files that say a folder is a clip stereotrack rendered (clips made before clip.json have
#: scenario.yaml): only such a folder, or an empty one, is ever re-rendered.
RENDERED_MARK = (CLIP_INFO, "scenario.yaml")
#: What a render puts in a clip folder; a re-render replaces exactly these (and the stale ``out/``).
RENDERED = ("calib.yaml", CLIP_INFO, "scenario.yaml", "truth.csv", "target_truth.csv", "left", "right", "left.mp4",
            "right.mp4", "out")


def _commit(staging: Path, clip_dir: Path) -> None:
    """Move a complete render into ``clip_dir``. A new folder is one rename; over an existing clip
    the old rendered files go first, calib.yaml first of all, and the new calib.yaml comes last,
    so an interrupted commit leaves a folder that is recognisably no clip (no calibration)."""
    if not clip_dir.exists():
        staging.rename(clip_dir)
        return
    for name in RENDERED:
        p = clip_dir / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    for p in sorted(staging.iterdir(), key=lambda p: p.name == "calib.yaml"):
        p.rename(clip_dir / p.name)
    staging.rmdir()


def _write_clip_files(scenario: Scenario, staging: Path, truth: Truth) -> list[str]:
    """Truth, scenario and calibration beside the frames; returns notes (markers never in view)."""
    rig = scenario.rig.build()
    proj = project_truth(rig, scenario, truth)
    notes = [f"marker '{name}' is never visible in either camera" for i, name in enumerate(truth.names)
             if not proj.visible[:, i, :].any()]
    write_text(staging / "scenario.yaml", scenario.to_yaml())
    write_json(staging / CLIP_INFO, clip_description(scenario))
    write_truth(staging / "truth.csv", truth, proj)
    if truth.targets:
        write_target_truth(staging / "target_truth.csv", truth, proj)
    save_calibration(rig, staging / "calib.yaml")
    return notes


def _finish_clip(scenario: Scenario, staging: Path, clip_dir: Path, notes: list[str]) -> RenderResult:
    """Commit a clip whose frames and truth are all in ``staging``; warn about its notes."""
    _commit(staging, clip_dir)
    for msg in notes:
        warnings.warn(f"{clip_dir}: {msg}", stacklevel=3)
    return RenderResult(clip_dir, scenario.frames, notes)


def render_clips(
    jobs: list[tuple[Scenario, str | Path]],
    fmt: Format = "mp4",
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
) -> list[RenderResult]:
    """Render several clips (scenario, folder) with ``workers`` persistent processes.

    Every camera of every clip is one job; a worker keeps its EGL context across jobs. Each clip
    is rendered into a hidden staging folder and committed only when both cameras and its truth
    are written; workers die with this process. ``progress(done, total)`` counts stereo pairs.
    ``workers=1`` renders here, in this process, one camera after the other.
    """
    import concurrent.futures as cf

    from pipeline.io import check_replaceable, ensure_dir

    total = sum(s.frames for s, _ in jobs)
    dirs = [Path(d) for _, d in jobs]
    for d in dirs:  # before any work: a folder stereotrack did not render is never replaced
        check_replaceable(d, RENDERED_MARK, "clip")
        ensure_dir(d.parent)
    stagings = [_staging_dir(d) for d in dirs]
    results: list[RenderResult | None] = [None] * len(jobs)
    try:
        if workers <= 1:
            from renderers.scene import create_offscreen_renderer

            renderers: dict[tuple[int, int], object] = {}
            done = 0
            try:
                for j, (scen, _) in enumerate(jobs):
                    size = (scen.rig.width, scen.rig.height)
                    if size not in renderers:
                        renderers[size] = create_offscreen_renderer(*size)
                    truth = simulate_truth(scen)
                    for c in range(2):

                        def tick(k: int, c: int = c, base: int = done, n: int = scen.frames) -> None:
                            if progress is not None:
                                progress(base + (k + 1 + c * n) // 2, total)

                        render_camera(scen, c, stagings[j], fmt, tick, renderers[size], truth)
                    done += scen.frames
                    results[j] = _finish_clip(scen, stagings[j], dirs[j], _write_clip_files(scen, stagings[j], truth))
            finally:
                for r in renderers.values():
                    r.delete()  # type: ignore[attr-defined]
            return results  # type: ignore[return-value]
        ctx = mp.get_context("spawn")
        q: mp.Queue = ctx.Queue()
        # one llvmpipe thread per worker: each worker is one core's worth of rendering (a user's
        # own LP_NUM_THREADS wins)
        saved = os.environ.get("LP_NUM_THREADS")
        os.environ["LP_NUM_THREADS"] = saved or "1"
        try:
            pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init,
                                          initargs=(os.getpid(), q))
        finally:
            if saved is None:
                del os.environ["LP_NUM_THREADS"]
        frames_done: dict[tuple[int, int], int] = {}
        cams_done = [0] * len(jobs)
        notes: list[list[str]] = [[] for _ in jobs]
        try:
            futs = {pool.submit(_render_job, scen.model_dump_json(), c, str(stagings[j]), fmt, j): (j, c)
                    for j, (scen, _) in enumerate(jobs) for c in range(2)}
            pending = set(futs)
            while pending:
                finished, pending = cf.wait(pending, timeout=0.2, return_when=cf.FIRST_COMPLETED)
                while True:
                    try:
                        j, c, k = q.get_nowait()
                    except queue.Empty:
                        break
                    frames_done[(j, c)] = k
                for f in finished:
                    j, c = futs[f]
                    try:
                        notes[j] += f.result()
                    except cf.process.BrokenProcessPool:
                        raise StereotrackError(f"the render worker for the {CAMERA_NAMES[c]} camera of {dirs[j]} died "
                                               "(killed, or out of memory)") from None
                    frames_done[(j, c)] = jobs[j][0].frames
                    cams_done[j] += 1
                    if cams_done[j] == 2:
                        results[j] = _finish_clip(jobs[j][0], stagings[j], dirs[j], notes[j])
                if progress is not None:
                    progress(sum(frames_done.values()) // 2, total)
        except BaseException:
            from pipeline.lifeline import end_pool

            end_pool(pool)
            raise
        pool.shutdown()
        return results  # type: ignore[return-value]
    except BaseException:
        for st in stagings:
            shutil.rmtree(st, ignore_errors=True)
        raise


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
