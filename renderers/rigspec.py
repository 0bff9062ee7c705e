"""A scenario's rig: the stereo pair (parameters, a free layout of the second camera, a calibration
file) or N cameras (a ring around the volume, or a rig file of any format read into ``views``),
its timing imperfections and the calibration error a user's calibration would have."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from pipeline.core.camera import StereoRig
from pipeline.core.errors import ScenarioError
from pipeline.core.rig import Rig

Vec3 = tuple[float, float, float]
Color = tuple[int, int, int]


class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # NaN or inf: an error naming the field


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


class ViewSpec(_Model):
    """One camera of a rig of N cameras, spelled out (what ``rig.ring`` and an N-camera
    ``rig.calibration`` are read into): its name, image size, intrinsics, distortion, world →
    camera pose (world: the first camera's frame), time offset and drop rate."""

    name: str = Field(min_length=1, pattern=r"^[A-Za-z0-9_-]+$")
    width: int = Field(gt=0, le=8192)
    height: int = Field(gt=0, le=8192)
    K: tuple[Vec3, Vec3, Vec3]
    D: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0)
    R: tuple[Vec3, Vec3, Vec3] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    T: Vec3 = (0.0, 0.0, 0.0)
    #: this camera's frame k is exposed at ``k/fps + time_offset_s``
    time_offset_s: float = 0.0
    drop_rate: float = Field(0.0, ge=0, lt=1)


class RingSpec(_Model):
    """``cameras`` cameras evenly on a circle of ``radius`` m around a point ``distance`` m in front
    of the first camera, ``height`` m above it (negative: higher, y points down), all looking at it:
    the motion-capture layout. They share the rig's width, height, focal length and distortion."""

    cameras: int = Field(4, ge=2, le=32)
    radius: float = Field(2.0, gt=0)
    height: float = -0.8


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
    #: a ring of N cameras around the working volume (read into ``views``)
    ring: RingSpec | None = None
    #: N cameras spelled out (from ``ring`` or an N-camera ``calibration``); None: the stereo pair
    views: list[ViewSpec] | None = None

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
        if sum(x is not None for x in (self.calibration, self.right, self.ring)) > 1:
            raise ValueError("give one of 'calibration', 'right' and 'ring'")
        if self.views is not None:
            if len(self.views) < 2:
                raise ValueError("a rig needs at least two cameras")
            if len({v.name for v in self.views}) < len(self.views):
                raise ValueError("the cameras' names repeat")
            if self.sync_offset_s or not isinstance(self.drop_rate, (int, float)):
                raise ValueError("with N cameras give each its time_offset_s and drop_rate in 'views'")
        if self.line_delay_s * self.height > 1.0:
            raise ValueError("line_delay_s × height exceeds one second: a rolling shutter reads a frame within its period")
        return self

    @property
    def drop_rates(self) -> tuple[float, float]:
        r = self.drop_rate
        return (float(r), float(r)) if isinstance(r, (int, float)) else (float(r[0]), float(r[1]))

    @property
    def n_cameras(self) -> int:
        return len(self.views) if self.views is not None else 2

    def camera_names(self) -> tuple[str, ...]:
        """``left``, ``right`` for the stereo pair, else each view's name."""
        return tuple(v.name for v in self.views) if self.views is not None else ("left", "right")

    def size_of(self, camera: int) -> tuple[int, int]:
        """Camera ``camera``'s image size (width, height)."""
        if self.views is not None:
            return self.views[camera].width, self.views[camera].height
        return self.width, self.height

    def time_offsets(self) -> tuple[float, ...]:
        """When each camera exposes frame k, after ``k/fps`` (s)."""
        if self.views is not None:
            return tuple(v.time_offset_s for v in self.views)
        return (0.0, self.sync_offset_s)

    def camera_drop_rates(self) -> tuple[float, ...]:
        """Each camera's share of dropped frames."""
        if self.views is not None:
            return tuple(max(v.drop_rate, float(self.drop_rate)) for v in self.views)  # type: ignore[arg-type]
        return self.drop_rates

    def build_any(self) -> StereoRig | Rig:
        """The stereo pair (:meth:`build`), or the :class:`Rig` of the views."""
        if self.views is None:
            return self.build()
        from pipeline.core.camera import Camera

        cams = tuple(Camera(np.array(v.K), np.array(v.R), np.array(v.T), np.array(v.D)) for v in self.views)
        return Rig(cams, self.camera_names(), tuple(self.size_of(c) for c in range(len(cams))), self.time_offsets())

    def build(self) -> StereoRig:
        """The rig that renders the clip (``calib_true.yaml`` when a calibration error is asked for)."""
        from pipeline.core.camera import Camera

        if self.views is not None:
            raise ValueError("an N-camera rig has no stereo pair: use build_any()")
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

        from pipeline.core.rigfiles import format_of, load_rig

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if format_of(path) != "calib" and (many := load_rig(path)).n != 2:
                return {**data, "rig": {**rig, "views": _views(many)}}
            cal = load_calibration(path) if format_of(path) == "calib" or path.is_dir() else load_rig(path).stereo(0, 1)
    except StereotrackError as exc:
        raise ScenarioError(f"rig.calibration: {exc}", source) from None
    if caught:
        raise ScenarioError(f"rig.calibration: {caught[0].message}", source)
    if cal.image_size == (0, 0):
        raise ScenarioError(f"rig.calibration: {path} records no image size; add image_width/image_height", source)
    mats = {"K1": cal.left.K.tolist(), "D1": cal.left.D.tolist(), "K2": cal.right.K.tolist(), "D2": cal.right.D.tolist(),
            "R": cal.R.tolist(), "T": cal.T.tolist()}
    return {**data, "rig": {**rig, "matrices": mats, "width": cal.image_size[0], "height": cal.image_size[1]}}


def _views(rig: Rig, offsets: bool = True) -> list[dict]:
    """A :class:`Rig` (re-expressed in its first camera's frame) as ``rig.views`` entries."""
    r = rig.in_frame_of(0)
    return [{"name": name, "width": w, "height": h, "K": c.K.tolist(), "D": np.ravel(c.D).tolist(), "R": c.R.tolist(),
             "T": np.ravel(c.t).tolist(), "time_offset_s": float(off) if offsets else 0.0}
            for c, name, (w, h), off in zip(r.cameras, r.names, r.sizes, r.offsets, strict=True)]


def _resolve_ring(data: dict, source: str | Path) -> dict:
    """``rig.ring`` read into ``rig.views`` (cameras ``cam0…`` sharing the rig's width, height,
    focal length and distortion), so the clip's scenario.yaml names every camera."""
    rig = data.get("rig") if isinstance(data, dict) else None
    if not isinstance(rig, dict) or not isinstance(rig.get("ring"), dict) or rig.get("views") is not None:
        return data
    try:
        ring = RingSpec.model_validate(rig["ring"])
        base = RigSpec.model_validate({k: v for k, v in rig.items() if k not in ("ring", "views")})
    except ValidationError:
        return data  # validation proper reports it, with the field's name
    from pipeline.core.camera import Camera
    from pipeline.core.rig import ring_rig

    focal = base.focal if isinstance(base.focal, (int, float)) else base.focal[0]
    made = ring_rig(ring.cameras, ring.radius, ring.height, (base.width, base.height), float(focal))
    if base.distortion is not None:
        D = np.array(base.distortion, float)
        made = Rig(tuple(Camera(c.K, c.R, c.t, D) for c in made.cameras), made.names, made.sizes)
    return {**data, "rig": {**rig, "views": _views(made)}}
