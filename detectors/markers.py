"""Marker lists (``markers.yaml``, ``--markers``): which colours the detect stage looks for, read
and validated against the blob detector's colour syntax, by one precedence for every command."""

from __future__ import annotations

import warnings
from pathlib import Path

import yaml

from detectors.blob import MarkerColor
from pipeline.core.clip import MARKERS_FILE
from pipeline.core.errors import StereotrackError, first_line
from pipeline.core.io import safe_yaml_loader


def read_markers_file(path: str | Path) -> list[str]:
    """``markers.yaml``: a list of ``--markers`` specs, or a mapping with key ``markers`` holding one."""
    path = Path(path)
    try:
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=safe_yaml_loader())
    except (OSError, yaml.YAMLError, UnicodeDecodeError) as exc:
        raise StereotrackError(f"cannot read marker list ({first_line(exc)})", path) from None
    if isinstance(data, dict):
        if set(data) != {"markers"}:
            raise StereotrackError(f"expected one key 'markers', found {', '.join(map(str, data))}", path)
        data = data["markers"]
    if not isinstance(data, list) or not data or not all(isinstance(s, str) for s in data):
        raise StereotrackError("'markers' must be a non-empty list of specs such as 'ball:30-60:60:60', "
                               "'red=#e61e1e' or 'ball@100,120,40,40'", path)
    for spec in data:  # validate now, naming the file
        try:
            if MarkerColor.parse_window(spec) is None:
                MarkerColor.parse(spec)
        except StereotrackError as exc:
            raise StereotrackError(str(exc), path) from None
    return data


def resolve_marker_specs(clip: Path, specs: list[str] | None, default: list[str] | None = None) -> list[str] | None:
    """The marker specs that apply to ``clip``, by one precedence: ``--markers`` (``specs``), else the
    clip's own ``markers.yaml``, else ``default`` (a batch root's ``markers.yaml``); None leaves the
    colours to a rendered clip's description. ``--markers`` that differ from the clip's own file are
    used with a warning naming both."""
    folder = clip if clip.is_dir() else clip.parent
    own = folder / MARKERS_FILE
    if specs:
        if own.is_file() and read_markers_file(own) != list(specs):
            warnings.warn(f"{own}: --markers {','.join(specs)} used instead of this file's "
                          f"{','.join(read_markers_file(own))}", stacklevel=2)
        return specs
    if own.is_file():
        return read_markers_file(own)
    return default
