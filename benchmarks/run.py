"""The main job as a user waits for it: ``stereotrack run`` on the built-in default scenario from
nothing (render, detect, estimate, report, recording) and ``stereotrack run CLIP`` on the clip it
rendered (every stage but rendering), each in a fresh process, interleaved, with the machine's load
beside them. The README and the getting-started page quote this page only.

    python benchmarks/run.py [--repeat 3] [--out DIR | --write-docs]
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import page


def timed(cmd: list[str], cwd: Path) -> float:
    """Wall seconds of one command (fresh interpreter), which must succeed."""
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=cwd, capture_output=True, check=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="(accepted for symmetry; this page has no figures)")
    args = ap.parse_args()
    exe = [sys.executable, "-m", "pipeline.app.cli", "run"]
    fresh, again, load = [], [], []
    with tempfile.TemporaryDirectory(prefix="stereotrack-run-") as tmp:
        for _ in range(args.repeat):
            shutil.rmtree(Path(tmp) / "runs", ignore_errors=True)
            load.append(os.getloadavg()[0])
            fresh.append(timed(exe, Path(tmp)))  # renders runs/default, then every stage
            shutil.rmtree(Path(tmp) / "runs" / "default" / "out")
            again.append(timed([*exe, "runs/default"], Path(tmp)))
    print(f"# `stereotrack run`, seconds ({args.repeat} fresh processes each, interleaved)\n")
    print(f"{os.cpu_count()} cores; 1-minute load average before each pair: "
          f"{', '.join(f'{v:.1f}' for v in load)}.\n")
    print("| command | median | range |")
    print("|---|---:|---:|")
    for name, ts in (("`stereotrack run` (render the default scenario, then every stage)", fresh),
                     ("`stereotrack run runs/default` (the rendered clip: every stage but rendering)", again)):
        print(f"| {name} | {statistics.median(ts):.1f} | {min(ts):.1f}–{max(ts):.1f} |")


if __name__ == "__main__":
    page("run", main)
