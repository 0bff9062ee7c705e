"""The ``stereotrack`` command line (typer + rich). I/O and presentation only: every command calls
the library functions the tests call."""

from __future__ import annotations

import sys
import warnings
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from pipeline.errors import StereotrackError

app = typer.Typer(
    help="Track objects in stereo video: render synthetic clips, detect markers, estimate 3-D tracks.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
    add_completion=False,
)
console = Console(stderr=True)
out = Console()


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

    if fmt not in ("mp4", "png"):
        raise StereotrackError(f"--format must be mp4 or png, not {fmt!r}")
    scen = load_scenario(scenario)
    try:
        scen = scen.with_overrides(frames=frames, seed=seed)
    except Exception as exc:  # pydantic validation of the overrides
        raise StereotrackError(f"invalid --frames/--seed: {str(exc).splitlines()[-1].strip()}") from None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with progress_bar() as bar:
            task = bar.add_task(f"render {scen.name}", total=scen.frames)
            result = render_clip(scen, output, fmt=fmt, workers=workers,  # type: ignore[arg-type]
                                 progress=lambda done, total: bar.update(task, completed=done))
    for w in caught:
        console.print(f"[yellow]warning:[/] {w.message}")
    out.print(f"wrote {result.frames} stereo frames to {result.clip_dir}")


def _parse_roi(roi: str | None) -> tuple[int, int, int, int] | None:
    if roi is None:
        return None
    try:
        x, y, w, h = (int(v) for v in roi.split(","))
    except ValueError:
        raise StereotrackError(f"--roi must be x,y,w,h in pixels, not {roi!r}") from None
    return x, y, w, h


def _fmt(v: float | None, spec: str = ".3f") -> str:
    return "—" if v is None else format(v, spec)


@app.command("detect")
def detect_cmd(
    clip: Annotated[Path, typer.Argument(help="Clip folder (left/right videos or PNG folders) or a single video.")],
    detector: Annotated[str, typer.Option(help="blob, meanshift or camshift.")] = "blob",
    markers: Annotated[list[str] | None, typer.Option(
        "--markers", help="Marker colour, NAME:HLO-HHI[:SMIN[:VMIN]] (OpenCV HSV) or NAME=#RRGGBB; repeatable "
        "or comma-separated. Default: the colours in the clip's scenario.yaml.")] = None,
    roi: Annotated[str | None, typer.Option(help="Initial tracking window x,y,w,h (meanshift/camshift).")] = None,
    allow_unequal: Annotated[bool, typer.Option("--allow-unequal", help="Truncate unequal left/right lengths.")] = False,
    output: Annotated[Path | None, typer.Option("-o", "--output", help="Output folder (default CLIP/out).")] = None,
) -> None:
    """Find the markers in every frame; write detections.csv and print a per-camera summary."""
    from detectors.stage import detect_clip

    specs = [s for m in markers or [] for s in m.split(",") if s.strip()] or None
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with progress_bar() as bar:
            task = bar.add_task(f"detect ({detector})", total=None)
            result = detect_clip(clip, detector, specs, _parse_roi(roi), allow_unequal, output,  # type: ignore[arg-type]
                                 progress=lambda done, total: bar.update(task, completed=done, total=total or None))
    for w in caught:
        console.print(f"[yellow]warning:[/] {w.message}")
    table = Table("camera", "frames", "detections", "misses", "px err median", "p95", "max", title=str(result.path))
    for s in result.summaries:
        table.add_row(s.camera, str(s.frames), str(s.detections), "—" if s.misses is None else str(s.misses),
                      _fmt(s.err_median), _fmt(s.err_p95), _fmt(s.err_max))
    out.print(table)


def main() -> None:
    """Console-script entry point: user errors become one line on stderr and exit code 2."""
    try:
        app()
    except StereotrackError as exc:
        console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
        sys.exit(2)
    except KeyboardInterrupt:
        console.print("[bold red]interrupted[/]")
        sys.exit(130)


if __name__ == "__main__":
    main()
