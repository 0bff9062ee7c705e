"""Batch throughput: clips per minute for 1 and 2 local workers, each with and without per-clip
report figures (``--figures``; the default draws none, the leaderboard is always written), a
2-worker Dask LocalCluster, and a Dask scheduler with two worker processes of their own on
127.0.0.1 (``--scheduler-file``, the path users take to a real cluster), over the same folder of
clips, in one run. Each row is printed as it is measured.

    python benchmarks/batch.py [--clips 12] [--frames 60] [--against REV]

``--against REV`` also times the same batch with stereotrack as of git revision REV (a worktree
of this repository, run in a subprocess with its own code), interleaved with today's default at
the same worker counts: the "vs REV" column.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from _common import page, stack_tree

from pipeline.app.batch import run_batch
from pipeline.core.settings import RunSettings
from renderers.render import render_clips
from renderers.scenario import load_scenario

METHODS = ["triangulation", "kf3d", "ekf", "spsa", "alphabeta"]


@contextlib.contextmanager
def dask_processes(folder: Path, workers: int):
    """A ``dask scheduler`` and ``dask worker`` processes on 127.0.0.1; yields the scheduler file."""
    sched_file = folder / "scheduler.json"
    quiet = {"stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    procs = [subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1", "--port", "0",
                               "--no-dashboard", "--scheduler-file", str(sched_file)], **quiet)]
    try:
        while not sched_file.is_file():
            time.sleep(0.1)
        procs.append(subprocess.Popen([sys.executable, "-m", "dask", "worker", "--scheduler-file", str(sched_file),
                                       "--nworkers", str(workers), "--nthreads", "1", "--no-dashboard"], **quiet))
        yield sched_file
    finally:
        for p in reversed(procs):
            p.terminate()
            p.wait(timeout=30)


def batch_at(tree: Path, inp: Path, out: Path, workers: int) -> float:
    """Seconds the batch takes with the code in ``tree`` (its own interpreter, its own imports)."""
    shutil.rmtree(out, ignore_errors=True)
    # pipeline.app.batch since the folders were layers; pipeline.batch in older trees (looked for in
    # the tree's files: an import spec would find this checkout's pipeline.app through its editable install)
    module = "pipeline.app.batch" if (tree / "pipeline" / "app" / "batch.py").is_file() else "pipeline.batch"
    code = ("import sys, time, importlib; sys.path.insert(0, sys.argv[1]); "
            f"run_batch = importlib.import_module({module!r}).run_batch; t = time.perf_counter(); "
            f"r = run_batch(sys.argv[2], sys.argv[3], workers={workers}, methods={METHODS!r}); "
            "assert all(o.status == 'ok' for o in r), [o.error for o in r]; print(time.perf_counter() - t)")
    env = {**os.environ, "PYTHONPATH": str(tree)}
    res = subprocess.run([sys.executable, "-c", code, str(tree), str(inp), str(out)], capture_output=True, text=True,
                         env=env, cwd=tree)
    if res.returncode:
        raise SystemExit(f"the batch at {tree} failed:\n{res.stderr[-3000:]}")
    return float(res.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clips", type=int, default=12)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--against", default=None, help="a git revision to time the same batch with")
    args = ap.parse_args()
    print(f"# batch throughput ({args.clips} clips of {args.frames} frames, 640×480 MP4, 3 markers, methods "
          f"{', '.join(METHODS)}; {os.cpu_count()} cores)\n")
    print("| setup | clips/min | vs 1 worker (default) | default vs --figures, same workers |")
    print("|---|---|---|---|", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        inp = Path(tmp) / "in"
        base = load_scenario("multi_marker").with_overrides(frames=args.frames)
        render_clips([(base.with_overrides(seed=s), inp / f"clip{s}") for s in range(args.clips)], "mp4", 2)
        first, with_figures = None, {}
        setups = (("local, 1 worker, --figures", 1, None, True), ("local, 1 worker", 1, None, False),
                  ("local, 2 workers, --figures", 2, None, True), ("local, 2 workers", 2, None, False),
                  ("Dask LocalCluster, 2 workers (start-up included)", 2, "local", False),
                  ("Dask scheduler + 2 worker processes, --scheduler-file", 2, "file", False))
        if args.against:
            setups = (*setups[:4], (f"{args.against}, 1 worker", 1, "rev", False), ("local, 1 worker", 1, None, False),
                      (f"{args.against}, 2 workers", 2, "rev", False), ("local, 2 workers", 2, None, False),
                      *setups[4:])
            tree = stack_tree(Path(tmp), args.against)
        then: dict[int, float] = {}
        for label, workers, sched, figures in setups:
            out = Path(tmp) / "out"
            if sched == "rev":
                then[workers] = args.clips / batch_at(tree, inp, out, workers) * 60
                print(f"| {label} | {then[workers]:.1f} |  |  |", flush=True)
                continue
            shutil.rmtree(out, ignore_errors=True)
            with contextlib.ExitStack() as stack:
                sched_file = stack.enter_context(dask_processes(Path(tmp), workers)) if sched == "file" else None
                t0 = time.perf_counter()
                res = run_batch(inp, out, RunSettings(methods=METHODS, figures=figures), workers=workers,
                                scheduler=Path(sched_file) if sched == "file" else sched)
                dt = time.perf_counter() - t0
            assert all(o.status == "ok" for o in res), [o.error for o in res if o.status != "ok"]
            cpm = args.clips / dt * 60
            if figures:
                with_figures[workers] = cpm
            elif first is None:
                first = cpm
            vs_one = f"{cpm / first:.2f}×" if first else ""
            ratio = f"{cpm / with_figures[workers]:.2f}×" if not figures and sched is None else ""
            if not figures and sched is None and workers in then:
                ratio += f"; vs {args.against}: {cpm / then.pop(workers):.2f}×"
            print(f"| {label} | {cpm:.1f} | {vs_one} | {ratio} |", flush=True)


if __name__ == "__main__":
    page("batch", main)
