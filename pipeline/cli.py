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
