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
from pipeline.errors import ClipError, RenderBackendError, StereotrackError
from pipeline.io import write_text
from renderers.motion import Truth, simulate_truth
from renderers.scenario import Scenario
from renderers.truth import ProjectedTruth, project_truth, write_target_truth, write_truth

CAMERA_NAMES = ("left", "right")
Format = Literal["mp4", "png"]


@dataclass
class RenderResult:
    """What a render produced."""

    clip_dir: Path
    frames: int
    truth: Truth
    projected: ProjectedTruth
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
    scenario: Scenario, cam_index: int, clip_dir: Path, fmt: Format, tick: Callable[[int], None] | None = None
) -> int:
    """Render every frame of one camera into ``clip_dir``; returns the number of frames."""
    from renderers.scene import StereoScene, create_offscreen_renderer

    rig = scenario.rig.build()
    truth = simulate_truth(scenario)
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
        renderer.delete()
    return scenario.frames


def _worker(scenario_json: str, cam_index: int, clip_dir: str, fmt: Format, q: mp.Queue) -> None:
    """Process entry point: renders one camera, reports progress and errors through ``q``."""
    try:
        scenario = Scenario.model_validate_json(scenario_json)

        def tick(k: int) -> None:
            if k % 5 == 4 or k == scenario.frames - 1:
                q.put(("progress", cam_index, k + 1))

        render_camera(scenario, cam_index, Path(clip_dir), fmt, tick)
        q.put(("done", cam_index, None))
    except StereotrackError as exc:
        q.put(("error", cam_index, (type(exc).__name__, str(exc))))
    except BaseException as exc:
        q.put(("error", cam_index, ("StereotrackError", f"{type(exc).__name__}: {exc}")))


def render_clip(
    scenario: Scenario,
    clip_dir: str | Path,
    fmt: Format = "mp4",
    workers: int = 2,
    progress: Callable[[int, int], None] | None = None,
) -> RenderResult:
    """Render ``scenario`` into ``clip_dir``.

    ``progress(done, total)`` is called with stereo frame pairs completed. ``workers=2`` renders
    the two cameras in two processes; ``workers=1`` renders them one after the other here.
    """
    clip_dir = Path(clip_dir)
    clip_dir.mkdir(parents=True, exist_ok=True)
    rig = scenario.rig.build()
    truth = simulate_truth(scenario)
    proj = project_truth(rig, scenario, truth)
    notes = []
    for i, name in enumerate(truth.names):
        if not proj.visible[:, i, :].any():
            msg = f"marker '{name}' is never visible in either camera"
            notes.append(msg)
            warnings.warn(msg, stacklevel=2)

    total = scenario.frames
    if workers <= 1:
        done = [0, 0]
        for c in range(2):

            def tick(k: int, c: int = c) -> None:
                done[c] = k + 1
                if progress is not None:
                    progress((done[0] + done[1]) // 2, total)

            render_camera(scenario, c, clip_dir, fmt, tick)
    else:
        _render_parallel(scenario, clip_dir, fmt, progress)

    save_calibration(rig, clip_dir / "calib.yaml")
    write_text(clip_dir / "scenario.yaml", scenario.to_yaml())
    write_truth(clip_dir / "truth.csv", truth, proj)
    if truth.targets:
        write_target_truth(clip_dir / "target_truth.csv", truth, proj)
    return RenderResult(clip_dir, total, truth, proj, notes)


def _render_parallel(scenario: Scenario, clip_dir: Path, fmt: Format, progress: Callable[[int, int], None] | None) -> None:
    ctx = mp.get_context("spawn")
    # one camera per process and core: Mesa's llvmpipe would otherwise start a thread per core in
    # each process and the two would fight over the same cores (a user's own setting wins)
    saved = os.environ.get("LP_NUM_THREADS")
    os.environ["LP_NUM_THREADS"] = saved or "1"
    q: mp.Queue = ctx.Queue()
    payload = scenario.model_dump_json()
    procs = [ctx.Process(target=_worker, args=(payload, c, str(clip_dir), fmt, q), daemon=True) for c in range(2)]
    try:
        for p in procs:
            p.start()
    finally:
        if saved is None:
            del os.environ["LP_NUM_THREADS"]
    done, finished, error = [0, 0], set(), None
    try:
        while len(finished) < 2 and error is None:
            try:
                kind, cam, payload_ = q.get(timeout=0.5)
            except queue.Empty:
                dead = [c for c, p in enumerate(procs) if not p.is_alive() and c not in finished]
                if dead and q.empty():
                    error = ("StereotrackError", f"render worker for the {CAMERA_NAMES[dead[0]]} camera died "
                             f"(exit code {procs[dead[0]].exitcode})")
                continue
            if kind == "progress":
                done[cam] = payload_
                if progress is not None:
                    progress(min(done), scenario.frames)
            elif kind == "done":
                finished.add(cam)
                done[cam] = scenario.frames
                if progress is not None:
                    progress(min(done), scenario.frames)
            else:
                error = payload_
    finally:
        for p in procs:
            if error is not None and p.is_alive():
                p.terminate()
            p.join(timeout=10)
    if error is not None:
        cls = RenderBackendError if error[0] == "RenderBackendError" else StereotrackError
        raise cls(error[1])

