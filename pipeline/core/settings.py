"""A run's settings and its hooks, each one object.

:class:`RunSettings` is what a run computes with — the command line's options, validated once,
here — and what a batch's manifest records, so that a clip made with other settings is redone.
:class:`RunHooks` is how a run reports as it goes (stage names, progress, decoded frames, each
method's tracks): never recorded, never changing a result. ``stereotrack run``, ``batch``,
``detect`` and ``estimate`` build both and hand them to :func:`pipeline.app.run.process_clip`,
:func:`pipeline.app.batch.run_batch`, :func:`detectors.stage.detect_clip` and
:func:`pipeline.estimate.estimate_clip`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from pipeline.core.errors import StereotrackError

#: the command-line option of each setting, for errors that name what the user typed
OPTIONS = {"detector": "--detector", "methods": "--methods", "markers": "--markers", "roi": "--roi",
           "calib_units": "--calib-units", "configs": "--config", "time_offset": "--time-offset", "fps": "--fps",
           "force_window": "--force", "images": "--no-images", "figures": "--figures", "allow_unequal": "--allow-unequal",
           "target_radius": "target radius", "recording": "recording"}


class RunSettings(BaseModel):
    """What a run computes with (frozen; validated on creation)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    #: a registered detector (``stereotrack methods`` lists them; checked against the registry by the detect stage)
    detector: str = "blob"
    #: the estimators to run; None: every point method (and the target methods on a four-point target)
    methods: tuple[str, ...] | None = None
    #: ``--markers`` specs (resolved already: see :func:`detectors.markers.resolve_marker_specs`); None: the clip's own
    markers: tuple[str, ...] | None = None
    #: meanshift/CamShift's first search window ``x, y, w, h`` (px)
    roi: tuple[int, int, int, int] | None = None
    #: length unit of the calibration's ``T`` (``m``, ``cm``, ``mm``); None: what the file declares, else metres
    calib_units: str | None = None
    #: method → its settings (``--config``), as written: the pipeline still fills in data-driven defaults
    configs: dict[str, dict[str, Any]] | None = None
    #: the right camera's delay: ``auto`` (estimated, applied when significant), ``off``, or seconds
    time_offset: Literal["auto", "off"] | float = "auto"
    #: frames per second, winning over every rate the clip states
    fps: float | None = None
    #: keep a colour learned from a window even when it selects far more than the marker
    force_window: bool = False
    #: truncate left/right footage of unequal lengths instead of refusing it
    allow_unequal: bool = False
    #: the four-point target's radius (m); None: the clip's
    target_radius: float | None = None
    #: write the rerun recording; with ``images`` the frames go into it
    recording: bool = True
    images: bool = True
    #: draw the report's figures
    figures: bool = True

    @field_validator("methods")
    @classmethod
    def _some_methods(cls, v: tuple[str, ...] | None) -> tuple[str, ...] | None:
        if v is not None and not v:
            raise ValueError("needs at least one method name (leave it out for every method)")
        return v

    @field_validator("calib_units")
    @classmethod
    def _unit(cls, v: str | None) -> str | None:
        from pipeline.core.calibration import LENGTH_UNITS  # (OpenCV's import: only when a unit is given)

        if v is not None and v not in LENGTH_UNITS:
            raise ValueError(f"names an unknown length unit {v!r} (known: {', '.join(LENGTH_UNITS)})")
        return v

    @field_validator("fps", "target_radius")
    @classmethod
    def _positive(cls, v: float | None) -> float | None:
        if v is not None and not (math.isfinite(v) and v > 0):
            raise ValueError(f"must be a positive number, not {v:g}")
        return v

    @field_validator("time_offset", mode="before")
    @classmethod
    def _offset(cls, v: Any) -> Any:
        if isinstance(v, str) and v not in ("auto", "off"):
            try:
                v = float(v)
            except ValueError:
                raise ValueError(f"takes auto, off or seconds (e.g. 0.0167), not {v!r}") from None
        if isinstance(v, float) and not math.isfinite(v):
            raise ValueError(f"must be finite, not {v!r}")
        return v

    @classmethod
    def checked(cls, **values: Any) -> RunSettings:
        """The settings, or one :class:`StereotrackError` naming the option that is wrong."""
        try:
            return cls(**values)
        except ValidationError as exc:
            err = exc.errors()[0]
            field = str(err["loc"][0]) if err["loc"] else "settings"
            raise StereotrackError(f"{OPTIONS.get(field, field)} {err['msg'].removeprefix('Value error, ')}") from None

    def record(self, root_markers: list[str] | None = None) -> dict[str, Any]:
        """What a batch's manifest records of these settings (the layout manifests have always had:
        ``fps`` and ``figures`` only when given, so the manifests of earlier batches stay valid)."""
        out: dict[str, Any] = {"detector": self.detector, "methods": _listed(self.methods),
                               "markers": _listed(self.markers), "root_markers": root_markers,
                               "calib_units": self.calib_units, "configs": self.configs, "images": self.images,
                               "time_offset": self.time_offset}
        if self.fps is not None:
            out["fps"] = self.fps
        if self.figures:
            out["figures"] = True
        return out


def _listed(v: tuple[str, ...] | None) -> list[str] | None:
    return list(v) if v is not None else None


@dataclass(frozen=True)
class RunHooks:
    """How a run reports as it goes; none of it changes a result, and none of it is recorded.

    ``stage(name)``: a stage starts (or says more precisely what it counts). ``progress(done,
    total)``: work done within the stage. ``frame(k, left, right)``: each decoded frame pair (the
    recording logs frames as the detect stage decodes them). ``image(camera, k, img)``: what the
    camera's detection worker makes of its image of frame k (the recording's JPEG); with it,
    ``frame(k, *made)`` receives those instead of the images, which then stay with the worker (a
    process of its own). ``method(result, name, tracks, scores)``: each point method's tracks and
    their scores as the method finishes."""

    stage: Callable[[str], None] | None = None
    progress: Callable[[int, int], None] | None = None
    frame: Callable[..., None] | None = None
    image: Callable[[int, int, Any], Any] | None = None
    method: Callable[..., None] | None = None

    def say(self, name: str) -> None:
        if self.stage is not None:
            self.stage(name)

    def tick(self, done: int, total: int) -> None:
        if self.progress is not None:
            self.progress(done, total)
