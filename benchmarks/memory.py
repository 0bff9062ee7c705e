"""Peak memory of `stereotrack run` against clip length: the default scenario rendered at 640×480
with 150 and 1500 frames, each run in a fresh process (its VmHWM: the peak resident memory of the whole process; getrusage's
ru_maxrss would also count the RSS of the process that started it, which Linux carries across exec).
Every row is printed as it is measured.

    python benchmarks/memory.py [--frames 150 1500] [--out DIR]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from _common import page

from renderers.render import render_clip
from renderers.scenario import load_scenario

CODE = ("import sys\nfrom pipeline.cli import main\nsys.argv = ['stereotrack', *sys.argv[1:]]\n"
        "try:\n    main()\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
        "print('PEAK', next(int(ln.split()[1]) for ln in open('/proc/self/status') if ln.startswith('VmHWM')))")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, nargs="+", default=[150, 1500])
    ap.add_argument("--out", type=Path, default=None, help="where the clips go (default: a temporary folder)")
    args = ap.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="stereotrack-memory-"))
    print("| frames (640×480, stereo) | `stereotrack run` peak RSS (MB) | run time (s) | run.rrd (MB) |")
    print("|---|---|---|---|", flush=True)
    peaks: list[float] = []
    for n in args.frames:
        clip = root / f"default_{n}"
        if not (clip / "calib.yaml").is_file():
            render_clip(load_scenario("default").with_overrides(frames=n), clip)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", CODE, "run", str(clip)], capture_output=True, text=True)
        if proc.returncode:
            sys.exit(proc.stdout + proc.stderr)
        peak = int(proc.stdout.rsplit("PEAK", 1)[1]) / 1024
        rrd = (clip / "out" / "run.rrd").stat().st_size / 2**20
        print(f"| {n} | {peak:.0f} | {time.perf_counter() - t0:.1f} | {rrd:.1f} |", flush=True)
        peaks.append(peak)
    if len(peaks) > 1:
        print(f"\nPeak at {args.frames[-1]} frames over the peak at {args.frames[0]}: {peaks[-1] / peaks[0]:.2f}× "
              f"({(peaks[-1] - peaks[0]) / (args.frames[-1] - args.frames[0]) * 1024:.0f} kB per frame).")


if __name__ == "__main__":
    page("memory", main)
