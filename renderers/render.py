"""Render a scenario into one clip folder: videos or PNG frames, ``calib.yaml``,
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
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.calibration import save_calibration
from pipeline.core.camera import StereoRig
from pipeline.core.clip import CLIP_INFO, TIMESTAMPS
from pipeline.core.errors import StereotrackError
from pipeline.core.io import check_replaceable, write_json, write_text
from pipeline.core.outputs import OUT
from pipeline.core.rig import Rig
from pipeline.core.rigfiles import save_rig
from renderers.motion import Truth, simulate_truth
from renderers.scenario import CalibrationErrorSpec, Scenario, clip_description
from renderers.truth import frame_times, project_truth, write_target_truth, write_timestamps, write_truth
from renderers.writers import BackgroundWriter, Format, FrameWriter, SensorNoise, writer_threaded

CAMERA_NAMES = ("left", "right")
#: an N-camera clip's calibration (a stereo clip's is calib.yaml)
RIG_FILE = "rig.json"


@dataclass
class RenderResult:
    """What a render produced."""

    clip_dir: Path
    frames: int
    warnings: list[str]
    cameras: tuple[str, ...] = ("left", "right")


def render_camera(
    scenario: Scenario, cam_index: int, clip_dir: Path, fmt: Format, tick: Callable[[int], None] | None = None,
    renderer=None,  # a pyrender.OffscreenRenderer to reuse (a persistent worker's; any size)
    truth: Truth | None = None,
) -> np.ndarray | None:
    """Render every frame of one camera into ``clip_dir`` at that camera's own times (sync offset,
    jitter, rolling shutter, exposure), skipping the frames it drops. Returns, for scenes with
    objects that can hide a marker (distractors, occluders), each frame's visible pixel count per
    marker (frames × markers, from a segmentation render); else None."""
    from renderers.scene import StereoScene, create_offscreen_renderer, set_multisample

    rig = scenario.rig.build_any()
    truth = truth if truth is not None else simulate_truth(scenario)
    times = frame_times(scenario)
    scene = StereoScene(scenario, rig, truth)
    own = renderer is None
    if own:
        renderer = create_offscreen_renderer(*scene.views[cam_index].size)
    set_multisample(renderer, scenario.render.multisample)
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
    if not _RENDERER:
        _RENDERER.append(create_offscreen_renderer(scenario.rig.width, scenario.rig.height))

    def tick(k: int) -> None:
        if _PROGRESS is not None and (k % 5 == 4 or k == scenario.frames - 1):
            _PROGRESS.put((job, cam_index, k + 1))

    return render_camera(scenario, cam_index, Path(staging), fmt, tick, _RENDERER[0], simulate_truth(scenario))


def _staging_dir(clip_dir: Path) -> Path:
    """The name of a fresh hidden folder beside ``clip_dir`` for one attempt at rendering it
    (stale ones of killed attempts are removed); the caller makes it."""
    import uuid

    for stale in clip_dir.parent.glob(f".{clip_dir.name}.partial-*"):
        shutil.rmtree(stale, ignore_errors=True)
    return clip_dir.parent / f".{clip_dir.name}.partial-{uuid.uuid4().hex[:12]}"


#: The file that says a folder is a clip stereotrack rendered (its description, with the keys
#: :func:`_is_our_description` checks; never ``scenario.yaml``, which a user writes): only such a
#: folder, or an empty one, is ever re-rendered.
RENDERED_MARK = (CLIP_INFO,)
#: What a render puts in a clip folder; a re-render replaces exactly these (and the stale ``out/``).
RENDERED = ("calib.yaml", "calib_true.yaml", RIG_FILE, CLIP_INFO, "scenario.yaml", "truth.csv", "target_truth.csv",
            TIMESTAMPS, "left", "right", "left.mp4", "right.mp4", OUT)
#: A marker counts as visible when at least this share of its unoccluded image area shows.
VISIBLE_SHARE = 0.4


def _is_our_description(path: Path) -> bool:
    """Whether ``path`` is a clip description the renderer wrote (a JSON object with its fps, frame
    count and markers), not a user's file of the same name."""
    import json

    try:
        info = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(info, dict) and {"fps", "frames", "markers"} <= info.keys()


def _check_ours(clip_dir: Path) -> None:
    """Refuse, before any work, a folder that is neither new, empty nor a clip stereotrack rendered."""
    check_replaceable(clip_dir, RENDERED_MARK, "clip")
    info = clip_dir / CLIP_INFO
    if info.exists() and not _is_our_description(info):
        raise StereotrackError(f"{CLIP_INFO} here is not a clip description stereotrack wrote; choose an empty or "
                               "new folder for the clip", clip_dir)


def _rendered_cameras(clip_dir: Path) -> list[str]:
    """The camera files (``NAME.mp4``, ``NAME/``) an N-camera clip rendered here holds, by its clip.json."""
    import json

    try:
        names = json.loads((clip_dir / CLIP_INFO).read_text()).get("cameras") or []
    except (OSError, ValueError, AttributeError):
        return []
    return [f for n in names if isinstance(n, str) and n.replace("_", "").replace("-", "").isalnum()
            for f in (n, f"{n}.mp4")]


def _commit(staging: Path, clip_dir: Path) -> None:
    """Move a complete render into ``clip_dir``. A new folder is one rename; over an existing clip
    the old rendered files go first, calib.yaml first of all, and the new calib.yaml comes last,
    so an interrupted commit leaves a folder that is recognisably no clip (no calibration)."""
    if not clip_dir.exists():
        staging.rename(clip_dir)
        return
    for name in (*RENDERED, *_rendered_cameras(clip_dir)):
        p = clip_dir / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    for p in sorted(staging.iterdir(), key=lambda p: p.name in ("calib.yaml", RIG_FILE)):
        p.rename(clip_dir / p.name)
    staging.rmdir()


def _write_clip_files(scenario: Scenario, staging: Path, truth: Truth, fmt: Format,
                      counts: list[np.ndarray | None]) -> list[str]:
    """Truth, timestamps, scenario, description and calibration beside the frames (the user's
    calibration, perturbed when a calibration error is asked for, with the true one beside it);
    returns notes (markers never in view)."""
    rig = scenario.rig.build_any()
    names = scenario.rig.camera_names()
    proj = project_truth(rig, scenario, truth, distractors=all(c is None for c in counts))
    for c, cnt in enumerate(counts):
        if cnt is not None:  # the rendered image decides: occluded or cut by the frame ⇒ not visible
            proj.visible[:, :, c] &= cnt >= VISIBLE_SHARE * expected_areas(rig.cameras[c], truth, proj, c)
    notes = [f"marker '{name}' is never visible in {'either camera' if len(names) == 2 else 'any camera'}"
             for i, name in enumerate(truth.names) if not proj.visible[:, i, :].any()]
    info = clip_description(scenario)
    write_text(staging / "scenario.yaml", scenario.to_yaml())
    write_json(staging / CLIP_INFO, info)
    write_truth(staging / "truth.csv", truth, proj, names, {m["name"]: m["group"] for m in info["markers"]})
    write_timestamps(staging / TIMESTAMPS, proj.times, fmt, names)
    if isinstance(rig, Rig):  # N cameras: the rig file of its own format (no stereo calib.yaml)
        save_rig(rig, staging / RIG_FILE)
        return notes
    if truth.targets:
        write_target_truth(staging / "target_truth.csv", truth, proj)
    if scenario.calibration_error is not None:
        save_calibration(rig, staging / "calib_true.yaml")
        rig = perturbed_rig(rig, scenario.calibration_error, scenario.seed)
    save_calibration(rig, staging / "calib.yaml")
    return notes


def expected_areas(cam, truth: Truth, proj, c: int) -> np.ndarray:
    """Each marker's unoccluded image area (px², frames × markers): a sphere's disc, a flat disc
    foreshortened by its tilt."""
    n, m = truth.positions.shape[:2]
    out = np.zeros((n, m))
    f = float(np.sqrt(cam.K[0, 0] * cam.K[1, 1]))
    for i in range(m):
        p, _, nrm = truth.at(proj.t_seen[:, i, c], [i])
        p, nrm = p[:, 0], nrm[:, 0]
        z = np.maximum(cam.depth(p), 1e-6)
        area = np.pi * (f * truth.radii[i] / z) ** 2
        if np.all(np.isfinite(nrm)):
            ray = cam.center - p
            area *= np.abs(np.einsum("ij,ij->i", nrm, ray)) / np.linalg.norm(ray, axis=1)
        out[:, i] = area
    return out


def perturbed_rig(rig: StereoRig, err: CalibrationErrorSpec, seed: int) -> StereoRig:
    """The calibration a user would have: focal lengths, principal points, baseline length, the
    second camera's rotation and k1, k2 perturbed by the spec's standard deviations, drawn from
    ``[err.seed or seed, 50000]``."""
    from pipeline.core.camera import Camera

    rng = np.random.default_rng([err.seed if err.seed is not None else seed, 50_000])

    def camera_K(K: np.ndarray) -> np.ndarray:
        K = K.copy()
        K[0, 0] *= 1 + err.focal * rng.standard_normal()
        K[1, 1] *= 1 + err.focal * rng.standard_normal()
        K[:2, 2] += err.principal_point * rng.standard_normal(2)
        return K

    def dist(D: np.ndarray) -> np.ndarray:
        D = D.copy()
        D[:2] += err.distortion * rng.standard_normal(2)
        return D

    K1, K2, D1, D2 = camera_K(rig.left.K), camera_K(rig.right.K), dist(rig.left.D), dist(rig.right.D)
    rvec = np.radians(err.rotation_deg) * rng.standard_normal(3)
    R = cv2.Rodrigues(rvec)[0] @ rig.R
    C = rig.right.center * (1 + err.baseline * rng.standard_normal())
    return StereoRig(Camera(K1, D=D1), Camera(K2, R, -R @ C, D2), rig.image_size)


def _finish_clip(scenario: Scenario, staging: Path, clip_dir: Path, fmt: Format,
                 counts: list[np.ndarray | None]) -> RenderResult:
    """Write the truth and calibration of a clip whose frames are all in ``staging``, commit it,
    and warn about its notes."""
    notes = _write_clip_files(scenario, staging, simulate_truth(scenario), fmt, counts)
    _commit(staging, clip_dir)
    for msg in notes:
        warnings.warn(f"{clip_dir}: {msg}", stacklevel=3)
    return RenderResult(clip_dir, scenario.frames, notes, scenario.rig.camera_names())


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
        _check_ours(d)
        ensure_dir(d.parent)
    stagings: list[Path] = []
    try:  # an interrupt while the staging folders are being made leaves none of them behind
        for d in dirs:
            stagings.append(_staging_dir(d))  # named first, made after: the cleanup below sees each
            stagings[-1].mkdir(parents=True)
        if workers <= 1:
            return _render_here(jobs, stagings, dirs, fmt, progress)
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
    renderer = create_offscreen_renderer(jobs[0][0].rig.width, jobs[0][0].rig.height)
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
            results.append(_finish_clip(scen, stagings[j], dirs[j], fmt, counts))
    finally:
        renderer.delete()
    return results


def _render_pool(jobs: Sequence[tuple[Scenario, str | Path]], stagings: list[Path], dirs: list[Path], fmt: Format,
                 workers: int, progress: Callable[[int, int], None] | None) -> list[RenderResult]:
    """Every camera of every clip as a job of a pool of persistent render workers (one llvmpipe
    thread each, a user's own LP_NUM_THREADS aside); a clip is finished when both its cameras are."""
    import concurrent.futures as cf

    from pipeline.core.lifeline import child_environment, end_pool, signals_deferred

    total = sum(s.frames for s, _ in jobs)
    ctx = mp.get_context("spawn")
    q: mp.Queue = ctx.Queue()
    pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init,
                                  initargs=(os.getpid(), q))
    frames_done: dict[tuple[int, int], int] = {}
    counts: list[list] = [[None] * scen.rig.n_cameras for scen, _ in jobs]
    cams_done = [0] * len(jobs)
    results: list[RenderResult | None] = [None] * len(jobs)
    try:
        with signals_deferred(), child_environment({"LP_NUM_THREADS": "1"}):  # submitting spawns the workers
            futs = {pool.submit(_render_job, scen.model_dump_json(), c, str(stagings[j]), fmt, j): (j, c)
                    for j, (scen, _) in enumerate(jobs) for c in range(scen.rig.n_cameras)}
        pending = set(futs)
        while pending:
            finished, pending = cf.wait(pending, timeout=0.2, return_when=cf.FIRST_COMPLETED)
            _drain(q, frames_done)
            for f in finished:
                j, c = futs[f]
                try:
                    counts[j][c] = f.result()
                except cf.process.BrokenProcessPool:
                    cam = jobs[j][0].rig.camera_names()[c]
                    raise StereotrackError(f"the render worker for the {cam} camera of {dirs[j]} died "
                                           "(killed, or out of memory)") from None
                frames_done[(j, c)] = jobs[j][0].frames
                cams_done[j] += 1
                if cams_done[j] == jobs[j][0].rig.n_cameras:
                    results[j] = _finish_clip(jobs[j][0], stagings[j], dirs[j], fmt, counts[j])
            if progress is not None:
                progress(int(sum(k / jobs[jc[0]][0].rig.n_cameras for jc, k in frames_done.items())), total)
    except BaseException:
        end_pool(pool)
        raise
    pool.shutdown()
    return [r for r in results if r is not None]  # every clip finished (a failure raised above)


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
