"""Start-up: wall time of commands that do little (``--help``, ``methods``, ``scenarios``) and of
the imports a batch worker pays (``import pipeline.app.run``), each the median of several fresh
interpreters run interleaved, as a ratio to ``python -c "import numpy"`` timed in the same rounds.
``--against REV`` times the same commands on the code of git revision REV too.

Bytecode caching is on, as in a user's Python (this benchmark unsets ``PYTHONDONTWRITEBYTECODE``
and runs every command once before timing, so no round pays for compiling sources).

    python benchmarks/startup.py [--repeat 9] [--against REV]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import page, stack_tree

NUMPY = "python -c 'import numpy'"


def cli(args: str, tree: Path | None = None) -> list[str]:
    """The ``stereotrack`` command ``args``, run from ``tree`` (a checkout) or from this one."""
    prefix = f"import sys; sys.path.insert(0, {str(tree)!r}); " if tree else "import sys; "
    code = f"{prefix}sys.argv = ['stereotrack', *{args.split()!r}]; from pipeline.app.cli import main; main()"
    return [sys.executable, "-c", code]


def cases(tree: Path | None, rev: str) -> dict[str, list[str]]:
    """Command label → argv, today's first, then (with a tree) the same at ``rev``."""
    base = {NUMPY: [sys.executable, "-c", "import numpy"], "python alone": [sys.executable, "-c", "pass"]}
    ours = {f"stereotrack {a}": cli(a) for a in ("--help", "methods", "scenarios")}
    ours["import pipeline.app.run (a batch worker's imports)"] = [sys.executable, "-c", "import pipeline.app.run"]
    if tree is not None:
        ours |= {f"stereotrack {a} at {rev}": cli(a, tree) for a in ("--help", "methods", "scenarios")}
    return base | ours


def measure(todo: dict[str, list[str]], repeat: int) -> dict[str, float]:
    """Median wall seconds of each command over ``repeat`` interleaved rounds (after one warm-up)."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    times: dict[str, list[float]] = {k: [] for k in todo}
    for r in range(repeat + 1):
        for name, cmd in todo.items():
            t0 = time.perf_counter()
            subprocess.run(cmd, capture_output=True, check=True, env=env)
            if r:
                times[name].append(time.perf_counter() - t0)
    return {k: statistics.median(v) for k, v in times.items()}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--against", default=None, help="a git revision to time beside today's code")
    args = ap.parse_args()
    tree = stack_tree(Path(tempfile.mkdtemp(prefix="stereotrack-startup-")), args.against) if args.against else None
    med = measure(cases(tree, args.against or ""), args.repeat)
    print(f"# start-up (median of {args.repeat} fresh interpreters, interleaved, bytecode cached)\n")
    print(f"| command | seconds | × `{NUMPY}` |")
    print("|---|---:|---:|")
    for name, t in med.items():
        print(f"| {name} | {t:.3f} | {t / med[NUMPY]:.2f} |")


if __name__ == "__main__":
    page("startup", main)
