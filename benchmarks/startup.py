"""Start-up: wall time of commands that do little (``--help``, ``methods``, ``scenarios``) and of
the imports a batch worker pays (``import pipeline.app.run``), each the median of several fresh
interpreters, run interleaved.

    python benchmarks/startup.py [--repeat 7]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time

from _common import page

CASES = {
    "stereotrack --help": [sys.executable, "-m", "pipeline.app.cli", "--help"],
    "stereotrack methods": [sys.executable, "-m", "pipeline.app.cli", "methods"],
    "stereotrack scenarios": [sys.executable, "-m", "pipeline.app.cli", "scenarios"],
    "import pipeline.app.run (a batch worker's imports)": [sys.executable, "-c", "import pipeline.app.run"],
    "python alone": [sys.executable, "-c", "pass"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args()
    times: dict[str, list[float]] = {k: [] for k in CASES}
    for _ in range(args.repeat):
        for name, cmd in CASES.items():
            t0 = time.perf_counter()
            subprocess.run(cmd, capture_output=True, check=True)
            times[name].append(time.perf_counter() - t0)
    print(f"# start-up, seconds (median of {args.repeat} fresh interpreters, interleaved)\n")
    print("| command | seconds |")
    print("|---|---:|")
    for name, ts in times.items():
        print(f"| {name} | {statistics.median(ts):.2f} |")


if __name__ == "__main__":
    page("startup", main)
