"""Batch throughput: clips per minute for 1 and 2 local workers and for a 2-worker Dask
LocalCluster over the same folder of clips, in one run.

    python benchmarks/batch.py [--clips 12] [--frames 60]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from pipeline.batch import run_batch
from renderers.render import render_clip
from renderers.scenario import load_scenario

METHODS = ["triangulation", "kf3d", "ekf", "spsa", "alphabeta"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--clips", type=int, default=12)
    ap.add_argument("--frames", type=int, default=60)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        inp = Path(tmp) / "in"
        base = load_scenario("multi_marker").with_overrides(frames=args.frames)
        for s in range(args.clips):
            render_clip(base.with_overrides(seed=s), inp / f"clip{s}", fmt="mp4")
        rows = []
        for label, workers, sched in (("local, 1 worker", 1, None), ("local, 2 workers", 2, None),
                                      ("Dask LocalCluster, 2 workers", 2, "local")):
            out = Path(tmp) / "out"
            shutil.rmtree(out, ignore_errors=True)
            t0 = time.perf_counter()
            res = run_batch(inp, out, workers=workers, scheduler=sched, methods=METHODS)
            dt = time.perf_counter() - t0
            assert all(o.status == "ok" for o in res), [o.error for o in res if o.status != "ok"]
            rows.append((label, args.clips / dt * 60))
    print(f"# batch throughput ({args.clips} clips of {args.frames} frames, 640×480 MP4, 3 markers, methods "
          f"{', '.join(METHODS)}; {os.cpu_count()} cores)\n")
    print("| setup | clips/min | vs 1 worker |")
    print("|---|---|---|")
    for label, cpm in rows:
        print(f"| {label} | {cpm:.1f} | {cpm / rows[0][1]:.2f}× |")


if __name__ == "__main__":
    main()
