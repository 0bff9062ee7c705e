"""The ``stereotrack`` commands on one clip (and the lists of what is built in): ``scenarios``,
``methods``, ``render``, ``detect``, ``estimate``, ``calibrate``, ``export``, ``report``, ``run``.
I/O and presentation only: each calls the library functions the tests call."""

import warnings
from contextlib import ExitStack
from pathlib import Path
from typing import Annotated, Literal

import typer
from rich.markup import escape
from rich.table import Table

from pipeline.app.cli_common import (
    METHODS_HELP,
    AllowUnequalOption,
    CalibUnitsOption,
    ConfigOption,
    DetectorOption,
    ForceWindowOption,
    FpsOption,
    MarkersOption,
    TimeOffsetOption,
    WorkersOption,
    app,
    clip_format,
    console,
    fmt_value,
    marker_specs,
    method_configs,
    method_list,
    metrics_table,
    out,
    parse_roi,
    print_learned,
    print_sync,
    print_time,
    progress_bar,
    stage_eta,
)
from pipeline.core.errors import StereotrackError
from pipeline.core.outputs import Outputs


def writable_output(folder: Path | None) -> None:
    """A folder given with ``-o``: new, empty, or one stereotrack wrote (:data:`~pipeline.core.outputs.OURS`);
    a user's folder is refused, one line naming it, nothing written."""
    from pipeline.core.io import check_replaceable
    from pipeline.core.outputs import OURS

    if folder is not None:
        check_replaceable(folder, OURS, "outputs")


def stage_lock(clip: Path, output: Path | None, what: str, make: bool = True) -> ExitStack:
    """The locks a single stage holds while it runs: its output folder and, when it reads another,
    the clip's ``out/`` it reads from (a `run` writing there meanwhile makes it fail at once, naming
    the holder, as a second `run` does). ``make=False``: lock the clip's ``out/`` only if it exists."""
    from pipeline.core.lifeline import OutputLock

    stack = ExitStack()
    own = Outputs.of(clip if clip.is_dir() else clip.parent).folder
    try:
        for folder in dict.fromkeys([output or own, own]):
            if folder == own and (output is not None or not make) and not own.is_dir():
                continue  # nothing to read there, nothing to make
            stack.enter_context(OutputLock(folder, f"stereotrack {what} {clip}"))
    except BaseException:
        stack.close()
        raise
    return stack


def mark_output(folder: Path | None) -> None:
    """After a command wrote into a folder given with ``-o``: mark it as stereotrack's, so that the
    next command writing there finds it so."""
    from pipeline.core.outputs import OUTPUT_MARK

    if folder is not None and folder.is_dir():
        (folder / OUTPUT_MARK).touch()


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
    if names:
        from pipeline.estimators import registry

        return _print_settings(names, registry())
    from pipeline.app.catalogue import listing

    estimators, detectors = listing()  # no estimator or detector module imported unless a plugin is installed
    table = Table("method", "kind", "cameras", "description", title="estimators (--methods, --config)")
    for name, (kind, cameras, description) in estimators.items():
        table.add_row(name, kind, cameras, description)
    out.print(table)
    found = Table("detector", "description", title="detectors (--detector)")
    for name, description in detectors.items():
        found.add_row(name, description)
    out.print(found)
    out.print("settings of a method: stereotrack methods NAME", highlight=False)


def _print_settings(names: list[str], reg: dict) -> None:
    """Each named method's settings: the key, its default and what it does."""
    unknown = [n for n in names if n not in reg]
    if unknown:
        raise StereotrackError(f"unknown method(s) {', '.join(unknown)} (known: {', '.join(reg)})")
    from pipeline.core.docstrings import attribute_docs

    for name in names:
        fields, docs = reg[name].Config.model_fields, attribute_docs(reg[name].Config)
        table = Table(title=f"{name} (a --config file's '{name}:' section)")
        table.add_column("setting", no_wrap=True, min_width=max(len(k) for k in fields))  # a key is never cut
        table.add_column("default", overflow="fold")
        table.add_column("what it does", overflow="fold")
        for key, field in fields.items():
            default = field.get_default(call_default_factory=True)
            shown = default.model_dump() if hasattr(default, "model_dump") else default
            table.add_row(key, escape(str(shown)), escape(" ".join(docs.get(key, "").replace("``", "").split())))
        out.print(table)


@app.command("render")
def render_cmd(
    scenario: Annotated[str, typer.Argument(help="Scenario YAML file or built-in name (see `stereotrack scenarios`).")],
    output: Annotated[Path, typer.Option("-o", "--output", help="Clip folder to write.")],
    frames: Annotated[int | None, typer.Option(help="Override the scenario's frame count.")] = None,
    seed: Annotated[int | None, typer.Option(help="Override the scenario's seed.")] = None,
    fmt: Annotated[str, typer.Option("--format", help="mp4 (videos) or png (lossless frame folders).")] = "mp4",
    workers: Annotated[int, typer.Option(help="1 renders the cameras in turn; 2 both at once (threads for the analytic "
                                              "rasteriser, processes for pyrender).")] = 2,
) -> None:
    """Render a scenario into a stereo clip folder with exact ground truth and calib.yaml."""
    from renderers.render import render_clip
    from renderers.scenario import load_scenario

    fmt = clip_format(fmt)
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
    what = "stereo frames" if len(result.cameras) == 2 else f"frames of each of {len(result.cameras)} cameras"
    out.print(f"wrote {result.frames} {what} to {result.clip_dir}")


@app.command("detect")
def detect_cmd(
    clip: Annotated[Path, typer.Argument(help="Clip folder (left/right videos or PNG folders) or a single video.")],
    detector: DetectorOption = "blob",
    markers: MarkersOption = None,
    roi: Annotated[str | None, typer.Option(help="Initial tracking window x,y,w,h (meanshift/camshift).")] = None,
    allow_unequal: AllowUnequalOption = False,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Output folder (default CLIP/out).")] = None,
    calib_units: CalibUnitsOption = None,
    fps: FpsOption = None,
    force: ForceWindowOption = False,
    workers: Annotated[int, typer.Option("--workers", min=1, help="Processes the cameras are decoded and detected "
                                         "in (1: threads of this process; the detections are the same).")] = 2,
) -> None:
    """Find the markers in every frame; write detections.csv and print a per-camera summary."""
    from detectors.stage import detect_clip
    from pipeline.core.clip import Clip
    from pipeline.core.settings import RunHooks, RunSettings

    settings = RunSettings.checked(detector=detector, markers=marker_specs(markers), roi=parse_roi(roi), fps=fps,
                                   allow_unequal=allow_unequal, calib_units=calib_units, force_window=force)
    writable_output(output)
    clip_ = Clip(clip, settings.fps)
    with stage_lock(clip, output, "detect"), progress_bar() as bar:
        task = bar.add_task(f"detect ({detector})", total=None)
        hooks = RunHooks(progress=lambda done, total: bar.update(task, completed=done, total=total or None))
        result = detect_clip(clip_, settings, output, hooks, workers=workers)
    mark_output(output)
    print_learned(result.learned)
    print_time(clip_.fps, clip_.fps_source)
    table = Table("camera", "frames", "detections", "misses", "false (hidden)", "px err median", "p95", "max",
                  title=str(result.path))
    for s in result.summaries:
        table.add_row(s.camera, str(s.frames), str(s.detections), "—" if s.misses is None else str(s.misses),
                      "—" if s.false is None else str(s.false), fmt_value(s.err_median), fmt_value(s.err_p95),
                      fmt_value(s.err_max))
    out.print(table)


@app.command("estimate")
def estimate_cmd(
    clip: Annotated[Path, typer.Argument(help="Clip folder with calib.yaml and out/detections.csv.")],
    methods: Annotated[str | None, typer.Option(help=METHODS_HELP)] = None,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Where the outputs go (default CLIP/out); "
                                                "inputs are always read from CLIP/out.")] = None,
    calib_units: CalibUnitsOption = None,
    config: ConfigOption = None,
    time_offset: TimeOffsetOption = "auto",
    fps: FpsOption = None,
    workers: WorkersOption = 2,
) -> None:
    """Estimate 3-D tracks with each method; write estimates/<method>.csv and metrics.json."""
    from pipeline.core.clip import Clip
    from pipeline.core.settings import RunHooks, RunSettings
    from pipeline.estimate import estimate_clip

    settings = RunSettings.checked(methods=method_list(methods), configs=method_configs(config), calib_units=calib_units,
                                   time_offset=time_offset, fps=fps)
    writable_output(output)
    with stage_lock(clip, output, "estimate"), progress_bar() as bar:
        task = bar.add_task("estimate", total=None, eta=False)
        hooks = RunHooks(stage=lambda name: bar.update(task, description=name),
                         progress=lambda d, t: bar.update(task, completed=d, total=t))
        res = estimate_clip(Clip(clip, settings.fps), settings, output, hooks, in_dir=Outputs.of(clip).folder,
                           workers=workers)
    mark_output(output)
    print_time(res.metrics["time"]["fps"], res.metrics["time"]["source"])
    print_sync(res.metrics)
    out.print(metrics_table(res.metrics, str(Outputs(res.out_dir).metrics)))


@app.command("calibrate")
def calibrate_cmd(
    images: Annotated[Path, typer.Argument(help="Folder of image pairs (left*/right* numbered alike, or left/ and "
                                           "right/ folders) or of two videos left.* and right.*; or, for three or "
                                           "more cameras, one sub-folder of numbered images per camera (cam0/, cam1/, "
                                           "…: the same number is the same instant).")],
    board: Annotated[str, typer.Option(help="chessboard:COLSxROWS (inner corners) or charuco:COLSxROWS:DICT "
                                       "(squares; DICT e.g. 4X4_50).")],
    square: Annotated[str, typer.Option(help="Side of a square with its unit: 24mm, 2.4cm, 0.024 (metres).")],
    marker: Annotated[str | None, typer.Option(help="ChArUco: side of a marker, with its unit.")] = None,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="The calibration to write (default calib.yaml; "
                                                "for camera sub-folders rig.json, or any rig format by its name).")] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace an existing calibration that `calibrate` did not "
                                        "write (one it wrote, with its report beside it, is replaced anyway), and "
                                        "write one whose stereo RMS is absurd (over 5 px).")] = False,
    left_only: Annotated[Path | None, typer.Option("--left-only", help="A folder of the first camera's own board "
                                                   "images (not simultaneous with the other's): its intrinsics use "
                                                   "them beside the pairs.")] = None,
    right_only: Annotated[Path | None, typer.Option("--right-only", help="The same for the second camera.")] = None,
) -> None:
    """Calibrate a stereo rig from board pairs, or a rig of N cameras from per-camera folders: the
    calibration (metres) and a report beside it."""
    from pipeline.calibrate import calibrate_folder, parse_board, parse_length
    from pipeline.calibrate.rig import calibrate_rig_folder, camera_folders

    b = parse_board(board, parse_length(square), parse_length(marker, "--marker") if marker else None)
    folders = camera_folders(images) if images.is_dir() else []
    if len(folders) >= 2 and {f.name for f in folders} != {"left", "right"}:
        target = output or Path("rig.json")
        with progress_bar() as bar:
            bar.add_task("calibrate", total=None)
            rig_cal, rig_report = calibrate_rig_folder(images, b, target)
        out.print(f"{rig_cal.rig.n} cameras ({', '.join(rig_cal.rig.names)}); {rig_cal.shared} shared views; joint RMS "
                  f"{rig_cal.rms_joint:.3f} px; leave-one-camera-out " + ", ".join(
                      f"{n} {e:.2f} px" for n, e in rig_cal.loo.items()), highlight=False)
        out.print(f"wrote {target} and {rig_report}")
        return
    output = output or Path("calib.yaml")
    with progress_bar() as bar:
        bar.add_task("calibrate", total=None)
        cal, report, _ = calibrate_folder(images, b, output, force, (left_only, right_only))
    for name, why in cal.rejected.items():
        out.print(f"left out {name}: {why}", highlight=False)
    out.print(f"{len(cal.used)} pairs; RMS left {cal.rms_left:.3f} px, right {cal.rms_right:.3f} px, stereo "
              f"{cal.rms_stereo:.3f} px; baseline {cal.baseline:.4f} m; second camera {cal.second_camera_phrase}",
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
    predicted: Annotated[bool, typer.Option("--predicted", help="Also write the frames a method only predicted "
                                            "(held, coasted, gated); by default they are gaps, as no camera "
                                            "measured them.")] = False,
) -> None:
    """Write each method's 3-D tracks as <method>.<format>: marker names, frame rate, metres."""
    from pipeline.present.export import export_clip

    with stage_lock(clip, None, "export", make=False):  # -o: a folder export_clip checks is new, empty or ours
        written = export_clip(clip, fmt.lower(), method_list(methods), output, predicted=predicted)
    for path in written:
        out.print(f"wrote {path}")


@app.command("report")
def report_cmd(
    clip: Annotated[Path, typer.Argument(help="Clip folder whose out/ holds estimates and metrics.")],
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Where the outputs go (default CLIP/out); "
                                                "inputs are always read from CLIP/out.")] = None,
) -> None:
    """Write out/report.md and out/report.html with the metrics tables and figures."""
    from pipeline.present.report import write_report

    writable_output(output)
    with stage_lock(clip, output, "report"), progress_bar() as bar:
        task = bar.add_task("report", total=None)
        path = write_report(clip, output, progress=lambda d, t: bar.update(task, completed=d, total=t),
                            in_dir=Outputs.of(clip).folder)
    mark_output(output)
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
    methods: Annotated[str | None, typer.Option(help=METHODS_HELP)] = None,
    fmt: Annotated[str, typer.Option("--format", help="Rendered clip format: mp4 or png.")] = "mp4",
    markers: MarkersOption = None,
    calib_units: CalibUnitsOption = None,
    config: ConfigOption = None,
    time_offset: TimeOffsetOption = "auto",
    fps: FpsOption = None,
    force: ForceWindowOption = False,
    allow_unequal: AllowUnequalOption = False,
    workers: WorkersOption = 2,
) -> None:
    """Run every stage on one clip: (render), detect, estimate, metrics, report, recording.

    A clip folder of real footage needs two videos (or PNG folders), a calibration and its markers
    (--markers or a markers.yaml in the folder)."""
    from pipeline.app.run import DEFAULT_SCENARIO, process_clip
    from pipeline.core.settings import RunHooks, RunSettings

    t0 = __import__("time").perf_counter()
    settings = RunSettings.checked(detector=detector, methods=method_list(methods), markers=marker_specs(markers),
                                   calib_units=calib_units, configs=method_configs(config), time_offset=time_offset, fps=fps,
                                   force_window=force, allow_unequal=allow_unequal)
    clip = _clip_or_render(target or DEFAULT_SCENARIO, output, frames, seed, clip_format(fmt))
    with progress_bar() as bar:
        task = bar.add_task("detect", total=None)

        def stage(name: str) -> None:  # a fresh task: no count or clock carried over from the stage before
            nonlocal task
            bar.remove_task(task)
            task = bar.add_task(name, total=None, eta=stage_eta(name))

        hooks = RunHooks(stage=stage, progress=lambda d, t: bar.update(task, completed=d, total=t))
        res = process_clip(clip, settings=settings, hooks=hooks, keep_tracks=False, workers=workers)
    print_learned(res.detect.learned)
    print_time(res.estimate.metrics["time"]["fps"], res.estimate.metrics["time"]["source"])
    print_sync(res.estimate.metrics)
    out.print(metrics_table(res.estimate.metrics, f"{clip} — {res.estimate.n_frames} frames"))
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
        if output is not None:
            raise StereotrackError(f"-o sets where a rendered clip goes; {clip} is a clip folder already (its outputs go to "
                                   f"{clip / 'out'}): drop -o, or name a scenario file to render", clip)
        return clip
    from renderers.render import render_clip
    from renderers.scenario import load_scenario

    scen = load_scenario(target).with_overrides(frames=frames, seed=seed)
    clip = output or Path("runs") / scen.name
    with progress_bar() as bar:
        task = bar.add_task(f"render {scen.name}", total=scen.frames)
        render_clip(scen, clip, fmt=fmt, progress=lambda d, t: bar.update(task, completed=d))
    return clip
