"""``stereotrack rig``: read a calibration of N cameras in any format stereotrack knows, show it,
and convert it to another (:mod:`pipeline.core.rigfiles`)."""

from pathlib import Path
from typing import Annotated

import typer
from rich.table import Table

from pipeline.app.cli_common import CalibUnitsOption, app, out
from pipeline.core.errors import CalibrationError

rig_app = typer.Typer(help="Camera rigs of N cameras: show one, convert between calibration formats.",
                      no_args_is_help=True)
app.add_typer(rig_app, name="rig")

_FORMATS_HELP = ("calib.toml (Anipose/Pose2Sim), NAME.qca.txt (Qualisys), rig.json, rig.yaml/rig.xml (OpenCV "
                 "FileStorage), a folder (one OpenCV file per camera) or calib.yaml (two cameras)")


@rig_app.command("show")
def show_cmd(rig_path: Annotated[Path, typer.Argument(help=f"The rig: {_FORMATS_HELP}, or a clip folder.")],
             calib_units: CalibUnitsOption = None) -> None:
    """Print each camera's name, image size, focal lengths, centre (m), distortion and time offset."""
    import numpy as np

    from pipeline.core.rigfiles import load_rig

    rig = load_rig(rig_path, calib_units)
    table = Table(title=f"{rig_path}: {rig.n} cameras (world: the file's frame; metres)")
    for col in ("camera", "size", "fx, fy (px)", "centre (m)", "distortion", "offset (ms)"):
        table.add_column(col)
    for cam, name, (w, h), off in zip(rig.cameras, rig.names, rig.sizes, rig.offsets, strict=True):
        d = np.ravel(cam.D)
        table.add_row(name, f"{w}×{h}", f"{cam.K[0, 0]:.1f}, {cam.K[1, 1]:.1f}",
                      ", ".join(f"{v:+.3f}" for v in cam.center), f"{np.count_nonzero(d)} of {d.size}",
                      f"{off * 1e3:g}")
    out.print(table)


@rig_app.command("convert")
def convert_cmd(
    source: Annotated[Path, typer.Argument(help=f"The rig to read: {_FORMATS_HELP}.")],
    target: Annotated[Path, typer.Argument(help="The rig to write; its name picks the format (as SOURCE). An "
                                           "existing file is never replaced.")],
    calib_units: CalibUnitsOption = None,
    units: Annotated[str | None, typer.Option(help="Length unit to write the translations in: m (default), cm "
                                              "or mm (Qualisys is always mm).")] = None,
) -> None:
    """Convert a rig between calibration formats, every number kept exactly."""
    from pipeline.core.rigfiles import FORMATS, format_of, load_rig, save_rig

    if units is not None and units not in ("m", "cm", "mm"):
        raise CalibrationError(f"--units names an unknown length unit {units!r} (use m, cm or mm)")
    if target.exists() and not (target.is_dir() and not any(target.iterdir())):
        raise CalibrationError("exists: stereotrack never replaces a file it did not write; choose another name",
                               target)
    fmt = format_of(target)
    rig = load_rig(source, calib_units)
    save_rig(rig, target, units)
    out.print(f"wrote {target} ({FORMATS[fmt]}, {rig.n} cameras: {', '.join(rig.names)})", highlight=False)
