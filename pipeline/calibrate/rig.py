"""``stereotrack calibrate`` for two or more cameras in per-camera folders: a rig from a folder of board images, one
sub-folder per camera (``cam0/``, ``cam1/``, … numbered alike: the same number is the same
instant, seen by any subset of the cameras), written as a rig file with a report beside it.

Each camera's intrinsics come from every image it has of the board (Zhang's method, OpenCV's
``calibrateCameraExtended``; images only that camera took count too), then every pose jointly from
the views two or more cameras share (OpenCV 5's ``calibrateMultiview``: pairwise initialisation
refined by bundle adjustment, the intrinsics held as found). The report gives each camera's RMS
reprojection error and its leave-one-camera-out error: the board placed by the other cameras that
saw it (each from its own corners) and projected into this one, which a wrong pose cannot hide.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.board import Board
from pipeline.core.camera import Camera
from pipeline.core.errors import StereotrackError
from pipeline.core.frames import IMAGE_EXTS
from pipeline.core.io import write_text
from pipeline.core.rig import Rig
from pipeline.core.rigfiles import save_rig

#: a camera is poorly calibrated (a warning names it) above this RMS or leave-one-out error (px)
POOR_PX = 1.0


@dataclass
class RigCalibration:
    """What the N-camera calibration found: the rig (first camera's frame, metres) and its errors."""

    rig: Rig
    rms: dict[str, float]  # per camera, its own intrinsic calibration
    rms_joint: float  # the bundle adjustment's over every camera and shared view
    loo: dict[str, float]  # per camera: RMS of its corners against the board as the others place it
    views: dict[str, int]  # per camera: images with the board found
    shared: int  # views with the board found in two or more cameras
    warnings: list[str] = field(default_factory=list)


def camera_folders(images: Path) -> list[Path]:
    """The camera sub-folders of a board-image folder (each holding numbered images), by name."""
    if not images.is_dir():
        raise StereotrackError("no such folder of board images", images)
    return sorted(d for d in images.iterdir() if d.is_dir() and not d.name.startswith(".")
                  and any(p.suffix.lower() in IMAGE_EXTS for p in d.iterdir()))


def _numbered(folder: Path) -> dict[int, Path]:
    import re

    out = {}
    for p in folder.iterdir():
        m = re.search(r"(\d+)$", p.stem)
        if p.suffix.lower() in IMAGE_EXTS and m:
            out[int(m.group(1))] = p
    return out


def _corners(board: Board, folders: list[Path]) -> tuple[list[int], list[list[np.ndarray | None]], list[tuple[int, int]]]:
    """The view numbers, each camera's corners per view (None: not found or no image), image sizes."""
    from pipeline.calibrate import find_corners

    files = [_numbered(f) for f in folders]
    numbers = sorted(set().union(*files))
    found: list[list[np.ndarray | None]] = []
    sizes = []
    for f, mine in zip(folders, files, strict=True):
        row: list[np.ndarray | None] = []
        size = None
        for k in numbers:
            grey = cv2.imread(str(mine[k]), cv2.IMREAD_GRAYSCALE) if k in mine else None
            if grey is None:
                row.append(None)
                continue
            if size is None:
                size = grey.shape[::-1]
            elif grey.shape[::-1] != size:
                raise StereotrackError(f"image size {grey.shape[1]}×{grey.shape[0]} differs from the camera's first "
                                       f"{size[0]}×{size[1]}", mine[k])
            c = find_corners(board, grey)
            row.append(c[1].astype(np.float32) if c is not None else None)
        if size is None:
            raise StereotrackError("no readable image", f)
        found.append(row)
        sizes.append((int(size[0]), int(size[1])))
    return numbers, found, sizes


def calibrate_rig(images: str | Path, board: Board) -> RigCalibration:
    """Intrinsics per camera, then the poses jointly; errors name the folder and what is missing."""
    images = Path(images)
    if board.kind != "chessboard":
        raise StereotrackError("calibrating three or more cameras takes a chessboard (every corner in every view)",
                               images)
    folders = camera_folders(images)
    if len(folders) < 2:
        raise StereotrackError("needs a sub-folder of board images per camera (two or more)", images)
    names = [f.name for f in folders]
    _, found, sizes = _corners(board, folders)
    grid = np.mgrid[0 : board.cols, 0 : board.rows].T.reshape(-1, 2) * board.square
    obj = np.column_stack([grid, np.zeros(len(grid))]).astype(np.float32)
    Ks, Ds, rms = [], [], {}
    for name, row, size in zip(names, found, sizes, strict=True):
        mine = [p for p in row if p is not None]
        if len(mine) < 3:
            raise StereotrackError(f"the board was found in {len(mine)} image(s) of camera {name}: at least 3 are needed",
                                   images / name)
        out = cv2.calibrateCameraExtended([obj] * len(mine), mine, size, None, None,  # type: ignore[call-overload]
                                          flags=cv2.CALIB_FIX_K3)
        rms[name] = float(out[0])
        Ks.append(out[1])
        Ds.append(out[2])
    mask = np.array([[p is not None for p in row] for row in found], dtype=np.uint8)
    shared = mask.sum(axis=0) >= 2
    if shared.sum() < 3:
        raise StereotrackError(f"{int(shared.sum())} view(s) show the board to two or more cameras: at least 3 are "
                               "needed to find the poses", images)
    cols = np.flatnonzero(shared)
    empty = np.zeros((0, 2), np.float32)
    pts: list[list[np.ndarray]] = [[p if (p := row[k]) is not None else empty for k in cols] for row in found]
    # OpenCV's stubs type the outputs (Rs, Ts: None asks it to allocate them) and the masks as UMat
    res = cv2.calibrateMultiview([obj] * len(cols), pts, sizes, mask[:, cols], np.zeros(len(names), np.uint8),  # type: ignore[call-overload]
                                 Ks, Ds, None, None, flagsForIntrinsics=np.full(len(names), cv2.CALIB_FIX_K3, dtype=int),
                                 flags=cv2.CALIB_USE_INTRINSIC_GUESS | cv2.CALIB_FIX_INTRINSIC)
    cams = tuple(Camera(np.asarray(K, float), cv2.Rodrigues(np.asarray(r, float))[0], np.ravel(np.asarray(t, float)),
                        np.ravel(np.asarray(D, float))) for K, D, r, t in zip(res[1], res[2], res[3], res[4], strict=True))
    rig = Rig(cams, tuple(names), tuple(sizes)).in_frame_of(0)
    cal = RigCalibration(rig, rms, float(res[0]), _leave_one_out(rig, found, obj), {n: int(m.sum()) for n, m in
                                                                                zip(names, mask, strict=True)},
                         int(shared.sum()))
    cal.warnings = [f"camera {n}: {what} error {e:.2f} px (over {POOR_PX:g} px)" for what, errs in
                    (("RMS reprojection", cal.rms), ("leave-one-camera-out", cal.loo)) for n, e in errs.items() if e > POOR_PX]
    return cal


def _leave_one_out(rig: Rig, found: list[list[np.ndarray | None]], obj: np.ndarray) -> dict[str, float]:
    """Per camera: the RMS distance (px) between its detected corners and the board as the other
    cameras place it — each other camera that saw the same view finds the board's pose from its own
    corners (``solvePnP``), which is carried into this camera through the two poses — over every
    view it shares. Independent of this camera's own pose estimate, so a wrong pose shows."""
    out = {}
    for c, name in enumerate(rig.names):
        sq = []
        for k in range(len(found[0])):
            mine = found[c][k]
            if mine is None:
                continue
            for i in range(rig.n):
                theirs = found[i][k]
                if i == c or theirs is None:
                    continue
                cam = rig.cameras[i]
                ok, rvec, tvec = cv2.solvePnP(obj, theirs, cam.K, np.asarray(cam.D, float))
                if not ok:
                    continue
                X_i = obj @ cv2.Rodrigues(rvec)[0].T + tvec.ravel()  # the board in camera i's frame
                X = (X_i - np.ravel(cam.t)) @ cam.R  # … in the world
                sq.append(np.sum((rig.cameras[c].project_distorted(X) - mine) ** 2, axis=1))
        out[name] = float(np.sqrt(np.mean(np.concatenate(sq)))) if sq else float("nan")
    return out


def report_text(cal: RigCalibration, rig_name: str) -> str:
    lines = [f"# Calibration report: {rig_name}", "", *(f"**Warning:** {w}" for w in cal.warnings),
             *([""] if cal.warnings else []),
             f"{cal.rig.n} cameras; {cal.shared} views shared by two or more; joint RMS reprojection "
             f"{cal.rms_joint:.3f} px. World: the first camera's frame, metres.", "",
             "| camera | images with the board | RMS reprojection (px) | leave-one-camera-out (px) | fx, fy (px) | "
             "centre (m) |", "|---|---:|---:|---:|---:|---|"]
    for name, cam in zip(cal.rig.names, cal.rig.cameras, strict=True):
        loo = cal.loo[name]
        lines.append(f"| {name} | {cal.views[name]} | {cal.rms[name]:.3f} | {'—' if np.isnan(loo) else f'{loo:.3f}'} | "
                     f"{cam.K[0, 0]:.2f}, {cam.K[1, 1]:.2f} | {', '.join(f'{v:+.4f}' for v in cam.center)} |")
    return "\n".join(lines) + "\n"


def calibrate_rig_folder(images: str | Path, board: Board, out: str | Path) -> tuple[RigCalibration, Path]:
    """The whole command for N cameras: the rig file (its format by name) and ``<stem>_report.md``."""
    out = Path(out)
    report = out.with_name(f"{out.name.split('.')[0]}_report.md")
    for path in (out, report):
        if path.exists():
            raise StereotrackError("exists: stereotrack never replaces a file; choose another -o or move it away", path)
    cal = calibrate_rig(images, board)
    save_rig(cal.rig, out, units="m")
    write_text(report, report_text(cal, out.name))
    for w in cal.warnings:
        warnings.warn(f"{out}: poor calibration: {w}", stacklevel=2)
    return cal, report
