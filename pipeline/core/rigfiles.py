"""N-camera rig files in the formats other tools write, read into a :class:`~pipeline.core.camera.Rig`
and written back exactly (every number as Python's shortest round-tripping repr, or OpenCV's 17
significant digits):

- Anipose / Pose2Sim TOML (``calib.toml``): ``[cam_N] name, size, matrix, distortions (k1 k2 p1
  p2 k3: k3 kept), rotation (Rodrigues), translation``;
- Qualisys ``.qca.txt`` (XML), read as Pose2Sim reads it: camera position in mm and orientation,
  intrinsics in 1/64 sub-pixels, camera axes turned by π about x to OpenCV's;
- OpenCV ``FileStorage`` YAML/XML: one file for the rig (``nb_cameras``, ``K_i D_i R_i T_i
  image_size_i``), or a folder of one file per camera (``camera_matrix``,
  ``distortion_coefficients``, ``image_width``, ``image_height``, ``R``, ``T``, as OpenCV's
  calibration sample names them);
- a plain JSON rig (``rig.json``);
- and the two-camera ``calib.yaml`` of :mod:`pipeline.core.calibration`.

Lengths come out in metres: each format may declare its unit (Qualisys is always mm) and
``units`` overrides, as for ``calib.yaml``."""

from __future__ import annotations

import json
import math
import warnings
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.core.calibration import (
    CALIB_NAMES,
    LENGTH_UNITS,
    _read_mat,
    _read_storage,
    load_calibration,
    save_calibration,
)
from pipeline.core.camera import Camera
from pipeline.core.errors import CalibrationError
from pipeline.core.io import atomic_path
from pipeline.core.lazy import lazy_module
from pipeline.core.rig import Rig

if TYPE_CHECKING:
    import cv2
else:
    cv2 = lazy_module("cv2")  # imported on first use: --help and `methods` need no OpenCV

#: What :func:`save_rig` and ``stereotrack rig convert`` write, by the output's name.
FORMATS = {"toml": "Anipose/Pose2Sim TOML", "qca": "Qualisys .qca.txt", "json": "JSON rig",
           "yaml": "OpenCV FileStorage rig (one file)", "folder": "OpenCV FileStorage, one file per camera",
           "calib": "stereotrack calib.yaml (two cameras)"}
#: A clip folder's rig files, in the order they are looked for (after ``calib.yaml``).
RIG_NAMES = ("calib.toml", "rig.json", "rig.yaml", "rig.yml", "rig.xml")
#: Cameras further apart than this with no declared unit are almost surely not in metres (a motion
#: capture room is rarely over 15 m across; Anipose's files are in the board's unit, often mm).
SUSPICIOUS_SPAN = 20.0
_FLIP = np.diag([1.0, -1.0, -1.0])  # Qualisys camera axes (y up, z back) ↔ OpenCV's: Rx(π)


def format_of(path: str | Path) -> str:
    """The format a rig path names: by suffix, a folder (or a name without suffix) for the
    per-camera layout, and ``calib.*`` for the two-camera calib.yaml."""
    path = Path(path)
    name = path.name.lower()
    if name.endswith((".qca.txt", ".qca")):
        return "qca"
    if path.is_dir() or not path.suffix:
        return "folder"
    if name in CALIB_NAMES and name != "calib.json":
        return "calib"
    suffix = path.suffix.lower().lstrip(".")
    fmt = {"toml": "toml", "json": "json", "yaml": "yaml", "yml": "yaml", "xml": "yaml"}.get(suffix)
    if fmt is None:
        raise CalibrationError(f"unknown rig format '.{suffix}' (use .toml, .qca.txt, .json, .yaml, .xml or a folder)",
                               path)
    return fmt


def find_rig(folder: str | Path) -> Path | None:
    """A clip folder's calibration, whichever format it is in (None when it has none)."""
    folder = Path(folder)
    for name in (*CALIB_NAMES, *RIG_NAMES):
        if (folder / name).is_file():
            return folder / name
    qca = sorted(folder.glob("*.qca.txt"))
    return qca[0] if qca else None


def load_rig(path: str | Path, units: str | None = None) -> Rig:
    """Read a rig from any format of :data:`FORMATS` (a folder: its calibration file, else the
    per-camera layout); ``units`` (m, cm, mm) overrides the unit a file declares."""
    path = Path(path)
    if units is not None and units not in LENGTH_UNITS:
        raise CalibrationError(f"unknown length unit {units!r} (use m, cm or mm)")
    if path.is_dir() and (found := find_rig(path)) is not None:
        path = found
    elif not path.exists():
        raise CalibrationError("calibration file not found", path)
    fmt = format_of(path)
    if fmt == "calib" or (fmt == "yaml" and "K1" in _read_storage(path)):
        stereo = load_calibration(path, units)
        return Rig.from_stereo(stereo)
    reader = {"toml": _read_toml, "qca": _read_qca, "json": _read_json, "yaml": _read_yaml_rig,
              "folder": _read_folder}[fmt]
    rig, declared = reader(path)
    rig = _in_metres(rig, declared, units, path)
    rig.check(path)
    return rig


def save_rig(rig: Rig, path: str | Path, units: str | None = None) -> None:
    """Write ``rig`` in the format ``path`` names (atomically; a folder: one file per camera);
    ``units`` declares the length unit the file's translations are written in."""
    path = Path(path)
    fmt = format_of(path)
    scaled = rig if units is None else _scaled(rig, 1.0 / LENGTH_UNITS[units])
    if fmt == "calib":
        if rig.n != 2:
            raise CalibrationError(f"calib.yaml holds two cameras; this rig has {rig.n} (write .toml, .json or .yaml)",
                                   path)
        save_calibration(rig.stereo(0, 1), path, units)
        return
    if fmt == "qca":
        _write_qca(_scaled(rig, 1000.0), path)
        return
    if fmt == "folder":
        _write_folder(scaled, path, units)
        return
    text = {"toml": _toml_text, "json": _json_text}.get(fmt)
    if text is not None:
        with atomic_path(path) as tmp:
            Path(tmp).write_text(text(scaled, units), encoding="utf-8")
        return
    _write_yaml_rig(scaled, path, units)


def _scaled(rig: Rig, s: float) -> Rig:
    """The rig with every translation multiplied by ``s`` (a change of length unit)."""
    cams = tuple(Camera(c.K, c.R, np.ravel(c.t) * s, c.D) for c in rig.cameras)
    return Rig(cams, rig.names, rig.sizes, rig.offsets)


def _in_metres(rig: Rig, declared: str | None, units: str | None, path: Path) -> Rig:
    """The rig's translations in metres, from the unit given (``units``) or declared, with the
    warnings of ``calib.yaml``: an override that contradicts the file, a long unit-less baseline."""
    if units is not None and declared is not None and units != declared:
        warnings.warn(f"{path}: --calib-units {units} overrides the unit the file declares (units: {declared})",
                      stacklevel=3)
    unit = units or declared
    if unit is None and rig.baseline > SUSPICIOUS_SPAN:
        likely, scale = ("millimetres", "mm") if rig.baseline > 300 else ("centimetres", "cm")
        warnings.warn(f"{path}: the cameras are {rig.baseline:g} apart with no declared unit; this looks like {likely}: "
                      f"declare 'units: {scale}' in the file or pass --calib-units {scale}", stacklevel=3)
    return rig if unit in (None, "m") else _scaled(rig, LENGTH_UNITS[unit])


# --------------------------------------------------------------------------------------------
# checked values
# --------------------------------------------------------------------------------------------


def _array(value: Any, shape: tuple[int, ...], what: str, path: Path) -> np.ndarray:
    try:
        a = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise CalibrationError(f"{what} is not a list of numbers", path) from None
    if a.size != int(np.prod(shape)):
        raise CalibrationError(f"{what} has {a.size} values, expected {int(np.prod(shape))}", path)
    if not np.all(np.isfinite(a)):
        raise CalibrationError(f"{what} contains NaN or infinite values", path)
    return a.reshape(shape)


def _size(value: Any, what: str, path: Path) -> tuple[int, int]:
    a = _array(value, (2,), what, path)
    if not np.all(a == np.round(a)) or np.any(a <= 0):
        raise CalibrationError(f"{what} {a.tolist()} is not two positive whole numbers", path)
    return int(a[0]), int(a[1])


def _dist(value: Any, what: str, path: Path) -> np.ndarray:
    d = np.ravel(_array(value, (np.size(value),), what, path))
    if d.size not in (4, 5, 8, 12, 14):
        raise CalibrationError(f"{what} has {d.size} distortion coefficients; expected 4, 5, 8, 12 or 14", path)
    return d


def _camera(K: np.ndarray, D: np.ndarray, R: np.ndarray, t: np.ndarray, what: str, path: Path) -> Camera:
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise CalibrationError(f"{what}: not a camera matrix (positive focal lengths, last row 0 0 1)", path)
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise CalibrationError(f"{what}: the rotation is not a rotation matrix", path)
    return Camera(K, R, np.ravel(t).astype(float), D)


def _unit(value: Any, path: Path) -> str | None:
    if value is None:
        return None
    text = str(value).strip().lower()
    if text not in LENGTH_UNITS:
        raise CalibrationError(f"field 'units' must be m, cm or mm, not {value!r}", path)
    return text


def _rodrigues(rvec: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3, 1))[0]


def _rvec(R: np.ndarray) -> list[float]:
    return cv2.Rodrigues(R)[0].ravel().tolist()


def _num(x: float) -> str:
    """A float as the shortest text that reads back to the same double."""
    return repr(float(x))


# --------------------------------------------------------------------------------------------
# Anipose / Pose2Sim TOML
# --------------------------------------------------------------------------------------------


def _read_toml(path: Path) -> tuple[Rig, str | None]:
    import tomllib

    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"not a readable TOML file ({exc})", path) from None
    meta = data.get("metadata", {}) if isinstance(data.get("metadata", {}), dict) else {}
    cams, names, sizes, offsets = [], [], [], []
    for key, d in data.items():
        if key == "metadata" or not isinstance(d, dict):
            continue
        if d.get("fisheye"):
            raise CalibrationError(f"[{key}] is a fisheye camera: stereotrack models pinhole lenses only", path)
        missing = [k for k in ("matrix", "distortions", "rotation", "translation", "size") if k not in d]
        if missing:
            raise CalibrationError(f"[{key}] lacks {', '.join(missing)}", path)
        K = _array(d["matrix"], (3, 3), f"[{key}] matrix", path)
        R = _rodrigues(_array(d["rotation"], (3,), f"[{key}] rotation", path))
        cams.append(_camera(K, _dist(d["distortions"], f"[{key}] distortions", path), R,
                            _array(d["translation"], (3,), f"[{key}] translation", path), f"[{key}]", path))
        names.append(str(d.get("name", key)))
        sizes.append(_size(d["size"], f"[{key}] size", path))
        offsets.append(float(d.get("time_offset", 0.0)))
    if not cams:
        raise CalibrationError("no [cam_N] tables: not an Anipose/Pose2Sim calibration", path)
    return Rig(tuple(cams), tuple(names), tuple(sizes), tuple(offsets)), _unit(meta.get("units"), path)


def _toml_text(rig: Rig, units: str | None) -> str:
    def vec(v) -> str:
        return "[ " + ", ".join(_num(x) for x in np.ravel(v)) + ",]"

    out = []
    for k, (cam, name, size, off) in enumerate(zip(rig.cameras, rig.names, rig.sizes, rig.offsets, strict=True)):
        out += [f"[cam_{k}]", f"name = {json.dumps(name)}", f"size = [ {float(size[0])!r}, {float(size[1])!r},]",
                "matrix = [ " + ", ".join(vec(row) for row in cam.K) + ",]",
                f"distortions = {vec(cam.D)}", f"rotation = {vec(_rvec(cam.R))}", f"translation = {vec(cam.t)}"]
        if off:
            out.append(f"time_offset = {_num(off)}")
        out.append("")
    out += ["[metadata]", "adjusted = false", "error = 0.0", f'units = "{units or "m"}"']
    return "\n".join(out) + "\n"


# --------------------------------------------------------------------------------------------
# Qualisys .qca.txt
# --------------------------------------------------------------------------------------------

_QCA_INTRINSIC = ("focalLengthU", "focalLengthV", "centerPointU", "centerPointV", "skew", "radialDistortion1",
                  "radialDistortion2", "radialDistortion3", "tangentalDistortion1", "tangentalDistortion2")


def _read_qca(path: Path) -> tuple[Rig, str | None]:
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"not a readable Qualisys calibration (XML: {exc})", path) from None
    cams, names, sizes = [], [], []
    for k, tag in enumerate(root.findall("cameras/camera")):
        what = f"camera {tag.get('serial') or k}"
        fov, tr, intr = tag.find("fov_video"), tag.find("transform"), tag.find("intrinsic")
        if fov is None or tr is None or intr is None:
            raise CalibrationError(f"{what} lacks fov_video, transform or intrinsic", path)
        left, top = _attr(fov, "left", what, path), _attr(fov, "top", what, path)
        sizes.append(_size([_attr(fov, "right", what, path) - left + 1, _attr(fov, "bottom", what, path) - top + 1],
                           f"{what} fov_video", path))
        i = {a: _attr(intr, a, what, path) / 64.0 for a in _QCA_INTRINSIC}
        K = np.array([[i["focalLengthU"], i["skew"], i["centerPointU"] - left],
                      [0.0, i["focalLengthV"], i["centerPointV"] - top], [0.0, 0.0, 1.0]])
        D = np.array([i["radialDistortion1"], i["radialDistortion2"], i["tangentalDistortion1"],
                      i["tangentalDistortion2"], i["radialDistortion3"]])
        M = np.array([[_attr(tr, f"r{r}{c}", what, path) for c in (1, 2, 3)] for r in (1, 2, 3)])
        pos = np.array([_attr(tr, a, what, path) for a in "xyz"])
        R = _FLIP @ M
        cams.append(_camera(K, D, R, -R @ pos, what, path))
        names.append(tag.get("serial") or f"cam{k}")
    if not cams:
        raise CalibrationError("no <cameras><camera> entries: not a Qualisys calibration", path)
    return Rig(tuple(cams), tuple(names), tuple(sizes)), "mm"


def _attr(node: ET.Element, name: str, what: str, path: Path) -> float:
    value = node.get(name)
    if value is None:
        raise CalibrationError(f"{what}: <{node.tag}> lacks '{name}'", path)
    try:
        x = float(value)
    except ValueError:
        raise CalibrationError(f"{what}: <{node.tag}> {name}={value!r} is not a number", path) from None
    if not math.isfinite(x):
        raise CalibrationError(f"{what}: <{node.tag}> {name} is not finite", path)
    return x


def _write_qca(rig_mm: Rig, path: Path) -> None:
    root = ET.Element("calibration", {"source": "stereotrack", "type": "regular"})
    cameras = ET.SubElement(root, "cameras")
    for cam, name, (w, h) in zip(rig_mm.cameras, rig_mm.names, rig_mm.sizes, strict=True):
        tag = ET.SubElement(cameras, "camera", {"active": "1", "serial": name, "model": "none", "viewrotation": "0"})
        box = {"left": "0", "top": "0", "right": str(w - 1), "bottom": str(h - 1)}
        ET.SubElement(tag, "fov_marker", box)
        ET.SubElement(tag, "fov_video", box)
        M = _FLIP @ cam.R
        pos = cam.center
        attrs = {a: _num(v) for a, v in zip("xyz", pos, strict=True)}
        attrs.update({f"r{r + 1}{c + 1}": _num(M[r, c]) for r in range(3) for c in range(3)})
        ET.SubElement(tag, "transform", attrs)
        D = np.r_[np.ravel(cam.D), np.zeros(5)][:5]
        if np.any(np.ravel(cam.D)[5:]):
            raise CalibrationError(f"camera {name} has rational/thin-prism distortion, which .qca.txt cannot hold", path)
        vals = (cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2], cam.K[0, 1], D[0], D[1], D[4], D[2], D[3])
        ET.SubElement(tag, "intrinsic", {a: _num(v * 64.0) for a, v in zip(_QCA_INTRINSIC, vals, strict=True)})
    ET.indent(root)
    with atomic_path(path) as tmp:
        ET.ElementTree(root).write(tmp, encoding="utf-8", xml_declaration=True)


# --------------------------------------------------------------------------------------------
# JSON
# --------------------------------------------------------------------------------------------


def _read_json(path: Path) -> tuple[Rig, str | None]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise CalibrationError(f"not a readable JSON rig ({exc})", path) from None
    if not isinstance(data, dict) or not isinstance(data.get("cameras"), list):
        raise CalibrationError("not a JSON rig (expected {\"cameras\": [...]})", path)
    cams, names, sizes, offsets = [], [], [], []
    for k, d in enumerate(data["cameras"]):
        what = f"cameras[{k}]"
        if not isinstance(d, dict) or any(key not in d for key in ("K", "R", "t", "size")):
            raise CalibrationError(f"{what} needs K, R, t and size", path)
        cams.append(_camera(_array(d["K"], (3, 3), f"{what}.K", path), _dist(d.get("D", [0.0] * 5), f"{what}.D", path),
                            _array(d["R"], (3, 3), f"{what}.R", path), _array(d["t"], (3,), f"{what}.t", path), what,
                            path))
        names.append(str(d.get("name", f"cam{k}")))
        sizes.append(_size(d["size"], f"{what}.size", path))
        offsets.append(float(d.get("time_offset", 0.0)))
    return Rig(tuple(cams), tuple(names), tuple(sizes), tuple(offsets)), _unit(data.get("units"), path)


def _json_text(rig: Rig, units: str | None) -> str:
    cams = [{"name": name, "size": list(size), "K": cam.K.tolist(), "D": np.ravel(cam.D).tolist(),
             "R": cam.R.tolist(), "t": np.ravel(cam.t).tolist(), "time_offset": off}
            for cam, name, size, off in zip(rig.cameras, rig.names, rig.sizes, rig.offsets, strict=True)]
    return json.dumps({"format": "stereotrack rig", "units": units or "m", "cameras": cams}, indent=1) + "\n"


# --------------------------------------------------------------------------------------------
# OpenCV FileStorage: one file, or one file per camera
# --------------------------------------------------------------------------------------------


def _read_yaml_rig(path: Path) -> tuple[Rig, str | None]:
    fs = _read_storage(path)
    n = fs.get("nb_cameras")
    if not isinstance(n, (int, float)) or n != int(n) or n < 1:
        raise CalibrationError("not an OpenCV rig file (needs nb_cameras, or K1 K2 R T for two cameras)", path)
    cams, names, sizes, offsets = [], [], [], []
    for k in range(int(n)):
        cams.append(_camera(_read_mat(fs, f"K_{k}", path, (3, 3)), _dist(_read_mat(fs, f"D_{k}", path, None), f"D_{k}",
                                                                        path),
                            _read_mat(fs, f"R_{k}", path, (3, 3)), _read_mat(fs, f"T_{k}", path, (3,)), f"camera {k}",
                            path))
        names.append(str(fs.get(f"camera_name_{k}", f"cam{k}")))
        sizes.append(_size(_read_mat(fs, f"image_size_{k}", path, (2,)), f"image_size_{k}", path))
        offsets.append(float(fs.get(f"time_offset_{k}", 0.0)))
    return Rig(tuple(cams), tuple(names), tuple(sizes), tuple(offsets)), _unit(fs.get("units"), path)


def _write_storage(path: Path, entries: list[tuple[str, Any]]) -> None:
    with atomic_path(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        for key, value in entries:
            fs.write(key, value)
        fs.release()


def _camera_entries(cam: Camera, suffix: str, keys: tuple[str, str, str, str]) -> list[tuple[str, Any]]:
    K, D, R, T = keys
    return [(K + suffix, cam.K), (D + suffix, np.ravel(cam.D).reshape(1, -1).astype(float)), (R + suffix, cam.R),
            (T + suffix, np.ravel(cam.t).reshape(3, 1).astype(float))]


def _write_yaml_rig(rig: Rig, path: Path, units: str | None) -> None:
    entries: list[tuple[str, Any]] = [("units", units or "m"), ("nb_cameras", rig.n)]
    for k, (cam, name, size, off) in enumerate(zip(rig.cameras, rig.names, rig.sizes, rig.offsets, strict=True)):
        entries += [(f"camera_name_{k}", name), (f"image_size_{k}", np.array(size, dtype=float).reshape(1, 2)),
                    (f"time_offset_{k}", float(off))]
        entries += _camera_entries(cam, f"_{k}", ("K", "D", "R", "T"))
    _write_storage(path, entries)


_PER_CAMERA_KEYS = ("camera_matrix", "distortion_coefficients", "R", "T")


def _read_folder(path: Path) -> tuple[Rig, str | None]:
    files = sorted(p for p in path.iterdir() if p.suffix.lower() in (".yml", ".yaml", ".xml")) if path.is_dir() else []
    if len(files) < 2:
        raise CalibrationError("no rig file here, nor two or more per-camera .yml files", path)
    stores = sorted(((_read_storage(f), f) for f in files), key=lambda sf: float(sf[0].get("camera_index", 0)))
    cams, names, sizes, offsets, units = [], [], [], [], set()
    for fs, f in stores:
        K, D, R, T = (_read_mat(fs, k, f, s) for k, s in zip(_PER_CAMERA_KEYS, ((3, 3), None, (3, 3), (3,)), strict=True))
        cams.append(_camera(K, _dist(D, "distortion_coefficients", f), R, T, f.name, f))
        names.append(str(fs.get("camera_name", f.stem)))
        sizes.append(_size([fs.get("image_width"), fs.get("image_height")], "image_width/image_height", f))
        offsets.append(float(fs.get("time_offset", 0.0)))
        units.add(_unit(fs.get("units"), f))
    if len(units) > 1:
        raise CalibrationError(f"the camera files declare different units ({', '.join(map(str, units))})", path)
    return Rig(tuple(cams), tuple(names), tuple(sizes), tuple(offsets)), units.pop()


def _write_folder(rig: Rig, path: Path, units: str | None) -> None:
    if path.exists() and not path.is_dir():
        raise CalibrationError("exists and is not a folder", path)
    path.mkdir(parents=True, exist_ok=True)
    for k, (cam, name, (w, h), off) in enumerate(zip(rig.cameras, rig.names, rig.sizes, rig.offsets, strict=True)):
        entries: list[tuple[str, Any]] = [("camera_index", k), ("camera_name", name), ("units", units or "m"),
                                          ("image_width", int(w)), ("image_height", int(h)), ("time_offset", float(off))]
        stem = name if name.replace("_", "").replace("-", "").isalnum() else f"cam{k}"
        _write_storage(path / f"{stem}.yml", entries + _camera_entries(cam, "", _PER_CAMERA_KEYS))
