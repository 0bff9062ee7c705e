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
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from pipeline.core.camera import StereoRig
from pipeline.core.errors import ScenarioError
from pipeline.core.io import read_yaml_mapping

Vec3 = tuple[float, float, float]
Color = tuple[int, int, int]

#: Folder of built-in scenarios (``data/scenarios`` at the repository root).
BUILTIN_DIR = Path(__file__).resolve().parent.parent / "data" / "scenarios"


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class CameraPose(_Model):
    """Where the second camera sits relative to the first: its centre (m) in the first camera's frame
    (x right, y down, z forward) and its orientation, as rotations of its axes about the first
    camera's x, y and z axes (degrees, applied in that order). ``[0.3, 0, 0]`` with no rotation is the
    usual side-by-side rig; ``[-0.3, 0, 0]`` has the second camera on the left, ``[0, -0.3, 0]`` above."""

    position: Vec3
    rotation_deg: Vec3 = (0.0, 0.0, 0.0)

    @field_validator("position")
    @classmethod
    def _apart(cls, v: Vec3) -> Vec3:
        if math.hypot(*v) < 1e-6:
            raise ValueError("the two cameras coincide: give the second camera a position away from the first")
        return v


class RigMatrices(_Model):
    """A rig spelled out (what ``rig.calibration`` is read into, so a clip's scenario.yaml stands alone)."""

    K1: tuple[Vec3, Vec3, Vec3]
    D1: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    K2: tuple[Vec3, Vec3, Vec3]
    D2: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    R: tuple[Vec3, Vec3, Vec3]
    T: Vec3


class RigSpec(_Model):
    """Stereo rig: resolution, focal length(s) in px, principal point, baseline (m), toe-in (deg);
    or a calibration file (``calibration``, relative to the scenario file); or a free layout of the
    second camera (``right``). Lens distortion (OpenCV's 4–14 coefficients) and the rig's timing:
    ``sync_offset_s`` (the right camera's frame k is exposed at ``k/fps + offset``), rolling shutter
    (``line_delay_s`` per image row), frame-time ``jitter_s`` (std, per camera and frame) and dropped
    frames (``drop_rate``, one value or [left, right])."""

    width: int = Field(640, gt=0, le=8192)
    height: int = Field(480, gt=0, le=8192)
    focal: float | tuple[float, float] = 600.0
    principal_point: tuple[float, float] | None = None
    baseline: float = Field(0.3, gt=0)
    toe_in_deg: float = Field(0.0, ge=-45, le=45)
    calibration: str | None = None
    matrices: RigMatrices | None = None
    right: CameraPose | None = None
    distortion: tuple[float, ...] | None = None
    distortion_right: tuple[float, ...] | None = None
    sync_offset_s: float = 0.0
    line_delay_s: float = Field(0.0, ge=0)
    jitter_s: float = Field(0.0, ge=0)
    drop_rate: float | tuple[float, float] = 0.0

    @field_validator("focal")
    @classmethod
    def _positive_focal(cls, v: float | tuple[float, float]) -> float | tuple[float, float]:
        vals = (v,) if isinstance(v, (int, float)) else v
        if any(f <= 0 for f in vals):
            raise ValueError("focal length must be positive")
        return v

    @field_validator("distortion", "distortion_right")
    @classmethod
    def _dist_length(cls, v: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if v is not None and len(v) not in (4, 5, 8, 12, 14):
            raise ValueError(f"OpenCV distortion has 4, 5, 8, 12 or 14 coefficients, not {len(v)}")
        return v

    @field_validator("drop_rate")
    @classmethod
    def _rate(cls, v: float | tuple[float, float]) -> float | tuple[float, float]:
        if any(not 0 <= r < 1 for r in ((v,) if isinstance(v, (int, float)) else v)):
            raise ValueError("a drop rate lies in [0, 1)")
        return v

    @model_validator(mode="after")
    def _one_layout(self) -> RigSpec:
        if self.calibration is not None and self.right is not None:
            raise ValueError("give either 'calibration' or 'right', not both")
        if self.line_delay_s * self.height > 1.0:
            raise ValueError("line_delay_s × height exceeds one second: a rolling shutter reads a frame within its period")
        return self

    @property
    def drop_rates(self) -> tuple[float, float]:
        r = self.drop_rate
        return (float(r), float(r)) if isinstance(r, (int, float)) else (float(r[0]), float(r[1]))

    def build(self) -> StereoRig:
        """The rig that renders the clip (``calib_true.yaml`` when a calibration error is asked for)."""
        from pipeline.core.camera import Camera

        if self.matrices is not None:
            m = self.matrices
            return StereoRig(Camera(np.array(m.K1), D=np.array(m.D1)),
                             Camera(np.array(m.K2), np.array(m.R), np.array(m.T), np.array(m.D2)),
                             (self.width, self.height))
        rig = StereoRig.from_parameters(self.width, self.height, self.focal, self.principal_point, self.baseline,
                                        self.toe_in_deg)
        K = rig.left.K
        R, T = rig.R, rig.T
        if self.right is not None:
            R_wc = _rotation_xyz(self.right.rotation_deg)  # second camera → first camera's frame
            R = R_wc.T
            T = -R @ np.array(self.right.position, float)
        D1 = np.array(self.distortion if self.distortion is not None else (0.0,) * 5, float)
        D2 = np.array(self.distortion_right if self.distortion_right is not None else D1, float)
        return StereoRig(Camera(K.copy(), D=D1), Camera(K.copy(), R, T, D2), rig.image_size)


def _rotation_xyz(deg: Vec3) -> np.ndarray:
    """Rotation about x, then y, then z (degrees): ``Rz @ Ry @ Rx``."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", deg, degrees=True).as_matrix()


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


class CalibrationErrorSpec(_Model):
    """What the user's calibration gets wrong (std devs, drawn once per clip from ``seed``): focal
    lengths (relative), principal points (px), baseline length (relative), the second camera's
    rotation (deg, per axis) and distortion (absolute, on k1 and k2). The clip's calib.yaml is the
    perturbed rig; calib_true.yaml the one that rendered it."""

    focal: float = Field(0.0, ge=0, le=0.5)
    principal_point: float = Field(0.0, ge=0, le=100)
    baseline: float = Field(0.0, ge=0, le=0.5)
    rotation_deg: float = Field(0.0, ge=0, le=10)
    distortion: float = Field(0.0, ge=0, le=1)
    seed: int | None = Field(None, ge=0)


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
    calibration_error: CalibrationErrorSpec | None = None

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
        if self.rig.line_delay_s * self.rig.height > 1.0 / self.fps:
            raise ValueError("rig.line_delay_s × height is longer than the frame period: the sensor could not read a frame")
        return self

    @property
    def imperfections(self) -> dict[str, object]:
        """What this clip's rig and scene do that an ideal rig does not (recorded in clip.json)."""
        r = self.rig
        out: dict[str, object] = {}
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


def _resolve_calibration(data: dict, source: str | Path) -> dict:
    """``rig.calibration: FILE`` (relative to the scenario file) read into ``rig.matrices`` and the
    image size, so that the rig is spelled out wherever the scenario travels (render workers, the
    clip's own scenario.yaml). A file that does not load is an error naming the scenario and field."""
    rig = data.get("rig") if isinstance(data, dict) else None
    if not isinstance(rig, dict) or not isinstance(rig.get("calibration"), str) or rig.get("matrices") is not None:
        return data
    from pipeline.core.calibration import load_calibration
    from pipeline.core.errors import StereotrackError

    base = Path(source).parent if Path(str(source)).is_file() else Path(".")
    path = base / rig["calibration"]
    try:
        import warnings

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            cal = load_calibration(path)
    except StereotrackError as exc:
        raise ScenarioError(f"rig.calibration: {exc}", source) from None
    if caught:
        raise ScenarioError(f"rig.calibration: {caught[0].message}", source)
    if cal.image_size == (0, 0):
        raise ScenarioError(f"rig.calibration: {path} records no image size; add image_width/image_height", source)
    mats = {"K1": cal.left.K.tolist(), "D1": cal.left.D.tolist(), "K2": cal.right.K.tolist(), "D2": cal.right.D.tolist(),
            "R": cal.R.tolist(), "T": cal.T.tolist()}
    return {**data, "rig": {**rig, "matrices": mats, "width": cal.image_size[0], "height": cal.image_size[1]}}


def parse_scenario(data: dict, source: str | Path = "<scenario>") -> Scenario:
    """Validate a scenario mapping; pydantic errors become one-line ``ScenarioError``s."""
    data = _resolve_calibration(data, source)
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
    if scenario.imperfections:
        out["imperfections"] = scenario.imperfections
    return out
