"""Declarative scenarios: YAML validated with pydantic (an invalid value names the field and file).

A scenario holds the rig, frame count, fps, seed, image noise/blur, background and one or more
objects, each with a motion model (SPEC §1; the built-ins live in ``data/scenarios/``).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from pipeline.camera import StereoRig
from pipeline.errors import ScenarioError
from pipeline.io import read_yaml_mapping

Vec3 = tuple[float, float, float]
Color = tuple[int, int, int]

#: Folder of built-in scenarios (``data/scenarios`` at the repository root).
BUILTIN_DIR = Path(__file__).resolve().parent.parent / "data" / "scenarios"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class RigSpec(_Model):
    """Stereo rig: resolution, focal length(s) in px, principal point, baseline (m), toe-in (deg)."""

    width: int = Field(640, gt=0, le=8192)
    height: int = Field(480, gt=0, le=8192)
    focal: float | tuple[float, float] = 600.0
    principal_point: tuple[float, float] | None = None
    baseline: float = Field(0.3, gt=0)
    toe_in_deg: float = Field(0.0, ge=-45, le=45)

    @field_validator("focal")
    @classmethod
    def _positive_focal(cls, v: float | tuple[float, float]) -> float | tuple[float, float]:
        vals = (v,) if isinstance(v, (int, float)) else v
        if any(f <= 0 for f in vals):
            raise ValueError("focal length must be positive")
        return v

    def build(self) -> StereoRig:
        return StereoRig.from_parameters(
            self.width, self.height, self.focal, self.principal_point, self.baseline, self.toe_in_deg
        )


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
    """The Soifer et al. planar target (SPEC §4.8): four markers at ``radius`` from the plate centre,
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
    """A static or moving object of another colour that no detector may report."""

    shape: Literal["cube", "sphere"] = "cube"
    color: Color = (200, 40, 200)
    size: float = Field(0.08, gt=0)
    position: Vec3
    velocity: Vec3 = (0.0, 0.0, 0.0)


class RenderSpec(_Model):
    """How frames look: shading, sensor noise (grey levels), blur (px), background."""

    shading: Literal["flat", "lit"] = "flat"
    noise_std: float = Field(0.0, ge=0, le=64)
    blur_sigma: float = Field(0.0, ge=0, le=20)
    background: Literal["textured", "plain"] = "textured"
    background_distance: float = Field(8.0, gt=0)
    background_color: Color = (110, 110, 105)


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
    distractors: list[Distractor] = []

    @model_validator(mode="after")
    def _unique_names(self) -> Scenario:
        names = [n for o in self.objects for n in o.marker_names()]
        dup = {n for n in names if names.count(n) > 1}
        if dup:
            raise ValueError(f"duplicate object/marker names: {sorted(dup)}")
        if sum(o.is_target for o in self.objects) > 1:
            raise ValueError("at most one four_point_target object per scenario")
        return self

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
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        parts = []
        for err in exc.errors()[:3]:
            loc = ".".join(str(x) for x in err["loc"] if not str(x).startswith(("function-", "tagged-union")))
            parts.append(f"{loc or '(top level)'}: {err['msg']}")
        more = f" (+{exc.error_count() - 3} more)" if exc.error_count() > 3 else ""
        raise ScenarioError("invalid scenario: " + "; ".join(parts) + more, source) from None


def clip_description(scenario: Scenario) -> dict:
    """What a clip rendered from ``scenario`` shows, for ``clip.json``: fps, frames, every marker
    with its colour (the points of a one-colour four-point target grouped under its name), and the
    target's radius and the dynamics the Kalman–Bucy filter assumes. Stages downstream read this
    instead of the scenario model."""
    markers, target = [], None
    for obj in scenario.objects:
        names, cols = obj.marker_names(), obj.marker_colors()
        group = obj.name if obj.is_target and len(set(cols)) == 1 else None
        markers += [{"name": n, "rgb": list(c), "group": group} for n, c in zip(names, cols, strict=True)]
        if isinstance(obj.motion, FourPointTarget):
            m = obj.motion
            target = {"name": obj.name, "radius": m.radius,
                      "config": {"a_alpha": m.alpha_matrix[1][1], "alpha_feedback": [-m.alpha_matrix[1][0], 0.0],
                                 "a_z": m.a_z}}
    return {"fps": scenario.fps, "frames": scenario.frames, "markers": markers, "target": target}
