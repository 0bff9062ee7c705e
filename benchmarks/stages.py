"""Each stage of ``stereotrack run`` as a user waits for it on a rendered clip: ``detect``,
``estimate`` (the default methods) and ``report``, each the whole command in a fresh process, the
three interleaved, beside the detect stage (the issue's yardstick: estimate and report no slower
than detect) and, with ``--against REV``, beside the same commands on the code of revision REV.

    python benchmarks/stages.py [--repeat 3] [--frames 150] [--against REV] [--write-docs]
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

from _common import page, stack_tree

STAGES = ("detect", "estimate", "report")


def command(stage: str, clip: Path, tree: Path | None) -> list[str]:
    """``stereotrack STAGE CLIP`` in a fresh interpreter, on this checkout's code or ``tree``'s."""
    prefix = f"import sys; sys.path.insert(0, {str(tree)!r}); " if tree else "import sys; "
    code = f"{prefix}sys.argv = ['stereotrack', {stage!r}, {str(clip)!r}]; from pipeline.app.cli import main; main()"
    return [sys.executable, "-c", code]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--frames", type=int, default=150, help="frames of the default scenario to render")
    ap.add_argument("--against", default=None, help="a git revision to time beside today's code")
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="stereotrack-stages-"))
    try:
        clip = tmp / "clip"
        subprocess.run([sys.executable, "-m", "pipeline.app.cli", "render", "default", "-o", str(clip), "--frames",
                        str(args.frames)], check=True, capture_output=True)
        tree = stack_tree(Path(tempfile.mkdtemp(prefix="stereotrack-stages-then-")), args.against) if args.against else None
        trees = {"": None, **({f" at {args.against}": tree} if tree else {})}
        env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
        times: dict[str, list[float]] = {f"{s}{label}": [] for label in trees for s in STAGES}
        load = []
        for r in range(args.repeat + 1):  # round 0 warms the caches (bytecode, compiled cores) and is not counted
            load.append(os.getloadavg()[0])
            for label, code in trees.items():
                for stage in STAGES:  # in order: each stage reads what the one before it wrote
                    t0 = time.perf_counter()
                    subprocess.run(command(stage, clip, code), check=True, capture_output=True, env=env)
                    if r:
                        times[f"{stage}{label}"].append(time.perf_counter() - t0)
        med = {k: statistics.median(v) for k, v in times.items()}
        print(f"# Stages of `stereotrack run` on the rendered default scenario ({args.frames} frames)\n")
        print(f"Whole commands in fresh processes, median of {args.repeat} interleaved rounds after one warm-up; "
              f"1-minute load before each round: {', '.join(f'{v:.1f}' for v in load)}.\n")
        print("| command | seconds (median) | range | × detect |")
        print("|---|---:|---:|---:|")
        for label in trees:
            for stage in STAGES:
                ts = times[f"{stage}{label}"]
                print(f"| `stereotrack {stage}`{label} | {med[stage + label]:.2f} | {min(ts):.2f}–{max(ts):.2f} | "
                      f"{med[stage + label] / med['detect' + label]:.2f} |")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    page("stages", main)
