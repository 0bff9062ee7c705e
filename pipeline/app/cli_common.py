"""What every ``stereotrack`` command shares: the typer app, the consoles, the progress-bar style, the
options several commands take, and how results are printed."""

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Literal

import typer
from rich.console import Console
from rich.table import Table

from pipeline.core.errors import StereotrackError

#: ``--methods``' help: what runs when it is not given
METHODS_HELP = "Comma-separated methods (default: those run by default; `stereotrack methods` lists every one)."

if TYPE_CHECKING:
    from rich.progress import Progress

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


def progress_bar() -> "Progress":
    """The one progress-bar style of every long command (rich's progress module is imported here:
    commands that show no bar never pay for it)."""
    from pipeline.app.progress import progress_bar as make

    return make(console)


def stage_eta(name: str) -> bool:
    """Whether a stage's progress can be timed by its rate (not the estimate stage: see
    :class:`RemainingColumn`)."""
    return not name.startswith("estimate")


def clip_format(fmt: str) -> Literal["mp4", "png"]:
    """``--format`` of a rendered clip: mp4 or png (checked before anything is rendered)."""
    if fmt == "mp4":
        return "mp4"
    if fmt == "png":
        return "png"
    raise StereotrackError(f"--format must be mp4 or png, not {fmt!r}")


def parse_roi(roi: str | None) -> tuple[int, int, int, int] | None:
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
AllowUnequalOption = Annotated[bool, typer.Option(
    "--allow-unequal", help="Truncate left/right videos of unequal lengths (and no timestamps.csv) to the shorter, "
    "with a warning, instead of stopping.")]
FpsOption = Annotated[float | None, typer.Option(
    "--fps", help="Frames per second of the footage. Wins over the clip's clip.yaml 'fps', a rendered clip's "
    "clip.json, timestamps.csv and the video header; frame folders with none of these are taken as 30 fps, "
    "with a warning.")]
ConfigOption = Annotated[Path | None, typer.Option(
    "--config", help="YAML file mapping a method name to its settings, e.g. 'ekf: {process_noise: 2.0}' "
    "(see `stereotrack methods`); the resolved settings are recorded in metrics.json.")]

WorkersOption = Annotated[int, typer.Option(
    "--workers", min=1, help="Processes the estimate stage runs its methods in (1: this process; the numbers "
    "are the same).")]


def method_configs(path: Path | None) -> dict | None:
    from pipeline.estimators.configs import load_method_configs

    return load_method_configs(path) if path is not None else None


def fmt_value(v: float | None, spec: str = ".3f") -> str:
    return "—" if v is None or v != v else format(v, spec)


def marker_specs(markers: list[str] | None) -> list[str] | None:
    """``--markers`` values: repeatable and comma-separated (a window spec's commas are its own)."""
    import re

    out = []
    for m in markers or []:
        out += [p for p in re.split(r",(?![0-9-])", m) if p.strip()]
    return out or None


def print_learned(learned: dict[str, str]) -> None:
    for name, spec in learned.items():
        out.print(f"learned marker {name!r} from its window: --markers {spec}")


def method_list(methods: str | None) -> list[str] | None:
    """``--methods``: None when not given; an empty list (refused by the settings) when given empty."""
    return None if methods is None else [m.strip() for m in methods.split(",") if m.strip()]


def print_time(fps: float, source: str) -> None:
    """The frame rate in use and where it came from (every estimate's dt follows from it)."""
    out.print(f"frame rate: {fps:g} fps (dt {1000 / fps:.2f} ms), from {source}", highlight=False)


def print_sync(metrics: dict) -> None:
    from pipeline.core.sync import SyncEstimate

    sync = metrics.get("sync")
    if sync:
        s = SyncEstimate(**{**sync, "ci_s": tuple(sync["ci_s"]) if sync.get("ci_s") else None})
        out.print(s.describe(), highlight=False)


def metrics_table(metrics: dict, title: str) -> Table:
    table = Table(title=title, caption="3-D errors and z in mm, reprojection in px, α in mrad; steps/s is "
                  "wall-clock on this machine and varies with its load")
    table.add_column("method", no_wrap=True)
    for col in ("3-D RMSE", "final", "reproj.", "α RMSE", "z RMSE", "steps/s"):
        table.add_column(col, justify="right", no_wrap=True)
    milli = lambda v: None if v is None else 1000 * v  # noqa: E731
    for m, e in metrics.get("methods", {}).items():
        table.add_row(m, fmt_value(milli(e.get("rmse")), ".2f"), fmt_value(milli(e.get("final")), ".2f"),
                      fmt_value(e.get("reprojection_rmse_px"), ".2f"), fmt_value(milli(e.get("alpha_rmse_rad")), ".2f"),
                      fmt_value(milli(e.get("distance_rmse_m")), ".2f"), fmt_value(e.get("steps_per_second"), ",.0f"))
    return table
