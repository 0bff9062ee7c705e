"""Calibration files: OpenCV FileStorage YAML/XML (one stereo file, or the stereo_calib sample's
intrinsics + extrinsics pair) and JSON, read into a :class:`~pipeline.core.camera.StereoRig` and
written back, with their units. The camera model itself lives in :mod:`pipeline.core.camera`;
this module knows only the file formats."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.core.camera import Camera, StereoRig
from pipeline.core.errors import CalibrationError
from pipeline.core.io import atomic_path, safe_yaml_loader
from pipeline.core.lazy import lazy_module

if TYPE_CHECKING:
    import cv2
else:
    cv2 = lazy_module("cv2")  # imported on first use: --help and `methods` need no OpenCV

# ---------------------------------------------------------------------------------------------
# Calibration files
# ---------------------------------------------------------------------------------------------

_DIST_LENGTHS = (4, 5, 8, 12, 14)

#: File names of a clip folder's calibration, in the order they are looked for.
CALIB_NAMES = ("calib.yaml", "calib.yml", "calib.xml", "calib.json")
#: OpenCV ``stereo_calib`` sample layout: intrinsics + extrinsics files.
INTRINSICS_NAMES = ("intrinsics.yml", "intrinsics.yaml", "intrinsics.xml")
EXTRINSICS_NAMES = ("extrinsics.yml", "extrinsics.yaml", "extrinsics.xml")
#: Length units a calibration may declare (``units: mm`` in calib.yaml), as metres per unit.
LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
#: A baseline longer than this with no declared unit is almost surely not in metres.
SUSPICIOUS_BASELINE = 5.0


def has_calibration(folder: str | Path) -> bool:
    """Whether ``folder`` holds a calibration in one of the layouts :func:`load_calibration` reads."""
    folder = Path(folder)
    names = (*CALIB_NAMES, *INTRINSICS_NAMES)
    return folder.is_dir() and any((folder / n).is_file() for n in names)


class _Matrix:
    """An ``!!opencv-matrix`` node (rows, cols, row-major data) or an ``!!opencv-nd-matrix`` one
    (sizes, data; read as a column)."""

    def __init__(self, node: dict) -> None:
        self.rows, self.cols, self.data = node.get("rows"), node.get("cols"), node.get("data")
        sizes = node.get("sizes")
        if self.rows is None and isinstance(sizes, list) and all(isinstance(n, int) and n >= 0 for n in sizes):
            self.rows, self.cols = int(np.prod(sizes)), 1


def _yaml_loader():
    base: Any = safe_yaml_loader()

    class Loader(base):
        """PyYAML with OpenCV's ``!!opencv-matrix`` tag."""

    def matrix(loader, node):
        return _Matrix(loader.construct_mapping(node, deep=True))

    Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", matrix)
    Loader.add_constructor("tag:yaml.org,2002:opencv-nd-matrix", matrix)
    return Loader


def _read_storage(path: Path) -> dict:
    """The top-level entries of an OpenCV FileStorage file. YAML and JSON are parsed in Python, so
    that a malformed file is an error naming it (OpenCV's own YAML reader can corrupt its heap on
    some malformed files and abort the process later); XML goes through ``cv2.FileStorage``."""
    if not path.is_file():
        raise CalibrationError("calibration file not found", path)
    if path.suffix.lower() == ".xml":
        return _read_xml_storage(path)
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError:
        raise CalibrationError("not a readable calibration file (not text)", path) from None
    except OSError as exc:
        raise CalibrationError(f"cannot read ({exc.strerror})", path) from None
    if text.lstrip().startswith("{"):
        import json

        try:
            data = json.loads(text, object_hook=lambda d: _Matrix(d) if str(d.get("type_id", "")).startswith("opencv-")
                              else d)
        except ValueError as exc:
            raise CalibrationError(f"not a readable calibration file (JSON: {exc})", path) from None
    else:
        import yaml

        body = "\n".join("" if line.startswith("%") else line for line in text.splitlines())  # %YAML:1.0 / %YAML 1.2
        try:
            data = yaml.load(body, Loader=_yaml_loader())
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            where = f" at line {mark.line + 1}" if mark is not None else ""
            raise CalibrationError(f"not a readable calibration file (YAML: {getattr(exc, 'problem', None) or exc}{where})",
                                   path) from None
    if not isinstance(data, dict):
        raise CalibrationError("not a readable calibration file (expected a mapping of named entries)", path)
    return data


def _read_xml_storage(path: Path) -> dict:
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        raise CalibrationError(f"not a readable OpenCV FileStorage file ({_first_line(exc)})", path) from None
    if not fs.isOpened():
        raise CalibrationError("not a readable OpenCV FileStorage file", path)
    try:
        out: dict = {}
        for key in fs.root().keys():
            node = fs.getNode(key)
            if node.empty():
                continue
            if node.isString():
                out[key] = node.string()
            elif node.isInt():
                out[key] = int(node.real())
            elif node.isSeq():
                out[key] = [node.at(i).real() for i in range(node.size())]
            elif node.isMap():
                m = node.mat()
                out[key] = _Matrix({"rows": m.shape[0], "cols": m.shape[1] if m.ndim > 1 else 1,
                                    "data": m.ravel().tolist()}) if m is not None else {}
            else:
                out[key] = node.real()
        return out
    except (cv2.error, SystemError) as exc:
        raise CalibrationError(f"not a readable OpenCV FileStorage file ({_first_line(exc)})", path) from None
    finally:
        fs.release()


def _first_line(exc: BaseException) -> str:
    """OpenCV's own words for a parse failure (``line 2: Missing , between the elements``), found
    in the exception chain: the binding wraps cv2.error in a SystemError that says nothing."""
    import re

    while isinstance(exc, SystemError) and (inner := exc.__cause__ or exc.__context__) is not None:
        exc = inner
    text = str(exc).strip()
    m = re.search(r"\((-?\d+):([^)]*)\).*?'[^']*\((\d+)\): ([^']*)'", text)
    if m:
        return f"{m.group(2).strip().lower()} at line {m.group(3)}: {m.group(4).strip()}"
    lines = text.splitlines()
    return lines[-1].strip() if lines else type(exc).__name__


def _number(v: object, key: str, path: Path) -> float:
    """A FileStorage number (OpenCV writes ``.Nan``, ``.Inf``, ``1.``)."""
    if isinstance(v, bool) or not isinstance(v, (int, float, str)):
        raise CalibrationError(f"key '{key}' holds {type(v).__name__}, not numbers", path)
    try:
        return float(str(v).strip().lower().replace(".nan", "nan").replace(".inf", "inf"))
    except ValueError:
        raise CalibrationError(f"key '{key}' holds {v!r}, not a number", path) from None


def _read_mat(fs: dict, key: str, path: Path, shape: tuple[int, ...] | None) -> np.ndarray:
    node = fs.get(key)
    if node is None:
        raise CalibrationError(f"missing key '{key}'", path)
    dims: tuple[int, ...]
    if isinstance(node, _Matrix):
        rows, cols = node.rows, node.cols
        if not isinstance(node.data, list) or not (isinstance(rows, int) and isinstance(cols, int) and rows >= 0
                                                   and cols >= 0):
            raise CalibrationError(f"key '{key}' is not a well-formed matrix (rows, cols, data)", path)
        if rows * cols != len(node.data):
            raise CalibrationError(f"key '{key}' declares {rows}×{cols} but holds {len(node.data)} values", path)
        vals, dims = node.data, (rows, cols)
    elif isinstance(node, list):
        vals, dims = node, (len(node),)
    else:
        raise CalibrationError(f"key '{key}' is not a matrix", path)
    mat = np.array([_number(v, key, path) for v in vals], dtype=float).reshape(dims)
    if shape is not None and mat.size != int(np.prod(shape)):
        raise CalibrationError(f"key '{key}' has shape {mat.shape}, expected {shape}", path)
    if not np.all(np.isfinite(mat)):
        raise CalibrationError(f"key '{key}' contains NaN or infinite values", path)
    return mat.reshape(shape) if shape is not None else mat


def _read_intrinsics(fs: dict, i: int, path: Path) -> np.ndarray:
    """``K1``/``K2`` (or the ``M1``/``M2`` of OpenCV's samples)."""
    for key in (f"K{i}", f"M{i}"):
        if key in fs:
            return _read_mat(fs, key, path, (3, 3))
    raise CalibrationError(f"missing key 'K{i}' (or 'M{i}')", path)


def _read_dist(fs: dict, key: str, path: Path) -> np.ndarray:
    if fs.get(key) is None:
        return np.zeros(5)
    d = _read_mat(fs, key, path, None).ravel()
    if d.size not in _DIST_LENGTHS:
        raise CalibrationError(f"key '{key}' has {d.size} distortion coefficients; expected 4, 5, 8, 12 or 14", path)
    return d


def _read_size(fs: dict, path: Path) -> tuple[int, int]:
    if fs.get("image_width") is not None and fs.get("image_height") is not None:
        w, h = (_number(fs[k], k, path) for k in ("image_width", "image_height"))
        vals = [w, h]
    elif fs.get("image_size") is not None:
        node = fs["image_size"]
        vals = list(_read_mat(fs, "image_size", path, None).ravel()) if isinstance(node, (_Matrix, list)) else [node]
        if len(vals) != 2:
            raise CalibrationError(f"field 'image_size' must be [width, height], found {len(vals)} value(s)", path)
    else:
        return (0, 0)
    if not all(np.isfinite(v) and v == int(v) for v in vals):
        raise CalibrationError(f"image size {vals} is not two whole numbers", path)
    return int(vals[0]), int(vals[1])


def load_calibration(path: str | Path, units: str | None = None) -> StereoRig:
    """Load a stereo calibration.

    ``path`` is a ``calib.yaml`` (keys ``K1 D1 K2 D2 R T`` and ``image_width``/``image_height``, as
    written by ``cv2.stereoCalibrate`` + ``cv2.FileStorage``), or a folder holding one, or a folder
    in the layout of OpenCV's ``stereo_calib`` sample (``intrinsics.yml`` with ``M1 D1 M2 D2``,
    ``extrinsics.yml`` with ``R T ...``). Both OpenCV 4 (``%YAML:1.0``) and 5 (``%YAML 1.2``) files
    load. Distortion may have 4, 5, 8, 12 or 14 coefficients.

    Lengths (``T``) come out in metres: the file may declare its unit (``units: mm|cm|m``), and
    ``units`` (the CLI's ``--calib-units``) overrides it, with a warning naming both when they
    differ. With no declared unit and a baseline longer than 5, a warning names the likely unit
    (OpenCV's chessboard tools use whatever unit the square size was typed in, very often millimetres).
    """
    path = Path(path)
    if units is not None and units not in LENGTH_UNITS:
        raise CalibrationError(f"unknown length unit {units!r} (use m, cm or mm)")
    if path.is_dir():
        for name in CALIB_NAMES:
            if (path / name).is_file():
                return load_calibration(path / name, units)
        intr = next((path / n for n in INTRINSICS_NAMES if (path / n).is_file()), None)
        extr = next((path / n for n in EXTRINSICS_NAMES if (path / n).is_file()), None)
        if intr is None or extr is None:
            raise CalibrationError("no calib.yaml (nor intrinsics.yml + extrinsics.yml) in this folder", path)
        return _load_stereo_calib_layout(intr, extr, units)
    return _load_stereo_calib_layout(path, path, units)


def _read_units(fs: dict, path: Path) -> str | None:
    unit = fs.get("units")
    if unit is None:
        return None
    text = unit.strip().lower() if isinstance(unit, str) else ""
    if text not in LENGTH_UNITS:
        raise CalibrationError(f"field 'units' must be m, cm or mm, not {unit!r}", path)
    return text


def _check_intrinsics(K: np.ndarray, key: str, path: Path) -> None:
    """Focal lengths must be positive: a negative one mirrors the image and gives NaN depths."""
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CalibrationError(f"field '{key}' has focal length fx={K[0, 0]:g}, fy={K[1, 1]:g}: both must be > 0", path)
    if not np.allclose(K[2], [0.0, 0.0, 1.0]):
        raise CalibrationError(f"field '{key}' is not a camera matrix (last row must be 0 0 1, got {K[2].tolist()})", path)


def _load_stereo_calib_layout(intr: Path, extr: Path, units: str | None = None) -> StereoRig:
    """Intrinsics (``K1/M1 D1 K2/M2 D2``, image size) from ``intr``, ``R T`` from ``extr`` (the same
    file for ``calib.yaml``)."""
    fs = _read_storage(intr)
    K1, K2 = (_read_intrinsics(fs, i, intr) for i in (1, 2))
    D1, D2 = _read_dist(fs, "D1", intr), _read_dist(fs, "D2", intr)
    size = _read_size(fs, intr)
    declared = _read_units(fs, intr)
    fs = _read_storage(extr) if extr != intr else fs
    R, T = _read_mat(fs, "R", extr, (3, 3)), _read_mat(fs, "T", extr, (3,))
    if size == (0, 0):
        size = _read_size(fs, extr)
    declared = declared or _read_units(fs, extr)
    for key, K in (("K1", K1), ("K2", K2)):
        _check_intrinsics(K, key, intr)
    if size != (0, 0) and (size[0] <= 0 or size[1] <= 0):
        raise CalibrationError(f"image size {size[0]}×{size[1]} is not positive", intr)
    if units is not None and declared is not None and units != declared:
        warnings.warn(f"{extr}: --calib-units {units} overrides the unit the file declares (units: {declared}); "
                      f"T is read in {units}", stacklevel=2)
    unit = units or declared
    baseline = float(np.linalg.norm(R.T @ T))
    if unit is None and baseline > SUSPICIOUS_BASELINE:
        likely, scale = ("millimetres", "mm") if baseline > 30 else ("centimetres", "cm")
        warnings.warn(f"{extr}: baseline is {baseline:g} with no declared unit; this looks like {likely} "
                      f"({baseline * LENGTH_UNITS[scale]:g} m): add 'units: {scale}' to the file or pass "
                      f"--calib-units {scale}", stacklevel=2)
    T = T * LENGTH_UNITS[unit or "m"]
    rig = StereoRig(Camera(K1, D=D1), Camera(K2, R, T, D2), size)
    rig.check(extr)
    return rig


def save_calibration(rig: StereoRig, path: str | Path, units: str | None = None) -> None:
    """Write ``calib.yaml`` through ``cv2.FileStorage`` (atomically), with derived ``P1``, ``P2``.
    ``units`` declares the length unit of ``T`` in the file (``T`` is scaled from metres to it)."""
    path = Path(path)
    if units is not None:
        s = 1.0 / LENGTH_UNITS[units]
        rig = StereoRig(rig.left, Camera(rig.right.K, rig.right.R, rig.right.t * s, rig.right.D), rig.image_size)
    with atomic_path(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        if units is not None:
            fs.write("units", units)
        fs.write("image_width", int(rig.image_size[0]))
        fs.write("image_height", int(rig.image_size[1]))
        fs.write("K1", rig.left.K)
        fs.write("D1", np.asarray(rig.left.D, dtype=float).reshape(1, -1))
        fs.write("K2", rig.right.K)
        fs.write("D2", np.asarray(rig.right.D, dtype=float).reshape(1, -1))
        fs.write("R", rig.R)
        fs.write("T", rig.T.reshape(3, 1))
        fs.write("P1", rig.left.P)
        fs.write("P2", rig.right.P)
        fs.release()
