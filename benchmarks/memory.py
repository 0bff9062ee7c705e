"""Peak memory of `stereotrack run` against clip length: the default scenario rendered at 640×480
with 150 and 1500 frames, each run in a fresh process (its VmHWM: the peak resident memory of the whole process; getrusage's
ru_maxrss would also count the RSS of the process that started it, which Linux carries across exec), and the largest
peak of the worker processes it forked (their ``RUSAGE_CHILDREN`` maximum).
Every row is printed as it is measured.

With two or more lengths, the shortest and the longest are then run once more stage by stage
(the peak reset at each stage through ``/proc/self/clear_refs``), as ``run`` streams each
method's tracks (``process_clip(keep_tracks=False)``) and keeping every track (the baseline).

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

CODE = ("import sys\nfrom pipeline.app.cli import main\nsys.argv = ['stereotrack', *sys.argv[1:]]\n"
        "try:\n    main()\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
        "import resource\n"
        "print('WORKER', resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
        "print('PEAK', next(int(ln.split()[1]) for ln in open('/proc/self/status') if ln.startswith('VmHWM')))")


#: ``process_clip`` on argv[1] in a fresh process, keeping every track when argv[2] is "keep": the
#: peak of each stage (VmHWM, reset as the stage starts) and the peak of the whole run, in kB
STAGES = """import sys
from pipeline.app.run import process_clip
from pipeline.core.settings import RunHooks
def kb(key):
    return next(int(ln.split()[1]) for ln in open('/proc/self/status') if ln.startswith(key))
peaks, last = [], ['start']
def stage(name):
    peaks.append((last[0].split(' (')[0], kb('VmHWM')))
    top[0] = max(top[0], kb('VmHWM'))
    open('/proc/self/clear_refs', 'w').write('5')
    last[0] = name
top = [0]
process_clip(sys.argv[1], sys.argv[1] + '/out_stages', hooks=RunHooks(stage=stage), keep_tracks=sys.argv[2] == 'keep')
stage('end')
for name, peak in peaks[1:]:
    print('STAGE', name, peak)
print('PEAK', top[0])
"""


def stage_peaks(clip: Path, keep: bool) -> tuple[dict[str, float], float]:
    """Each stage's peak and the run's peak (MB) of ``process_clip`` on ``clip``."""
    proc = subprocess.run([sys.executable, "-c", STAGES, str(clip), "keep" if keep else "stream"],
                          capture_output=True, text=True)
    if proc.returncode:
        sys.exit(proc.stdout + proc.stderr)
    lines = [ln.split() for ln in proc.stdout.splitlines()]
    stages: dict[str, float] = {}
    for f in (f for f in lines if f and f[0] == "STAGE"):  # a stage announced twice ("estimate"): its higher peak
        stages[" ".join(f[1:-1])] = max(stages.get(" ".join(f[1:-1]), 0.0), int(f[-1]) / 1024)
    return stages, next(int(f[1]) for f in lines if f and f[0] == "PEAK") / 1024


def stage_table(clips: dict[int, Path]) -> None:
    """Per stage, the peak at the shortest and the longest length, streaming and keeping every track."""
    (n0, c0), (n1, c1) = min(clips.items()), max(clips.items())
    runs = {(keep, n): stage_peaks(c, keep) for keep in (False, True) for n, c in ((n0, c0), (n1, c1))}
    print(f"\n| stage (peak MB, `process_clip`) | streaming, {n0} | streaming, {n1} | keeping every track, {n0} "
          f"| keeping every track, {n1} |\n|---|---|---|---|---|")
    for name in runs[False, n0][0]:
        cells = [f"{runs[k, n][0].get(name, float('nan')):.0f}" for k in (False, True) for n in (n0, n1)]
        print(f"| {name} | {' | '.join(cells)} |")
    whole = {k: runs[k, n1][1] / runs[k, n0][1] for k in (False, True)}
    print(f"| whole run | {' | '.join(f'{runs[k, n][1]:.0f}' for k in (False, True) for n in (n0, n1))} |")
    print(f"\nPeak at {n1} frames over the peak at {n0}, `process_clip`: {whole[False]:.2f}× streaming each method's "
          f"tracks, {whole[True]:.2f}× keeping every track.")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, nargs="+", default=[150, 1500])
    ap.add_argument("--out", type=Path, default=None, help="where the clips go (default: a temporary folder)")
    args = ap.parse_args()
    root = args.out or Path(tempfile.mkdtemp(prefix="stereotrack-memory-"))
    print("| frames (640×480, stereo) | `stereotrack run` peak RSS (MB) | largest worker's peak RSS (MB) | run time (s) "
          "| run.rrd (MB) |")
    print("|---|---|---|---|---|", flush=True)
    peaks: list[float] = []
    clips: dict[int, Path] = {}
    for n in args.frames:
        clip = root / f"default_{n}"
        if not (clip / "calib.yaml").is_file():
            render_clip(load_scenario("default").with_overrides(frames=n), clip)
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-c", CODE, "run", str(clip)], capture_output=True, text=True)
        if proc.returncode:
            sys.exit(proc.stdout + proc.stderr)
        peak = int(proc.stdout.rsplit("PEAK", 1)[1]) / 1024
        worker = int(proc.stdout.rsplit("WORKER", 1)[1].split()[0]) / 1024
        rrd = (clip / "out" / "run.rrd").stat().st_size / 2**20
        print(f"| {n} | {peak:.0f} | {worker:.0f} | {time.perf_counter() - t0:.1f} | {rrd:.1f} |", flush=True)
        peaks.append(peak)
        clips[n] = clip
    if len(peaks) > 1:
        print(f"\nPeak at {args.frames[-1]} frames over the peak at {args.frames[0]}: {peaks[-1] / peaks[0]:.2f}× "
              f"({(peaks[-1] - peaks[0]) / (args.frames[-1] - args.frames[0]) * 1024:.0f} kB per frame). The estimate "
              "stage's methods run in worker processes forked from the command (`--workers`, "
              "2 by default): most of a worker's resident memory is pages it shares with the command, copied only "
              "where one of them writes; `process_clip` below runs in one process.", flush=True)
        stage_table(clips)


if __name__ == "__main__":
    page("memory", main)
