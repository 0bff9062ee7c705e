"""Declarative scenarios: YAML validated with pydantic (an invalid value names the field and file).

A scenario holds the rig, frame count, fps, seed, image noise/blur, background and one or more
objects, each with a motion model (the built-ins live in ``data/scenarios/``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import Field, ValidationError, field_validator, model_validator

from pipeline.core.errors import ScenarioError
from pipeline.core.io import read_yaml_mapping
from renderers.rigspec import (  # noqa: F401  (a scenario's rig, named here for its readers)
    CalibrationErrorSpec,
    CameraPose,
    Color,
    RigMatrices,
    RigSpec,
    RingSpec,
    Vec3,
    ViewSpec,
    _Model,
    _resolve_calibration,
    _resolve_ring,
    _rotation_xyz,
)

#: Folder of built-in scenarios (``data/scenarios`` at the repository root).
BUILTIN_DIR = Path(__file__).resolve().parent.parent / "data" / "scenarios"


class ConstantVelocity(_Model):
    """``p(t) = start + velocity·t``; ``process_noise`` (m/s²) adds white random acceleration."""

    type: Literal["constant_velocity"]
    start: Vec3
    velocity: Vec3
    process_noise: float = Field(0.0, ge=0)


class ConstantAcceleration(_Model):
    """``p(t) = start + velocity·t + acceleration·t²/2``."""

    type: Literal["constant_acceleration"]
    start: Vec3
    velocity: Vec3
    acceleration: Vec3


class Sinusoid(_Model):
    """``p(t) = center + amplitude ⊙ sin(2π·frequency_hz·t + phase)`` per axis."""

    type: Literal["sinusoid"]
    center: Vec3
    amplitude: Vec3
    frequency_hz: float | Vec3 = Field(0.5)
    phase: Vec3 = (0.0, 0.0, 0.0)

    @field_validator("frequency_hz")
    @classmethod
    def _nonneg(cls, v: float | Vec3) -> float | Vec3:
        vals = (v,) if isinstance(v, (int, float)) else v
        if any(f < 0 for f in vals):
            raise ValueError("frequency must be non-negative")
        return v


class FourPointTarget(_Model):
    """The Soifer et al. planar target (Soifer, Fursov & Kharitonov): four markers at ``radius`` from the plate centre,
    1 and 3 on one axis, 2 and 4 on the rotation axis; the plate turns by α about the 2–4 axis with
    ``[α, α̇]' = alpha_matrix [α, α̇] + noise``; its centre moves along the left optical axis with
    ``z̈ = a_z ż + noise``.
    """

    type: Literal["four_point_target"]
    radius: float = Field(0.15, gt=0)
    alpha0: float = Field(math.pi / 6, ge=-1.4, le=1.4)
    alpha_rate0: float = 0.0
    alpha_matrix: tuple[tuple[float, float], tuple[float, float]] = ((0.0, 1.0), (-1.0, -1.73))
    alpha_noise: float = Field(0.0, ge=0)
    distance0: float = Field(2.0, gt=0)
    distance_rate0: float = 0.0
    a_z: float = -0.5
    distance_noise: float = Field(0.0, ge=0)
    axis_angle_deg: float = 0.0
    center_offset: tuple[float, float] = (0.0, 0.0)


Motion = Annotated[ConstantVelocity | ConstantAcceleration | Sinusoid | FourPointTarget, Field(discriminator="type")]


class ObjectSpec(_Model):
    """A tracked object: a coloured sphere marker, or (with four_point_target motion) the target."""

    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_\-]+$")
    color: Color = (230, 30, 30)
    radius: float = Field(0.04, gt=0)
    motion: Motion
    #: four-point target only: the four markers' colours (default: all ``color``) and plate colour.
    point_colors: tuple[Color, Color, Color, Color] | None = None
    plate_color: Color = (235, 235, 235)
    #: surface roughness under lit shading: low values give specular highlights
    roughness: float = Field(0.9, ge=0.0, le=1.0)
    #: markers that look alike: what the detector sees of this marker (its identity stays ``name``);
    #: markers of one colour form a group even without it (named after the colour)
    group: str | None = Field(None, min_length=1, pattern=r"^[A-Za-z0-9_\-]+$")

    @field_validator("color", "plate_color")
    @classmethod
    def _rgb(cls, v: Color) -> Color:
        if any(c < 0 or c > 255 for c in v):
            raise ValueError("colour components must lie in 0..255")
        return v

    @property
    def is_target(self) -> bool:
        return isinstance(self.motion, FourPointTarget)

    def marker_names(self) -> list[str]:
        """Names of the points this object contributes to truth/detections."""
        return [f"{self.name}_{i}" for i in range(1, 5)] if self.is_target else [self.name]

    def marker_colors(self) -> list[Color]:
        if self.is_target:
            return list(self.point_colors) if self.point_colors else [self.color] * 4
        return [self.color]


class Distractor(_Model):
    """An object that is no marker: of another colour (no detector may report it), of a marker's own
    colour (a look-alike), skin-toned, or a neutral occluder passing between a marker and a camera.
    It sits at ``position`` moving at ``velocity``, or follows ``motion`` (any point motion)."""

    shape: Literal["cube", "sphere", "box"] = "cube"
    color: Color = (200, 40, 200)
    size: float = Field(0.08, gt=0)
    #: a box's extents (m), x y z; ``size`` is its largest
    extents: Vec3 | None = None
    position: Vec3 = (0.0, 0.0, 3.0)
    velocity: Vec3 = (0.0, 0.0, 0.0)
    motion: Annotated[ConstantVelocity | ConstantAcceleration | Sinusoid, Field(discriminator="type")] | None = None
    roughness: float = Field(0.9, ge=0.0, le=1.0)


class RenderSpec(_Model):
    """How frames look: shading, sensor noise (grey levels), blur (px), background."""

    shading: Literal["flat", "lit"] = "flat"
    noise_std: float = Field(0.0, ge=0, le=64)
    blur_sigma: float = Field(0.0, ge=0, le=20)
    background: Literal["textured", "plain"] = "textured"
    background_distance: float = Field(8.0, gt=0)
    background_color: Color = (110, 110, 105)
    #: motion blur: the scene integrated over this exposure (s), centred on each frame time, from
    #: ``exposure_samples`` sub-frame renders (not a Gaussian)
    exposure_s: float = Field(0.0, ge=0)
    exposure_samples: int = Field(8, ge=2, le=64)
    #: samples per pixel of the rasteriser's anti-aliasing (0: none). 4 is pyrender's own; off,
    #: 640×480 renders run 1.9× (flat) and 1.4× (lit) faster on llvmpipe, with hard edges
    #: (benchmarks/render.py)
    multisample: int = Field(4, ge=0, le=16)
    #: what draws the frames: ``analytic`` (exact spheres, discs and boxes on the CPU, 16 samples
    #: per edge pixel; flat shading without distractors), ``pyrender`` (OpenGL, the reference), or
    #: ``auto``: analytic wherever it can draw the scene (renderers/raster.py)
    rasteriser: Literal["auto", "analytic", "pyrender"] = "auto"


class Scenario(_Model):
    """A complete declarative scenario; same scenario + same seed ⇒ identical truth."""

    name: str = "scenario"
    description: str = ""
    frames: int = Field(150, gt=0, le=100_000)
    fps: float = Field(30.0, gt=0)
    seed: int = Field(0, ge=0)
    rig: RigSpec = RigSpec()
    render: RenderSpec = RenderSpec()
    objects: list[ObjectSpec] = Field(min_length=1)
    distractors: list[Distractor] = Field(default_factory=list)
    calibration_error: CalibrationErrorSpec | None = None

    def analytic_blocker(self) -> str | None:
        """Why the analytic rasteriser cannot draw this scenario (None when it can)."""
        if self.render.shading != "flat":
            return "lit shading is drawn by pyrender only"
        if self.distractors:
            return "distractors (a segmentation render decides when they hide a marker) are drawn by pyrender only"
        return None

    def analytic(self) -> bool:
        """Whether the analytic rasteriser draws this scenario's frames."""
        return self.render.rasteriser != "pyrender" and self.analytic_blocker() is None

    @model_validator(mode="after")
    def _analytic_possible(self) -> Scenario:
        why = self.analytic_blocker() if self.render.rasteriser == "analytic" else None
        if why is not None:
            raise ValueError(f"render.rasteriser: analytic cannot draw this scenario: {why}; use auto or pyrender")
        return self

    @model_validator(mode="after")
    def _unique_names(self) -> Scenario:
        names = [n for o in self.objects for n in o.marker_names()]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"duplicate object/marker names: {sorted(dup)}")
        if sum(o.is_target for o in self.objects) > 1:
            raise ValueError("at most one four_point_target object per scenario")
        colours: dict[str, set] = {}
        for o in self.objects:
            if o.group is not None:
                colours.setdefault(o.group, set()).add(tuple(o.color))
        for group, cols in colours.items():
            if len(cols) > 1:
                raise ValueError(f"the markers of group {group!r} have different colours: a group is what looks alike")
            if group in names:
                raise ValueError(f"group {group!r} is also a marker's name")
        if self.render.exposure_s > 1.0 / self.fps:
            raise ValueError(f"render.exposure_s {self.render.exposure_s:g} s is longer than the frame period "
                             f"{1.0 / self.fps:g} s")
        if self.rig.views is not None and (any(o.is_target for o in self.objects) or self.calibration_error):
            raise ValueError("a four-point target and calibration_error need a stereo pair, not a rig of "
                             f"{self.rig.n_cameras} cameras")
        if self.rig.line_delay_s * self.rig.height > 1.0 / self.fps:
            raise ValueError("rig.line_delay_s × height is longer than the frame period: the sensor could not read a frame")
        return self

    @property
    def imperfections(self) -> dict[str, object]:
        """What this clip's rig and scene do that an ideal rig does not (recorded in clip.json)."""
        r = self.rig
        out: dict[str, object] = {}
        if r.views is not None:
            return self._view_imperfections()
        rig = r.build()
        if r.calibration is not None:
            out["calibration"] = r.calibration
        if r.right is not None:
            out["layout"] = {"right_center_m": rig.right.center.round(6).tolist(),
                             "right_rotation_deg": list(r.right.rotation_deg)}
        if np.any(rig.left.D) or np.any(rig.right.D):
            out["distortion"] = {"D1": rig.left.D.tolist(), "D2": rig.right.D.tolist()}
        for key in ("sync_offset_s", "line_delay_s", "jitter_s"):
            if getattr(r, key):
                out[key] = getattr(r, key)
        if any(r.drop_rates):
            out["drop_rate"] = list(r.drop_rates)
        if self.render.exposure_s > 0:
            out["exposure_s"] = self.render.exposure_s
            out["exposure_samples"] = self.render.exposure_samples
        if self.calibration_error is not None:
            out["calibration_error"] = self.calibration_error.model_dump()
        return out

    def _view_imperfections(self) -> dict[str, object]:
        """:attr:`imperfections` of an N-camera rig: per camera where it differs from ideal."""
        r, out = self.rig, dict[str, object]()
        views = r.views or []
        if any(np.any(v.D) for v in views):
            out["distortion"] = {v.name: list(v.D) for v in views}
        if any(r.time_offsets()):
            out["time_offsets_s"] = dict(zip(r.camera_names(), r.time_offsets(), strict=True))
        if any(r.camera_drop_rates()):
            out["drop_rate"] = dict(zip(r.camera_names(), r.camera_drop_rates(), strict=True))
        for key in ("line_delay_s", "jitter_s"):
            if getattr(r, key):
                out[key] = getattr(r, key)
        if self.render.exposure_s > 0:
            out["exposure_s"] = self.render.exposure_s
        return out

    @property
    def dt(self) -> float:
        return 1.0 / self.fps

    def marker_names(self) -> list[str]:
        return [n for o in self.objects for n in o.marker_names()]

    def marker_colors(self) -> dict[str, Color]:
        return {n: c for o in self.objects for n, c in zip(o.marker_names(), o.marker_colors(), strict=True)}

    def with_overrides(self, frames: int | None = None, seed: int | None = None) -> Scenario:
        upd: dict[str, object] = {}
        if frames is not None:
            upd["frames"] = frames
        if seed is not None:
            upd["seed"] = seed
        return parse_scenario({**self.model_dump(), **upd}, "--frames/--seed") if upd else self

    def to_yaml(self) -> str:
        return yaml.safe_dump(_plain(self.model_dump(mode="json")), sort_keys=False)


def _plain(obj: object) -> object:
    if isinstance(obj, dict):
        return {k: _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def builtin_scenarios() -> dict[str, Path]:
    """Built-in scenario names → files."""
    return {p.stem: p for p in sorted(BUILTIN_DIR.glob("*.yaml"))}


def resolve_scenario_path(name_or_path: str | Path) -> Path:
    """A path to a YAML file, or the name of a built-in scenario."""
    p = Path(name_or_path)
    if p.is_file():
        return p
    builtins = builtin_scenarios()
    key = p.stem if p.suffix in (".yaml", ".yml") and not p.exists() and p.parent == Path(".") else str(name_or_path)
    if key in builtins:
        return builtins[key]
    raise ScenarioError(
        f"no such scenario file or built-in scenario (built-ins: {', '.join(builtins) or 'none found'})", name_or_path
    )


def load_scenario(name_or_path: str | Path) -> Scenario:
    """Load and validate a scenario; errors name the file and the offending field."""
    path = resolve_scenario_path(name_or_path)
    data = read_yaml_mapping(path, ScenarioError)
    data.setdefault("name", path.stem)
    return parse_scenario(data, path)


def parse_scenario(data: dict, source: str | Path = "<scenario>") -> Scenario:
    """Validate a scenario mapping; pydantic errors become one-line ``ScenarioError``s."""
    data = _resolve_ring(_resolve_calibration(data, source), source)
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        parts = []
        for err in exc.errors()[:3]:
            loc = ".".join(str(x) for x in err["loc"] if not str(x).startswith(("function-", "tagged-union")))
            parts.append(f"{loc or '(top level)'}: {err['msg']}")
        more = f" (+{exc.error_count() - 3} more)" if exc.error_count() > 3 else ""
        raise ScenarioError("invalid scenario: " + "; ".join(parts) + more, source) from None


def marker_groups(scenario: Scenario) -> dict[str, str]:
    """Marker → its group of identical markers: its ``group``, else — when another marker shares its
    colour — the colour's name (``rgb_RRGGBB``); a marker of a colour of its own is in none."""
    plain = [o for o in scenario.objects if not o.is_target]
    shared = {tuple(o.color) for o in plain if sum(tuple(p.color) == tuple(o.color) for p in plain) > 1}
    out = {}
    for o in plain:
        if o.group is not None:
            out[o.name] = o.group
        elif tuple(o.color) in shared:
            out[o.name] = "rgb_" + "".join(f"{c:02x}" for c in o.color)
    return out


def clip_description(scenario: Scenario) -> dict:
    """What a clip rendered from ``scenario`` shows, for ``clip.json``: fps, frames, every marker
    with its colour (the points of a one-colour four-point target grouped under its name), and the
    target's radius and the dynamics the Kalman–Bucy filter assumes. Stages downstream read this
    instead of the scenario model."""
    markers, target = [], None
    groups = marker_groups(scenario)
    for obj in scenario.objects:
        names, cols = obj.marker_names(), obj.marker_colors()
        group = obj.name if obj.is_target and len(set(cols)) == 1 else groups.get(obj.name)
        markers += [{"name": n, "rgb": list(c), "group": group} for n, c in zip(names, cols, strict=True)]
        if isinstance(obj.motion, FourPointTarget):
            m = obj.motion
            target = {"name": obj.name, "radius": m.radius,
                      "config": {"a_alpha": m.alpha_matrix[1][1], "alpha_feedback": [-m.alpha_matrix[1][0], 0.0],
                                 "a_z": m.a_z}}
    out = {"fps": scenario.fps, "frames": scenario.frames, "markers": markers, "target": target}
    if scenario.rig.views is not None:
        out["cameras"] = list(scenario.rig.camera_names())
    if scenario.imperfections:
        out["imperfections"] = scenario.imperfections
    if scenario.render.shading != "flat":
        out["shading"] = scenario.render.shading
    return out
