"""The ``stereotrack`` command line (typer + rich). I/O and presentation only: every command calls
the library functions the tests call."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path
from typing import Annotated, Literal

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from pipeline.core.errors import StereotrackError, first_line
from pipeline.core.outputs import RECORDING, Outputs

app = typer.Typer(
    help="Track objects in stereo video: render synthetic clips, detect markers, estimate 3-D tracks.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
console = Console(stderr=True)
out = Console()


def _version(value: bool) -> None:
    if value:
        from pipeline.core.version import stereotrack_version

        out.print(f"stereotrack {stereotrack_version()}")
        raise typer.Exit()


@app.callback()
def _main(version: Annotated[bool, typer.Option("--version", callback=_version, is_eager=True,
                                                help="Print the version and exit.")] = False) -> None:
    """Track objects in stereo video: render synthetic clips, detect markers, estimate 3-D tracks."""


def progress_bar() -> Progress:
    """The one progress-bar style of every long command."""
    return Progress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),
        console=console,
        transient=False,
    )


@app.command("scenarios")
def scenarios_cmd() -> None:
    """List the built-in scenarios."""
    from renderers.scenario import builtin_scenarios, load_scenario

    table = Table("name", "frames", "fps", "markers", "description")
    for name in builtin_scenarios():
        s = load_scenario(name)
        table.add_row(name, str(s.frames), f"{s.fps:g}", ", ".join(s.marker_names()), s.description)
    out.print(table)


@app.command("methods")
def methods_cmd(
    names: Annotated[list[str] | None, typer.Argument(
        help="Methods whose settings to list (the keys of a --config file), with defaults and what each does.")] = None,
) -> None:
    """List every estimator and detector (built-in and plugins), or the settings of the methods named."""
    from detectors import registry as detectors
    from pipeline.estimators import registry

    if names:
        return _print_settings(names, registry())
    table = Table("method", "kind", "description", title="estimators (--methods, --config)")
    for name, cls in registry().items():
        table.add_row(name, cls.kind, cls.description())
    out.print(table)
    found = Table("detector", "description", title="detectors (--detector)")
    for name, det in detectors().items():
        found.add_row(name, (det.__doc__ or "").strip().splitlines()[0])
    out.print(found)
    out.print("settings of a method: stereotrack methods NAME", highlight=False)


def _print_settings(names: list[str], reg: dict) -> None:
    """Each named method's settings: the key, its default and what it does."""
    unknown = [n for n in names if n not in reg]
    if unknown:
        raise StereotrackError(f"unknown method(s) {', '.join(unknown)} (known: {', '.join(reg)})")
    for name in names:
        fields = reg[name].Config.model_fields
        table = Table(title=f"{name} (a --config file's '{name}:' section)")
        table.add_column("setting", no_wrap=True, min_width=max(len(k) for k in fields))  # a key is never cut
        table.add_column("default", overflow="fold")
        table.add_column("what it does", overflow="fold")
        for key, field in fields.items():
            default = field.get_default(call_default_factory=True)
            shown = default.model_dump() if hasattr(default, "model_dump") else default
            table.add_row(key, escape(str(shown)), escape(" ".join((field.description or "").replace("``", "").split())))
        out.print(table)


@app.command("render")
def render_cmd(
    scenario: Annotated[str, typer.Argument(help="Scenario YAML file or built-in name (see `stereotrack scenarios`).")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Clip folder to write.")],
    frames: Annotated[int | None, typer.Option(help="Override the scenario's frame count.")] = None,
    seed: Annotated[int | None, typer.Option(help="Override the scenario's seed.")] = None,
    fmt: Annotated[str, typer.Option("--format", help="mp4 (videos) or png (lossless frame folders).")] = "mp4",
    workers: Annotated[int, typer.Option(help="1 renders the cameras in turn; 2 in two processes.")] = 2,
) -> None:
    """Render a scenario into a stereo clip folder with exact ground truth and calib.yaml."""
    from renderers.render import render_clip
    from renderers.scenario import load_scenario

    fmt = _clip_format(fmt)
    scen = load_scenario(scenario)
    try:
        scen = scen.with_overrides(frames=frames, seed=seed)
    except Exception as exc:  # pydantic validation of the overrides
        raise StereotrackError(f"invalid --frames/--seed: {str(exc).splitlines()[-1].strip()}") from None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with progress_bar() as bar:
            task = bar.add_task(f"render {scen.name}", total=scen.frames)
            result = render_clip(scen, output, fmt=fmt, workers=workers,
                                 progress=lambda done, total: bar.update(task, completed=done))
    for w in caught:
        console.print(f"[yellow]warning:[/] {w.message}")
    out.print(f"wrote {result.frames} stereo frames to {result.clip_dir}")


def _clip_format(fmt: str) -> Literal["mp4", "png"]:
    """``--format`` of a rendered clip: mp4 or png (checked before anything is rendered)."""
    if fmt == "mp4":
        return "mp4"
    if fmt == "png":
        return "png"
    raise StereotrackError(f"--format must be mp4 or png, not {fmt!r}")


def _parse_roi(roi: str | None) -> tuple[int, int, int, int] | None:
    if roi is None:
        return None
    try:
        x, y, w, h = (int(v) for v in roi.split(","))
    except ValueError:
        raise StereotrackError(f"--roi must be x,y,w,h in pixels, not {roi!r}") from None
    return x, y, w, h


MarkersOption = Annotated[list[str] | None, typer.Option(
    "--markers", help="Marker colour, NAME:HLO-HHI[:SMIN[:VMIN]] (OpenCV HSV), NAME=#RRGGBB, or NAME@x,y,w,h to learn "
    "the range from that window of the first left frame; repeatable or comma-separated. Default: the clip's "
    "markers.yaml, else the colours of a rendered clip (clip.json).")]
DetectorOption = Annotated[str, typer.Option(
    help="A registered detector: blob, meanshift, camshift, or a plugin's (`stereotrack methods` lists them).")]
CalibUnitsOption = Annotated[str | None, typer.Option(
    "--calib-units", help="Length unit of the calibration's T (m, cm or mm). Default: the 'units' the file declares, "
    "else metres. Given, it overrides the file's, with a warning naming both when they differ; outputs are in metres.")]
TimeOffsetOption = Annotated[str, typer.Option(
    "--time-offset", help="The right camera's delay behind the left (s): 'auto' estimates it from the detections "
    "and applies it when its 95 % interval excludes 0; 'off'; or seconds. A clip's timestamps.csv wins.")]
ForceWindowOption = Annotated[bool, typer.Option(
    "--force", help="Keep a colour learned from a NAME@x,y,w,h window even when it selects far more of the first "
    "frame than the marker (by default that stops the command).")]
FpsOption = Annotated[float | None, typer.Option(
    "--fps", help="Frames per second of the footage. Wins over the clip's clip.yaml 'fps', a rendered clip's "
    "clip.json, timestamps.csv and the video header; frame folders with none of these are taken as 30 fps, "
    "with a warning.")]
ConfigOption = Annotated[Path | None, typer.Option(
    "--config", help="YAML file mapping a method name to its settings, e.g. 'ekf: {process_noise: 2.0}' "
    "(see `stereotrack methods`); the resolved settings are recorded in metrics.json.")]


def _configs(path: Path | None) -> dict | None:
    from pipeline.estimators.configs import load_method_configs

    return load_method_configs(path) if path is not None else None


def _fmt(v: float | None, spec: str = ".3f") -> str:
    return "—" if v is None or v != v else format(v, spec)


@app.command("detect")
def detect_cmd(
    clip: Annotated[Path, typer.Argument(help="Clip folder (left/right videos or PNG folders) or a single video.")],
    detector: DetectorOption = "blob",
    markers: MarkersOption = None,
    roi: Annotated[str | None, typer.Option(help="Initial tracking window x,y,w,h (meanshift/camshift).")] = None,
    allow_unequal: Annotated[bool, typer.Option("--allow-unequal", help="Truncate unequal left/right lengths.")] = False,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Output folder (default CLIP/out).")] = None,
    calib_units: CalibUnitsOption = None,
    fps: FpsOption = None,
    force: ForceWindowOption = False,
) -> None:
    """Find the markers in every frame; write detections.csv and print a per-camera summary."""
    from detectors.stage import detect_clip
    from pipeline.core.clip import Clip
    from pipeline.core.settings import RunHooks, RunSettings

    settings = RunSettings.checked(detector=detector, markers=_specs(markers), roi=_parse_roi(roi), fps=fps,
                                   allow_unequal=allow_unequal, calib_units=calib_units, force_window=force)
    clip_ = Clip(clip, settings.fps)
    with progress_bar() as bar:
        task = bar.add_task(f"detect ({detector})", total=None)
        hooks = RunHooks(progress=lambda done, total: bar.update(task, completed=done, total=total or None))
        result = detect_clip(clip_, settings, output, hooks)
    _print_learned(result.learned)
    _print_time(clip_.fps, clip_.fps_source)
    table = Table("camera", "frames", "detections", "misses", "false (hidden)", "px err median", "p95", "max",
                  title=str(result.path))
    for s in result.summaries:
        table.add_row(s.camera, str(s.frames), str(s.detections), "—" if s.misses is None else str(s.misses),
                      "—" if s.false is None else str(s.false), _fmt(s.err_median), _fmt(s.err_p95), _fmt(s.err_max))
    out.print(table)


def _specs(markers: list[str] | None) -> list[str] | None:
    """``--markers`` values: repeatable and comma-separated (a window spec's commas are its own)."""
    import re

    out = []
    for m in markers or []:
        out += [p for p in re.split(r",(?![0-9-])", m) if p.strip()]
    return out or None


def _print_learned(learned: dict[str, str]) -> None:
    for name, spec in learned.items():
        out.print(f"learned marker {name!r} from its window: --markers {spec}")


def _methods(methods: str | None) -> list[str] | None:
    """``--methods``: None when not given; an empty list (refused by the settings) when given empty."""
    return None if methods is None else [m.strip() for m in methods.split(",") if m.strip()]


def _print_time(fps: float, source: str) -> None:
    """The frame rate in use and where it came from (every estimate's dt follows from it)."""
    out.print(f"frame rate: {fps:g} fps (dt {1000 / fps:.2f} ms), from {source}", highlight=False)


def _print_sync(metrics: dict) -> None:
    from pipeline.core.sync import SyncEstimate

    sync = metrics.get("sync")
    if sync:
        s = SyncEstimate(**{**sync, "ci_s": tuple(sync["ci_s"]) if sync.get("ci_s") else None})
        out.print(s.describe(), highlight=False)


def _metrics_table(metrics: dict, title: str) -> Table:
    table = Table(title=title, caption="3-D errors and z in mm, reprojection in px, α in mrad; steps/s is "
                  "wall-clock on this machine and varies with its load")
    table.add_column("method", no_wrap=True)
    for col in ("3-D RMSE", "final", "reproj.", "α RMSE", "z RMSE", "steps/s"):
        table.add_column(col, justify="right", no_wrap=True)
    milli = lambda v: None if v is None else 1000 * v  # noqa: E731
    for m, e in metrics.get("methods", {}).items():
        table.add_row(m, _fmt(milli(e.get("rmse")), ".2f"), _fmt(milli(e.get("final")), ".2f"),
                      _fmt(e.get("reprojection_rmse_px"), ".2f"), _fmt(milli(e.get("alpha_rmse_rad")), ".2f"),
                      _fmt(milli(e.get("distance_rmse_m")), ".2f"), _fmt(e.get("steps_per_second"), ",.0f"))
    return table


@app.command("estimate")
def estimate_cmd(
    clip: Annotated[Path, typer.Argument(help="Clip folder with calib.yaml and out/detections.csv.")],
    methods: Annotated[str | None, typer.Option(help="Comma-separated methods (default: all point methods).")] = None,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Where the outputs go (default CLIP/out); "
                                                "inputs are always read from CLIP/out.")] = None,
    calib_units: CalibUnitsOption = None,
    config: ConfigOption = None,
    time_offset: TimeOffsetOption = "auto",
    fps: FpsOption = None,
) -> None:
    """Estimate 3-D tracks with each method; write estimates/<method>.csv and metrics.json."""
    from pipeline.core.clip import Clip
    from pipeline.core.settings import RunHooks, RunSettings
    from pipeline.estimate import estimate_clip

    settings = RunSettings.checked(methods=_methods(methods), configs=_configs(config), calib_units=calib_units,
                                   time_offset=time_offset, fps=fps)
    with progress_bar() as bar:
        task = bar.add_task("estimate", total=None)
        hooks = RunHooks(stage=lambda name: bar.update(task, description=name),
                         progress=lambda d, t: bar.update(task, completed=d, total=t))
        res = estimate_clip(Clip(clip, settings.fps), settings, output, hooks, in_dir=Outputs.of(clip).folder)
    _print_time(res.metrics["time"]["fps"], res.metrics["time"]["source"])
    _print_sync(res.metrics)
    out.print(_metrics_table(res.metrics, str(Outputs(res.out_dir).metrics)))


@app.command("calibrate")
def calibrate_cmd(
    images: Annotated[Path, typer.Argument(help="Folder of image pairs (left*/right* numbered alike, or left/ and "
                                           "right/ folders) or of two videos left.* and right.*.")],
    board: Annotated[str, typer.Option(help="chessboard:COLSxROWS (inner corners) or charuco:COLSxROWS:DICT "
                                       "(squares; DICT e.g. 4X4_50).")],
    square: Annotated[str, typer.Option(help="Side of a square with its unit: 24mm, 2.4cm, 0.024 (metres).")],
    marker: Annotated[str | None, typer.Option(help="ChArUco: side of a marker, with its unit.")] = None,
    output: Annotated[Path, typer.Option("-o", "--output", help="The calibration to write.")] = Path("calib.yaml"),
) -> None:
    """Calibrate a stereo rig from board pairs: calib.yaml (metres) and a report beside it."""
    from pipeline.calibrate import calibrate_folder, parse_board, parse_length

    b = parse_board(board, parse_length(square), parse_length(marker, "--marker") if marker else None)
    with progress_bar() as bar:
        bar.add_task("calibrate", total=None)
        cal, report, _ = calibrate_folder(images, b, output)
    for name, why in cal.rejected.items():
        out.print(f"left out {name}: {why}", highlight=False)
    out.print(f"{len(cal.used)} pairs; RMS left {cal.rms_left:.3f} px, right {cal.rms_right:.3f} px, stereo "
              f"{cal.rms_stereo:.3f} px; baseline {cal.baseline:.4f} m; second camera on the {cal.second_camera_side}",
              highlight=False)
    out.print(f"wrote {output} and {report}")


@app.command("export")
def export_cmd(
    clip: Annotated[Path, typer.Argument(help="Clip folder whose out/ holds estimates (after estimate or run).")],
    fmt: Annotated[str, typer.Option("--format", help="trc (OpenSim), c3d (motion capture) or csv (one row per "
                                     "frame).")] = "trc",
    methods: Annotated[str | None, typer.Option(help="Comma-separated methods (default: every one with "
                                                "estimates).")] = None,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Folder for the files (default "
                                                "CLIP/out/export).")] = None,
) -> None:
    """Write each method's 3-D tracks as <method>.<format>: marker names, frame rate, metres."""
    from pipeline.present.export import export_clip

    for path in export_clip(clip, fmt.lower(), _methods(methods), output):
        out.print(f"wrote {path}")


@app.command("report")
def report_cmd(
    clip: Annotated[Path, typer.Argument(help="Clip folder whose out/ holds estimates and metrics.")],
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Where the outputs go (default CLIP/out); "
                                                "inputs are always read from CLIP/out.")] = None,
) -> None:
    """Write out/report.md with the metrics table and figures."""
    from pipeline.present.report import write_report

    with progress_bar() as bar:
        task = bar.add_task("report", total=None)
        path = write_report(clip, output, progress=lambda d, t: bar.update(task, completed=d, total=t),
                            in_dir=Outputs.of(clip).folder)
    out.print(f"wrote {path}")


@app.command("run")
def run_cmd(
    target: Annotated[str | None, typer.Argument(
        help="A clip folder, a scenario (YAML or built-in name), or nothing for the built-in default scenario.")] = None,
    output: Annotated[Path | None, typer.Option("-o", "--output",
                                                help="Where a rendered clip goes (default runs/<scenario>).")] = None,
    frames: Annotated[int | None, typer.Option(help="Override the scenario's frame count.")] = None,
    seed: Annotated[int | None, typer.Option(help="Override the scenario's seed.")] = None,
    detector: DetectorOption = "blob",
    methods: Annotated[str | None, typer.Option(help="Comma-separated methods (default: all).")] = None,
    fmt: Annotated[str, typer.Option("--format", help="Rendered clip format: mp4 or png.")] = "mp4",
    markers: MarkersOption = None,
    calib_units: CalibUnitsOption = None,
    config: ConfigOption = None,
    time_offset: TimeOffsetOption = "auto",
    fps: FpsOption = None,
    force: ForceWindowOption = False,
) -> None:
    """Run every stage on one clip: (render), detect, estimate, metrics, report, recording.

    A clip folder of real footage needs two videos (or PNG folders), a calibration and its markers
    (--markers or a markers.yaml in the folder)."""
    from pipeline.app.run import DEFAULT_SCENARIO, process_clip
    from pipeline.core.settings import RunHooks, RunSettings

    t0 = __import__("time").perf_counter()
    settings = RunSettings.checked(detector=detector, methods=_methods(methods), markers=_specs(markers),
                                   calib_units=calib_units, configs=_configs(config), time_offset=time_offset, fps=fps,
                                   force_window=force)
    clip = _clip_or_render(target or DEFAULT_SCENARIO, output, frames, seed, _clip_format(fmt))
    with progress_bar() as bar:
        task = bar.add_task("detect", total=None)

        def stage(name: str) -> None:  # a fresh task: no count or clock carried over from the stage before
            nonlocal task
            bar.remove_task(task)
            task = bar.add_task(name, total=None)

        hooks = RunHooks(stage=stage, progress=lambda d, t: bar.update(task, completed=d, total=t))
        res = process_clip(clip, settings=settings, hooks=hooks, keep_tracks=False)
    _print_learned(res.detect.learned)
    _print_time(res.estimate.metrics["time"]["fps"], res.estimate.metrics["time"]["source"])
    _print_sync(res.estimate.metrics)
    out.print(_metrics_table(res.estimate.metrics, f"{clip} — {res.estimate.n_frames} frames"))
    out.print(f"outputs in {res.out_dir}: detections.csv, estimates/, metrics.json, report.html, report.md, run.rrd")
    out.print(f"replay: stereotrack view {clip}    ({__import__('time').perf_counter() - t0:.1f} s)")


def _clip_or_render(target: str, output: Path | None, frames: int | None, seed: int | None, fmt: Literal["mp4", "png"]) -> Path:
    """The clip folder ``run`` works on: ``target`` itself, or the scenario ``target`` rendered."""
    clip = Path(target)
    if clip.is_file() and clip.suffix.lower() not in (".yaml", ".yml"):
        from pipeline.core.frames import VIDEO_EXTS

        why = ("is a single video: a one-camera clip, which `stereotrack detect` reads; `run` needs a stereo clip folder "
               "(left/right videos and a calibration)") if clip.suffix.lower() in VIDEO_EXTS else \
            "is neither a clip folder nor a scenario (.yaml)"
        raise StereotrackError(why, clip)
    if clip.is_dir() and any(clip.iterdir()):
        return clip
    from renderers.render import render_clip
    from renderers.scenario import load_scenario

    scen = load_scenario(target).with_overrides(frames=frames, seed=seed)
    clip = output or Path("runs") / scen.name
    with progress_bar() as bar:
        task = bar.add_task(f"render {scen.name}", total=scen.frames)
        render_clip(scen, clip, fmt=fmt, progress=lambda d, t: bar.update(task, completed=d))
    return clip


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
    from pipeline.core.lifeline import terminate_with_parent

    rc = subprocess.run([*cmd, *map(str, rrds)], check=False, preexec_fn=terminate_with_parent).returncode
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
    import sys

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
    methods: Annotated[str | None, typer.Option(help="Comma-separated methods (default: all).")] = None,
    markers: MarkersOption = None,
    calib_units: CalibUnitsOption = None,
    config: ConfigOption = None,
    no_images: Annotated[bool, typer.Option("--no-images", help="Leave the frames out of each clip's recording.")] = False,
    time_offset: TimeOffsetOption = "auto",
    fps: FpsOption = None,
    figures: Annotated[bool, typer.Option("--figures", help="Draw each clip's report figures (the summary's "
                                          "leaderboard is always written).")] = False,
) -> None:
    """Process every clip folder under INPUT_DIR; exit code 1 if any clip failed.

    Markers: --markers for every clip, else each clip's markers.yaml, else INPUT_DIR/markers.yaml,
    else the colours of a rendered clip (clip.json)."""
    from pipeline.app.batch import run_batch
    from pipeline.core.settings import RunSettings

    settings = RunSettings.checked(detector=detector, methods=_methods(methods), markers=_specs(markers),
                                   calib_units=calib_units, configs=_configs(config), images=not no_images,
                                   time_offset=time_offset, fps=fps, figures=figures)
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

    def __init__(self, bar: Progress) -> None:
        self.bar = bar
        self.tasks: dict[str, TaskID] = {}

    def __call__(self, clip: str, stage: str) -> None:
        if stage == "done":
            if clip in self.tasks:
                self.bar.remove_task(self.tasks.pop(clip))
        elif clip not in self.tasks:
            self.tasks[clip] = self.bar.add_task(f"  {clip}: {stage}", total=None)
        else:
            self.bar.update(self.tasks[clip], description=f"  {clip}: {stage}")


def _print_batch(outcomes: list, output: Path) -> None:
    """The per-method leaderboard, the clips that failed or warned, and where the summary is."""
    from pipeline.present.summary import clip_warnings, method_rows

    rows = method_rows(outcomes)
    table = Table(title=f"{len(outcomes)} clips: 3-D RMSE (mm) of each method across clips",
                  caption="steps/s is wall-clock on this machine and varies with its load")
    for col in ("method", "clips", "mean", "95 % CI", "median", "runaway", "failed", "steps/s"):
        table.add_column(col, justify="left" if col == "method" else "right", no_wrap=True)
    for r in rows:
        from pipeline.present.summary import interval

        ci = interval(r["mean_ci_low_m"], r["mean_ci_high_m"])
        table.add_row(r["method"], str(r["clips"]), _fmt(r["mean_rmse_m"] and 1000 * r["mean_rmse_m"], ".2f"), ci,
                      _fmt(r["median_rmse_m"] and 1000 * r["median_rmse_m"], ".2f"), str(r["runaways"]),
                      str(r["failures"]), _fmt(r["median_steps_per_second"], ",.0f"))
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


@app.command("render-batch")
def render_batch_cmd(
    scenario: Annotated[str, typer.Argument(help="Scenario YAML or built-in name.")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Folder to fill with one clip per seed.")],
    seeds: Annotated[str, typer.Option(help="Seeds as A..B (inclusive) or a comma list.")] = "0..3",
    frames: Annotated[int | None, typer.Option(help="Override the scenario's frame count.")] = None,
    fmt: Annotated[str, typer.Option("--format", help="mp4 or png.")] = "mp4",
    workers: Annotated[int, typer.Option(help="Render processes, each keeping its GL context across clips.")] = 2,
) -> None:
    """Render a folder of clips of one scenario, one per seed, with persistent render workers."""
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
    fmt = _clip_format(fmt)
    base = load_scenario(scenario)
    jobs = []
    for s in seed_list:
        scen = base.with_overrides(frames=frames, seed=s)
        jobs.append((scen, output / f"{scen.name}_seed{s}"))
    with progress_bar() as bar:
        task = bar.add_task(f"render {len(jobs)} clips", total=sum(j[0].frames for j in jobs))
        render_clips(jobs, fmt, max(1, workers), lambda d, t: bar.update(task, completed=d))
    out.print(f"wrote {len(seed_list)} clips to {output}")


_shown: set[str] = set()


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line ``warning: FILE: problem`` (no source line, no category), each once; a
    library's warning (numpy's, say) names the library and the stereotrack line that caused it."""
    text = str(message)
    ours = issubclass(category, UserWarning) and bool({"pipeline", "detectors", "renderers"} & set(Path(filename).parts))
    if not ours:
        text = f"{Path(filename).name}:{lineno}: {category.__name__}: {text}"
    if text in _shown:
        return
    _shown.add(text)
    console.print(f"[yellow]warning:[/] {escape(text)}", highlight=False, soft_wrap=True)


def _error(text: str) -> None:
    console.print(f"[bold red]error:[/] {escape(text)}", highlight=False, soft_wrap=True)


def main() -> None:
    """Console-script entry point: user errors become one line on stderr and exit code 2; SIGINT and
    SIGTERM one line and exit 130/143, with locks released and temporary files and workers gone."""
    import os

    from pipeline.core import allocator
    from pipeline.core.lifeline import install_signal_handlers, received_signal

    allocator.tune()  # frames churn through the allocator: keep their pages (see the module)
    warnings.showwarning = _show_warning
    install_signal_handlers()
    try:
        app()
    except StereotrackError as exc:
        _error(str(exc))
        sys.exit(2)
    except OSError as exc:  # an output path that cannot be written, a disk that filled up
        where = f"{exc.filename}: " if exc.filename else ""
        _error(where + str(exc.strerror or exc))
        sys.exit(2)
    except KeyboardInterrupt:
        _interrupted()
    except SystemExit as exc:
        if exc.code == 130 and received_signal() is not None:  # typer turns KeyboardInterrupt into Exit(130)
            _interrupted()
        raise
    except Exception as exc:  # a bug, not a bad input: still one line, the traceback on request
        if os.environ.get("STEREOTRACK_DEBUG"):
            raise
        import traceback

        last = traceback.extract_tb(exc.__traceback__)[-1]
        _error(f"internal error: {type(exc).__name__}: {first_line(exc) if str(exc).strip() else ''} "
               f"({Path(last.filename).name}:{last.lineno}); rerun with STEREOTRACK_DEBUG=1 for the traceback")
        sys.exit(1)


def _interrupted() -> None:
    import os
    import signal

    from pipeline.core.lifeline import received_signal

    sig = received_signal() or signal.SIGINT
    console.print(f"[bold red]interrupted[/] ({signal.Signals(sig).name}): stopped; nothing half-written was kept",
                  highlight=False)
    # Every lock, temporary file and worker is gone by now (released on the way up). Leave at once with
    # the documented status: about one interrupted render-batch in ten under load was otherwise ended by
    # a KeyboardInterrupt during the interpreter's shutdown (exit status −2, whatever the signal).
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(128 + sig)


if __name__ == "__main__":
    main()
