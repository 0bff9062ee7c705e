"""Batch processing of clip folders: a local process pool by default, a Dask cluster when asked.

Kill-safe by construction: each attempt at a clip writes into its own ``OUT/.<name>.partial-<id>``
folder, writes ``manifest.json`` (sizes and checksums of every output, version, settings) last, and
is swapped into ``OUT/<name>`` only then; a rerun verifies manifests and redoes anything that does
not verify (``force`` redoes everything). Workers die with the batch (:mod:`pipeline.core.lifeline`),
one batch at a time holds the output folder's lock, and one failing clip is recorded with its
error and never stops the others.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import multiprocessing as mp
import os
import shutil
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.app.manifest import verify_manifest, write_manifest
from pipeline.core.calibration import has_calibration
from pipeline.core.errors import StereotrackError, first_line
from pipeline.core.interrupts import raise_if_interrupted
from pipeline.core.io import check_replaceable, ensure_dir, write_json
from pipeline.core.lifeline import OutputLock, die_with_parent, ignore_sigint, still_parented
from pipeline.core.outputs import DETECT_INFO, ESTIMATES, FIGURES, MANIFEST, OUT, Outputs, partial_folder
from pipeline.core.rigfiles import find_rig
from pipeline.core.settings import RunHooks, RunSettings
from pipeline.present.summary import ClipOutcome, write_summary


def find_clips(input_dir: str | Path, skip: Path | None = None) -> list[Path]:
    """Clip folders under ``input_dir``: folders holding a calibration (a stereo calib.yaml, or an
    N-camera rig file) or left/right footage. A
    clip's own sub-folders are its own (frames, outputs), never further clips; ``skip`` (the batch's
    output folder, when it lies inside the input) is not searched."""
    input_dir = Path(input_dir)
    if not input_dir.is_dir():
        raise StereotrackError("no such input folder", input_dir)
    clips = []
    for top, dirs, files in os.walk(input_dir):
        d = Path(top)
        dirs[:] = sorted(n for n in dirs if not n.startswith(".") and n not in (OUT, "left", "right", ESTIMATES, FIGURES)
                         and (skip is None or (d / n).resolve() != skip))
        has_left = any(n.startswith("left") for n in (*files, *dirs))
        if has_calibration(d) or find_rig(d) is not None or (has_left and any(n.startswith("right")
                                                                                for n in (*files, *dirs))):
            clips.append(d)
            dirs[:] = []
    return sorted(clips)


def clip_key(clip: Path, input_dir: Path) -> str:
    """A clip's name in a batch: its path relative to the input folder (``a/clip``), so that two
    clips of one name in different sub-folders never share an output folder."""
    rel = clip.relative_to(input_dir).as_posix()
    return input_dir.resolve().name if rel == "." else rel


#: where a pool worker sends (clip, stage) as it goes (set by :func:`_worker_init`)
_STAGES: Any = None


def _worker_init(parent_pid: int, single_thread: bool, stages: Any = None) -> None:
    """Pool-worker initializer: die with the batch process; leave Ctrl-C to it (the batch ends its
    workers itself); one OpenCV thread per worker when several workers share the cores; send
    each clip's stages to the batch through ``stages`` (a multiprocessing queue)."""
    global _STAGES
    _STAGES = stages
    die_with_parent(parent_pid)
    ignore_sigint()
    if single_thread:
        import cv2

        cv2.setNumThreads(1)


ATTEMPT = ".attempt.json"
#: Files that only stereotrack writes into a clip's output folder: a folder holding none of them
#: (and not empty) is someone else's and is never replaced, ``--force`` included.
OURS = (MANIFEST, DETECT_INFO)


def _attempt_info() -> dict[str, Any]:
    """Where this attempt runs: the Dask worker's address, or this process."""
    import socket

    info: dict[str, Any] = {"pid": os.getpid(), "host": socket.gethostname()}
    try:
        from distributed import get_worker

        info["worker"] = get_worker().address
    except (ImportError, ValueError):
        info["worker"] = f"pid {os.getpid()} on {info['host']}"
    return info


def _process_one(clip: str, key: str, out_root: str, job: BatchJob, parent_pid: int | None = None) -> ClipOutcome:
    """Process one clip into a temporary folder unique to this attempt, write its manifest last,
    and swap it into ``OUT/<key>``. Runs in a pool worker (``parent_pid``: the batch process; a
    worker whose batch has died never commits) or on a Dask worker."""
    import uuid
    import warnings

    from detectors.markers import resolve_marker_specs
    from pipeline.app.run import process_clip
    from pipeline.core.clip import input_files

    clip_p, final = Path(clip), Path(out_root) / key
    partial = partial_folder(final, uuid.uuid4().hex[:12])
    try:
        check_replaceable(final, OURS, "clip's outputs")
        ensure_dir(partial)
        write_json(partial / ATTEMPT, _attempt_info())
        inputs = input_files(clip_p)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            specs = resolve_marker_specs(clip_p, _listed(job.settings.markers), job.root_markers)
            settings = job.settings.model_copy(update={"markers": tuple(specs) if specs else None})
            process_clip(clip_p, partial, settings, RunHooks(stage=lambda name: _stage(key, name)), lock=False,
                         keep_tracks=False)
        (partial / ATTEMPT).unlink()
        write_manifest(partial, job.record, inputs)
        if parent_pid is not None and not still_parented(parent_pid):
            shutil.rmtree(partial, ignore_errors=True)
            os._exit(1)  # the batch is gone: never commit for a batch that no longer exists
        _swap_in(partial, final)
        notes = sorted({str(w.message) for w in caught})
        return ClipOutcome(key, "ok", json.loads(Outputs(final).metrics.read_text()), warnings=notes)
    except StereotrackError as exc:
        shutil.rmtree(partial, ignore_errors=True)
        return ClipOutcome(key, "failed", error=str(exc))
    except Exception as exc:
        shutil.rmtree(partial, ignore_errors=True)
        last = traceback.extract_tb(exc.__traceback__)[-1]
        return ClipOutcome(key, "failed", error=f"{type(exc).__name__}: {exc} ({Path(last.filename).name}:{last.lineno})")


def _stage(key: str, name: str) -> None:
    """Tell the batch which stage a clip is in (pool workers; a Dask run reports clips only)."""
    if _STAGES is not None:
        try:
            _STAGES.put_nowait((key, name))
        except Exception:  # a full or closed queue never stops a clip
            pass


def _swap_in(partial: Path, final: Path) -> None:
    """Replace ``final`` by the complete ``partial`` folder with two renames (the old one is moved
    aside first, then deleted), so ``final`` is at every moment either the old or the new output."""
    import uuid

    raise_if_interrupted()  # nothing is committed once a signal came
    old = None
    if final.exists():
        old = final.with_name(f".{final.name}.old-{uuid.uuid4().hex[:12]}")
        final.rename(old)
    partial.rename(final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


@dataclass(frozen=True)
class BatchJob:
    """What every clip of a batch runs with: the run's settings, the input folder's own
    ``markers.yaml`` (for clips without markers of their own) and what the manifest records."""

    settings: RunSettings
    root_markers: list[str] | None
    record: dict[str, Any]


def run_batch(input_dir: str | Path, output_dir: str | Path, settings: RunSettings | None = None, workers: int = 2,
              scheduler: str | Path | None = None, force: bool = False,
              progress: Callable[[int, int], None] | None = None,
              on_stage: Callable[[str, str], None] | None = None) -> list[ClipOutcome]:
    """Process every clip under ``input_dir`` with ``settings``; write ``summary.csv`` and ``summary.md``.

    Each clip's outputs go to ``OUT/<its path under input_dir>`` (``in/a/clip`` → ``OUT/a/clip``).
    A batch leaves the report's figures out unless ``settings.figures`` (``--figures``); the
    summary's leaderboard is always written. Markers: ``settings.markers`` apply to every clip;
    else a clip's own ``markers.yaml``; else ``INPUT/markers.yaml``; else a rendered clip's
    description (clip.json).

    ``scheduler``: None for a local process pool of ``workers`` processes; ``"local"`` for a Dask
    ``LocalCluster`` of ``workers`` processes; a ``tcp://host:port`` address (a string), or a Dask
    scheduler file (a :class:`~pathlib.Path`), for an existing Dask scheduler, whose workers must see ``input_dir`` and
    ``output_dir`` at the same paths. ``on_stage`` gets (clip, stage) as local workers go.

    The output folder is locked for the whole batch (a second batch on it fails at once, naming
    the holder). A clip counts as done only if its manifest verifies, was made with the same
    settings and from the same inputs; anything else (including leftovers of a killed batch) is
    redone, with a warning saying why when it had complete outputs.
    """
    input_dir, out_root = Path(input_dir), Path(output_dir)
    job = batch_job(input_dir, settings or RunSettings(figures=False))
    clips = find_clips(input_dir, skip=out_root.resolve())
    if not clips:
        raise StereotrackError("no clip folders here (a clip holds left/right videos or frame folders and a calibration)",
                               input_dir)
    keys = {c: clip_key(c, input_dir) for c in clips}
    ensure_dir(out_root)
    with OutputLock(out_root, f"stereotrack batch {input_dir}"):
        _remove_leftovers(out_root)
        outcomes = {keys[c]: o for c in clips if not force and (o := _complete(keys[c], out_root / keys[c], job.record, c))}
        todo = [c for c in clips if keys[c] not in outcomes]
        record = _Counter(outcomes, len(clips), progress, on_stage).record
        try:
            if todo and scheduler is not None:
                _run_dask(todo, keys, out_root, job, workers, scheduler, record)
            elif todo:
                _run_local(todo, keys, out_root, job, workers, record, on_stage)
        finally:
            dead = _remove_leftovers(out_root)  # attempts whose worker died, and anything an interrupt left
        _count_dead_attempts(outcomes, dead)
        ordered = [outcomes[keys[c]] for c in clips]
        write_summary(out_root, ordered)
    return ordered


def batch_job(input_dir: Path, settings: RunSettings) -> BatchJob:
    """What every clip runs with, checked before any work starts (the detector against the
    registry, the input folder's ``markers.yaml`` read); the manifest records it, and a clip made
    with other settings is redone."""
    from detectors import check_detector
    from detectors.markers import read_markers_file
    from pipeline.core.clip import MARKERS_FILE

    check_detector(settings.detector)
    root_markers = read_markers_file(input_dir / MARKERS_FILE) if (input_dir / MARKERS_FILE).is_file() else None
    return BatchJob(settings, root_markers, settings.record(root_markers))


def _listed(v: tuple[str, ...] | None) -> list[str] | None:
    return list(v) if v else None


def _count_dead_attempts(outcomes: dict[str, ClipOutcome], dead: list[tuple[str, str]]) -> None:
    """Every attempt counts: those whose worker died, and the one that finished."""
    for key, worker in dead:
        if key in outcomes:
            o = outcomes[key]
            o.attempts += 1
            o.warnings.append(f"{key}: the worker running an attempt at it ({worker}) died")


class _Counter:
    """Clips done: each outcome recorded, told to the progress callback and to ``on_stage``."""

    def __init__(self, outcomes: dict[str, ClipOutcome], total: int, progress: Callable[[int, int], None] | None,
                 on_stage: Callable[[str, str], None] | None) -> None:
        self.outcomes, self.total, self.progress, self.on_stage = outcomes, total, progress, on_stage
        if progress is not None:
            progress(len(outcomes), total)

    def record(self, o: ClipOutcome) -> None:
        self.outcomes[o.clip] = o
        if self.on_stage is not None:
            self.on_stage(o.clip, "done")
        if self.progress is not None:
            self.progress(len(self.outcomes), self.total)


def _complete(key: str, final: Path, settings: dict, clip: Path) -> ClipOutcome | None:
    """The outcome of a clip whose outputs are complete and current, else None (redo it), with a
    warning saying why when outputs were there but no longer count."""
    import warnings

    from pipeline.core.clip import input_files

    if not final.is_dir():
        return None
    why = verify_manifest(final, settings, input_files(clip))
    if why is None:
        try:
            return ClipOutcome(key, "skipped", json.loads(Outputs(final).metrics.read_text()))
        except (OSError, ValueError):
            why = "unreadable metrics.json"
    if why != "no manifest":
        warnings.warn(f"{final}: redoing this clip: {why}", stacklevel=3)
    return None


def _remove_leftovers(out_root: Path) -> list[tuple[str, str]]:
    """Remove the temporary folders of attempts that did not finish (``.X.partial-*``, ``.X.old-*``)
    anywhere under the output folder; returns (clip, worker) for each attempt that had started."""
    dead = []
    for stale in sorted([*out_root.rglob(".*.partial-*"), *out_root.rglob(".*.old-*")]):
        if stale.is_dir() and ".partial-" in stale.name:
            key = (stale.parent / stale.name[1:].rsplit(".partial-", 1)[0]).relative_to(out_root).as_posix()
            try:
                worker = str(json.loads((stale / ATTEMPT).read_text()).get("worker", "?"))
            except (OSError, ValueError, AttributeError):  # killed before it wrote its record: an attempt all the same
                worker = "?"
            dead.append((key, worker))
        shutil.rmtree(stale, ignore_errors=True) if stale.is_dir() else stale.unlink(missing_ok=True)
    return dead


def _drain(stages: Any, on_stage: Callable[[str, str], None] | None) -> None:
    """Hand every (clip, stage) the workers have sent to ``on_stage``."""
    import queue

    while stages is not None and on_stage is not None:
        try:
            on_stage(*stages.get_nowait())
        except queue.Empty:
            return


def _run_local(todo: list[Path], keys: dict[Path, str], out_root: Path, job: BatchJob, workers: int,
               record: Callable[[ClipOutcome], None], on_stage: Callable[[str, str], None] | None = None) -> None:
    """A spawn-context process pool whose workers die with this process, and are ended at once
    when the batch is interrupted (Ctrl-C, SIGTERM) instead of finishing their clips."""
    from concurrent.futures.process import BrokenProcessPool

    from pipeline.core.interrupts import signals_deferred
    from pipeline.core.lifeline import child_environment, end_pool

    ctx = mp.get_context("spawn")
    stages = ctx.Queue() if on_stage is not None else None
    pool = cf.ProcessPoolExecutor(max_workers=max(1, workers), mp_context=ctx, initializer=_worker_init,
                                  initargs=(os.getpid(), workers > 1, stages))
    try:
        with signals_deferred(), child_environment():  # submitting spawns the workers
            futs = {pool.submit(_process_one, str(c), keys[c], str(out_root), job, os.getpid()): keys[c]
                    for c in todo}
        pending = set(futs)
        while pending:
            finished, pending = cf.wait(pending, timeout=0.25, return_when=cf.FIRST_COMPLETED)
            _drain(stages, on_stage)
            for f in finished:
                try:
                    record(f.result())
                except BrokenProcessPool:
                    record(ClipOutcome(futs[f], "failed", error="its worker process died (killed, or out of memory)",
                                       attempts=0))
    except BaseException:
        end_pool(pool)
        raise
    pool.shutdown()
    if stages is not None:
        stages.close()


def _run_dask(todo: list[Path], keys: dict[Path, str], out_root: Path, job: BatchJob, workers: int,
              scheduler: str | Path, record: Callable[[ClipOutcome], None]) -> None:
    """On a Dask LocalCluster (``scheduler == "local"``) or an existing scheduler (an address or a
    scheduler file)."""
    from dask.distributed import as_completed

    cluster, client = _dask_client(workers, scheduler)
    try:
        with client:
            futs = {client.submit(_process_one, str(c), keys[c], str(out_root), job, pure=False): keys[c]
                    for c in todo}
            try:
                for f in as_completed(futs):
                    try:
                        o = f.result()
                    except Exception as exc:  # a worker died too often, or the cluster lost the task
                        o = ClipOutcome(futs[f], "failed", error=f"Dask: {type(exc).__name__}: {first_line(exc)}",
                                        attempts=0)
                    record(o)
            except BaseException:
                client.cancel(list(futs), force=True)
                raise
    finally:
        if cluster is not None:
            cluster.close()


def _dask_client(workers: int, scheduler: str | Path):
    """(LocalCluster or None, Client); an unreachable or unreadable scheduler is one error."""
    import logging

    from dask.distributed import Client, LocalCluster

    from pipeline.core.lifeline import child_environment

    with child_environment():
        cluster = LocalCluster(n_workers=max(1, workers), threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.WARNING) if scheduler == "local" else None
    scheduler_file = scheduler if isinstance(scheduler, Path) else None  # a path: a scheduler file
    where = scheduler
    # Dask's own setting (DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT) wins; 10 s otherwise
    timeout = os.environ.get("DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT", "10s")
    try:
        if cluster is not None:
            return cluster, Client(cluster, timeout=timeout)
        if scheduler_file is not None:
            return None, Client(scheduler_file=str(_checked_scheduler_file(scheduler_file)), timeout=timeout)
        return None, Client(scheduler, timeout=timeout)
    except (OSError, TimeoutError, ValueError) as exc:
        if cluster is not None:
            cluster.close()
        raise StereotrackError(f"cannot reach the Dask scheduler at {where} ({first_line(exc)})") from None


def _checked_scheduler_file(path: Path) -> Path:
    """A Dask scheduler file: JSON holding the scheduler's ``address``; else one error naming it."""
    if not path.is_file():
        raise StereotrackError("no such Dask scheduler file", path)
    try:
        data = json.loads(path.read_bytes())
    except (OSError, ValueError):
        raise StereotrackError("not a Dask scheduler file (not JSON; written by `dask scheduler --scheduler-file`)",
                               path) from None
    if not isinstance(data, dict) or not isinstance(data.get("address"), str) or "://" not in data["address"]:
        raise StereotrackError("not a Dask scheduler file (no scheduler 'address')", path)
    return path
