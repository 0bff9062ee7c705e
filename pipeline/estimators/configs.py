"""Estimator settings from a file (``--config FILE``): YAML mapping a method name to the fields of
its pydantic config, validated against the registry with errors naming the file and the field."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pydantic import ValidationError

from pipeline.core.errors import StereotrackError
from pipeline.core.io import read_yaml_mapping
from pipeline.estimators import registry


def load_method_configs(path: str | Path) -> dict[str, dict[str, Any]]:
    """``{method: {field: value}}`` from ``path``, each validated by its method's config class.

    The values are returned as written (not with defaults filled in) so that the pipeline can
    still supply data-driven defaults such as ``pixel_sigma``; ``metrics.json`` records the
    resolved config of every method that ran.
    """
    data = read_yaml_mapping(path)
    reg = registry()
    out: dict[str, dict[str, Any]] = {}
    for method, fields in data.items():
        if method not in reg:
            raise StereotrackError(f"unknown method {method!r} (known: {', '.join(reg)})", path)
        if fields is None:
            fields = {}
        if not isinstance(fields, dict):
            raise StereotrackError(f"{method}: expected a mapping of config fields, found {type(fields).__name__}", path)
        try:
            reg[method].Config.model_validate(fields)
        except ValidationError as exc:
            err = exc.errors()[0]
            where = ".".join(str(p) for p in (method, *err["loc"]))
            raise StereotrackError(f"{where}: {err['msg']}", path) from None
        out[str(method)] = fields
    return out
