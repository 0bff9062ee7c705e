"""The ``stereotrack`` commands over many clips and recordings: ``view``, ``batch``, ``render-batch``."""

import sys
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer
from rich.table import Table

from pipeline.app.cli_common import (
    METHODS_HELP,
    AllowUnequalOption,
    CalibUnitsOption,
    ConfigOption,
    DetectorOption,
    FpsOption,
    MarkersOption,
    TimeOffsetOption,
    app,
    clip_format,
    marker_specs,
    method_configs,
    method_list,
    out,
    progress_bar,
)
from pipeline.core.errors import StereotrackError
from pipeline.core.outputs import RECORDING, Outputs

if TYPE_CHECKING:
    from rich.progress import Progress, TaskID


@app.command("view")
def view_cmd(
    folder: Annotated[Path, typer.Argument(
        help="A clip folder (its out/run.rrd), an output folder holding run.rrd, a batch output folder (every "
        "clip's recording), or a .rrd file.")],
    web: Annotated[bool, typer.Option("--web", help="Serve rerun's web viewer on 127.0.0.1 and print its URL "
                                      "(over SSH: forward both ports).")] = False,
    port: Annotated[int, typer.Option(help="The web viewer's HTTP port (--web); the data port is the next one.")] = 9090,
) -> None:
    """Open recordings in the rerun viewer that stereotrack's rerun-sdk installs (or print the command)."""
    import os
    import subprocess

    rrds = _recordings(folder)
    viewer = _viewer()
    if viewer is None:
        raise StereotrackError("the rerun viewer is not installed next to this Python nor on PATH "
                               "(pip install rerun-sdk installs it)")
    if web:
        url = f"http://127.0.0.1:{port}/?url=rerun%2Bhttp://127.0.0.1:{port + 1}/proxy"
        out.print(f"serving {len(rrds)} recording(s) at {url}\n(over SSH: ssh -L {port}:127.0.0.1:{port} "
                  f"-L {port + 1}:127.0.0.1:{port + 1} HOST; Ctrl-C stops)", highlight=False, soft_wrap=True)
        cmd = [viewer, "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(port), "--port", str(port + 1)]
    elif not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        out.print(f"no display here: run `stereotrack view {folder} --web`, or on a machine with one:\n  "
                  f"rerun {' '.join(map(str, rrds))}", highlight=False)
        return
    else:
        cmd = [viewer]
    from functools import partial

    from pipeline.core.lifeline import terminate_with_parent

    rc = subprocess.run([*cmd, *map(str, rrds)], check=False,
                        preexec_fn=partial(terminate_with_parent, os.getpid())).returncode
    if rc:
        raise typer.Exit(rc)


def _recordings(folder: Path) -> list[Path]:
    """The recordings ``view`` opens: a .rrd file; a folder's run.rrd or out/run.rrd; else every
    clip's run.rrd under a batch output folder."""
    if folder.suffix == ".rrd" and folder.is_file():
        return [folder]
    for p in (Outputs(folder).recording, Outputs.of(folder).recording):
        if p.is_file():
            return [p]
    batch = sorted(p for p in folder.rglob(RECORDING) if not any(part.startswith(".") for part in p.relative_to(folder).parts)) \
        if folder.is_dir() else []
    if batch:
        return batch
    raise StereotrackError("no recording here (a .rrd file, run.rrd, out/run.rrd, or a batch output folder of "
                           "clips with run.rrd): `stereotrack run` or `stereotrack batch` writes them", folder)


def _viewer() -> str | None:
    """The rerun viewer that stereotrack's rerun-sdk installs (its binary, run directly, so that it
    can be ended with stereotrack), else the ``rerun`` beside this Python, else the one on PATH."""
    import shutil

    try:
        import rerun_cli

        binary = Path(rerun_cli.__file__).with_name("rerun")
        if binary.is_file():
            return str(binary)
    except ImportError:
        pass
    beside = Path(sys.executable).with_name("rerun")
    return str(beside) if beside.is_file() else shutil.which("rerun")


@app.command("batch")
def batch_cmd(
    input_dir: Annotated[Path, typer.Argument(help="Folder whose sub-folders are clips.")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Output folder (one sub-folder per clip).")],
    workers: Annotated[int, typer.Option(help="Worker processes.")] = 2,
    scheduler: Annotated[str | None, typer.Option(help="Dask scheduler address tcp://host:port (workers must see "
                                                  "INPUT_DIR and the output at the same paths).")] = None,
    scheduler_file: Annotated[Path | None, typer.Option("--scheduler-file",
                                                        help="Dask scheduler file (dask scheduler --scheduler-file).")] = None,
    dask: Annotated[str | None, typer.Option("--dask", help="'local' runs a Dask LocalCluster here.")] = None,
    force: Annotated[bool, typer.Option("--force", help="Redo clips whose outputs are complete.")] = False,
    detector: DetectorOption = "blob",
    methods: Annotated[str | None, typer.Option(help=METHODS_HELP)] = None,
    markers: MarkersOption = None,
    calib_units: CalibUnitsOption = None,
    config: ConfigOption = None,
    no_images: Annotated[bool, typer.Option("--no-images", help="Leave the frames out of each clip's recording.")] = False,
    time_offset: TimeOffsetOption = "auto",
    fps: FpsOption = None,
    figures: Annotated[bool, typer.Option("--figures", help="Draw each clip's report figures (the summary's "
                                          "leaderboard is always written).")] = False,
    allow_unequal: AllowUnequalOption = False,
) -> None:
    """Process every clip folder under INPUT_DIR; exit code 1 if any clip failed.

    Markers: --markers for every clip, else each clip's markers.yaml, else INPUT_DIR/markers.yaml,
    else the colours of a rendered clip (clip.json)."""
    from pipeline.app.batch import run_batch
    from pipeline.core.settings import RunSettings

    settings = RunSettings.checked(detector=detector, methods=method_list(methods), markers=marker_specs(markers),
                                   calib_units=calib_units, configs=method_configs(config), images=not no_images,
                                   time_offset=time_offset, fps=fps, figures=figures, allow_unequal=allow_unequal)
    if dask is not None and dask != "local":
        raise StereotrackError("--dask takes 'local'; use --scheduler tcp://host:port for a running cluster")
    if workers < 1:
        raise StereotrackError(f"--workers must be at least 1, not {workers}")
    sched = scheduler or scheduler_file or dask
    with progress_bar() as bar:
        task = bar.add_task("clips", total=None)
        outcomes = run_batch(input_dir, output, settings, workers, sched, force,
                             progress=lambda d, t: bar.update(task, completed=d, total=t), on_stage=_ClipStages(bar))
    _print_batch(outcomes, output)
    if any(o.status == "failed" for o in outcomes):
        raise typer.Exit(1)


class _ClipStages:
    """One progress line per clip in flight, saying its stage; removed when the clip is done."""

    def __init__(self, bar: "Progress") -> None:
        self.bar = bar
        self.tasks: dict[str, TaskID] = {}

    def __call__(self, clip: str, stage: str) -> None:
        if stage == "done":
            if clip in self.tasks:
                self.bar.remove_task(self.tasks.pop(clip))
        elif clip not in self.tasks:
            self.tasks[clip] = self.bar.add_task(f"  {clip}: {stage}", total=None, count=False, eta=False)
        else:
            self.bar.update(self.tasks[clip], description=f"  {clip}: {stage}")


def _print_batch(outcomes: list, output: Path) -> None:
    """The per-method leaderboard, the clips that failed or warned, and where the summary is."""
    from pipeline.present.summary import clip_warnings, method_rows

    rows = method_rows(outcomes)
    table = Table(title=f"{len(outcomes)} clips: 3-D RMSE (mm) of each method, best first",
                  caption="vs best: paired, same clips · away: runaways · more in summary.html")
    for col in ("method", "clips", "mean ±95%", "vs best ±95%", "away", "failed"):  # fits 80 columns
        table.add_column(col, justify="left" if col == "method" else "right", no_wrap=True)
    for r in rows:  # best first
        table.add_row(r["method"], str(r["clips"]), _plus_minus(r["mean_rmse_m"], r["mean_ci_low_m"], r["mean_ci_high_m"]),
                      _plus_minus(r["paired_diff_m"], r["paired_diff_ci_low_m"], r["paired_diff_ci_high_m"], "+.2f"),
                      str(r["runaways"]), str(r["failures"]))
    out.print(table)
    bad = [o for o in outcomes if o.status == "failed" or clip_warnings(o)]
    if bad:
        clips = Table("clip", "status", "attempts", "warnings", "error", title="clips that failed or warned")
        for o in bad:
            clips.add_row(o.clip, o.status, str(o.attempts), str(len(clip_warnings(o))), o.error)
        out.print(clips)
    n_ok = sum(o.status != "failed" for o in outcomes)
    out.print(f"{n_ok} of {len(outcomes)} clips done; summary: {output / 'summary.html'} (and summary.md, "
              f"summary.csv)", highlight=False)
    if any(Outputs(output / o.clip).recording.is_file() for o in outcomes if o.status != "failed"):
        out.print(f"replay every clip: stereotrack view {output}", highlight=False, soft_wrap=True)


def _plus_minus(mean: float | None, lo: float, hi: float, spec: str = ".2f") -> str:
    """``mean ± half-width`` in mm (the interval's larger half, as a clipped interval is uneven)."""
    import math

    if mean is None or not math.isfinite(mean):
        return "—"
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return f"{1000 * mean:{spec}}"
    return f"{1000 * mean:{spec}} ± {1000 * max(hi - mean, mean - lo):.2f}"


@app.command("render-batch")
def render_batch_cmd(
    scenario: Annotated[str, typer.Argument(help="Scenario YAML or built-in name.")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Folder to fill with one clip per seed.")],
    seeds: Annotated[str, typer.Option(help="Seeds as A..B (inclusive) or a comma list.")] = "0..3",
    frames: Annotated[int | None, typer.Option(help="Override the scenario's frame count.")] = None,
    fmt: Annotated[str, typer.Option("--format", help="mp4 or png.")] = "mp4",
    workers: Annotated[int, typer.Option(help="Clips (cameras) rendered at once: threads, or pyrender processes that "
                                              "keep their GL context across clips.")] = 2,
) -> None:
    """Render a folder of clips of one scenario, one per seed: on threads where the analytic rasteriser draws
    it, else with persistent pyrender workers."""
    from renderers.render import render_clips
    from renderers.scenario import load_scenario

    try:
        if ".." in seeds:
            a, b = seeds.split("..")
            seed_list = list(range(int(a), int(b) + 1))
        else:
            seed_list = [int(s) for s in seeds.split(",")]
    except ValueError:
        raise StereotrackError(f"--seeds must be A..B or a comma list, not {seeds!r}") from None
    fmt = clip_format(fmt)
    base = load_scenario(scenario)
    jobs = []
    for s in seed_list:
        scen = base.with_overrides(frames=frames, seed=s)
        jobs.append((scen, output / f"{scen.name}_seed{s}"))
    with progress_bar() as bar:
        task = bar.add_task(f"render {len(jobs)} clips", total=sum(j[0].frames for j in jobs))
        render_clips(jobs, fmt, max(1, workers), lambda d, t: bar.update(task, completed=d))
    out.print(f"wrote {len(seed_list)} clips to {output}")
