"""``stereotrack calibrate``: a stereo calibration from image pairs of a chessboard or ChArUco board,
written as ``calib.yaml`` (metres, ``units: m``, the image size) with a report beside it.

OpenCV does the work (Zhang's method: Z. Zhang, *A flexible new technique for camera calibration*,
IEEE TPAMI 22(11), 2000; corners by ``findChessboardCornersSB`` or the ChArUco detector; per-camera
``calibrateCameraExtended``, then ``stereoCalibrateExtended`` with the intrinsics fixed). What this
module adds is what a user otherwise checks by hand: which pairs were used and why others were not
(board not found in both images, or a reprojection error that is an outlier among the pairs), how
much of each image the board covered, the rectified epipolar error, the baseline, which side the
second camera is on, and a warning naming the cause when the calibration is poor.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pipeline.calibrate.order import reversed_pairs
from pipeline.core.board import Board
from pipeline.core.calibration import LENGTH_UNITS, save_calibration
from pipeline.core.camera import UNDISTORT_CRITERIA, Camera, StereoRig
from pipeline.core.errors import StereotrackError
from pipeline.core.frames import IMAGE_EXTS, VIDEO_EXTS
from pipeline.core.io import atomic_path, write_text

#: a calibration is poor (a warning names the cause) above this RMS (px), below this share of each
#: image covered by the board, or with fewer usable pairs than this
POOR_RMS_PX = 1.0
POOR_COVERAGE = 1 / 3
MIN_PAIRS = 8
#: a pair whose stereo reprojection error exceeds this many times the median (and 0.5 px) is dropped
OUTLIER_FACTOR = 3.0
#: frames sampled from a pair of videos
VIDEO_SAMPLES = 40
#: a calibration whose stereo RMS exceeds this (px) is not written without --force: its corners do
#: not fit one rig (a wrong --board, a moving board, pairs that are not simultaneous)
ABSURD_RMS_PX = 5.0
LENGTH = re.compile(r"^\s*([0-9]*\.?[0-9]+(?:[eE][-+]?[0-9]+)?)\s*(mm|cm|m)?\s*$")


#: a bare number (no unit) at least this large is refused: no printed board has squares of half a
#: metre, so ``--square 25`` means 25 mm, not the 25 m it would silently be read as
BARE_LENGTH_LIMIT = 0.5


def parse_length(text: str, what: str = "--square") -> float:
    """``24mm``, ``2.4cm``, ``0.024`` or ``0.024m`` → metres (a bare number under 0.5 is metres;
    a larger one is refused as ambiguous, naming the likely unit)."""
    m = LENGTH.match(str(text))
    if not m or float(m.group(1)) <= 0:
        raise StereotrackError(f"{what} {text!r} is not a length (e.g. 24mm, 2.4cm, 0.024)")
    value = float(m.group(1))
    if m.group(2) is None and value >= BARE_LENGTH_LIMIT:
        raise StereotrackError(f"{what} {text} has no unit and would be {value:g} metres: give one "
                               f"({m.group(1)}mm? {m.group(1)}cm?)")
    return value * LENGTH_UNITS[m.group(2) or "m"]


def parse_board(spec: str, square: float, marker: float | None = None) -> Board:
    """``chessboard:COLSxROWS`` (inner corners) or ``charuco:COLSxROWS:DICT`` (squares; DICT an
    OpenCV ArUco dictionary such as ``4X4_50``, which needs ``--marker``)."""
    m = re.fullmatch(r"(chessboard|charuco):(\d+)x(\d+)(?::([A-Za-z0-9_]+))?", spec.strip())
    if not m:
        raise StereotrackError(f"--board {spec!r}: expected chessboard:COLSxROWS or charuco:COLSxROWS:DICT")
    kind, cols, rows, dic = m.group(1), int(m.group(2)), int(m.group(3)), m.group(4)
    if min(cols, rows) < 2:
        raise StereotrackError(f"--board {spec!r}: a board needs at least 2 × 2")
    if kind == "chessboard":
        return Board(kind, cols, rows, square)
    name = "DICT_" + (dic or "4X4_50").upper().removeprefix("DICT_")
    if not hasattr(cv2.aruco, name):
        raise StereotrackError(f"--board {spec!r}: unknown ArUco dictionary {name}")
    if marker is None or not 0 < marker < square:
        raise StereotrackError("a ChArUco board needs --marker, the marker side, smaller than --square")
    return Board(kind, cols, rows, square, marker, name)


# -- the image pairs --------------------------------------------------------------------------------


def find_pairs(images: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, left grey, right grey) for every pair: ``left*``/``right*`` files matched by the
    number in their names, ``left/`` and ``right/`` folders matched the same way, or two videos
    ``left.*``/``right.*`` (``VIDEO_SAMPLES`` frames sampled evenly)."""
    if not images.is_dir():
        raise StereotrackError("not a folder of calibration images", images)
    vids = {c: next((p for p in sorted(images.iterdir()) if p.stem == c and p.suffix.lower() in VIDEO_EXTS), None)
            for c in ("left", "right")}
    if vids["left"] and vids["right"]:
        return _video_pairs(vids["left"], vids["right"])
    if (images / "left").is_dir() and (images / "right").is_dir():
        left, right = _numbered(images / "left", ""), _numbered(images / "right", "")
    else:
        left, right = _numbered(images, "left"), _numbered(images, "right")
    common = sorted(set(left) & set(right))
    if not common:
        raise StereotrackError("no image pairs: expected left*/right* images numbered alike (left01.png and "
                               "right01.png), left/ and right/ folders, or left and right videos", images)
    return [(f"pair {k}", _grey(left[k]), _grey(right[k])) for k in common]


def _folder_images(folder: Path) -> list[tuple[str, np.ndarray]]:
    """Every image of one camera's own board folder, by name."""
    if not folder.is_dir():
        raise StereotrackError("not a folder of board images", folder)
    paths = [p for p in sorted(folder.iterdir()) if p.suffix.lower() in IMAGE_EXTS]
    if not paths:
        raise StereotrackError("no images here", folder)
    return [(f"{folder.name}/{p.name}", _grey(p)) for p in paths]


def _numbered(folder: Path, prefix: str) -> dict[int, Path]:
    out: dict[int, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() in IMAGE_EXTS and p.name.lower().startswith(prefix):
            digits = re.findall(r"\d+", p.stem[len(prefix):])
            if digits:
                out[int(digits[-1])] = p
    return out


def _grey(path: Path) -> np.ndarray:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise StereotrackError("cannot read this image", path)
    return img


def _video_pairs(left: Path, right: Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    caps = [cv2.VideoCapture(str(p)) for p in (left, right)]
    try:
        n = min(int(c.get(cv2.CAP_PROP_FRAME_COUNT) or 0) for c in caps)
        if n <= 0:
            raise StereotrackError("cannot read frames from these videos", left.parent)
        keep = set(np.linspace(0, n - 1, min(VIDEO_SAMPLES, n)).astype(int).tolist())
        out: list[tuple[str, np.ndarray, np.ndarray]] = []
        for k in range(n):
            a, b = (c.read()[1] for c in caps)
            if k in keep and a is not None and b is not None:
                out.append((f"frame {k}", cv2.cvtColor(a, cv2.COLOR_BGR2GRAY), cv2.cvtColor(b, cv2.COLOR_BGR2GRAY)))
        return out
    finally:
        for c in caps:
            c.release()


# -- corners ------------------------------------------------------------------------------------


def find_corners(board: Board, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(board points N×3 in metres, image points N×2) of the corners found, or None."""
    if board.kind == "chessboard":
        flags = cv2.CALIB_CB_EXHAUSTIVE | cv2.CALIB_CB_ACCURACY
        ok, corners = cv2.findChessboardCornersSB(grey, (board.cols, board.rows), flags=flags)
        return _chessboard(board, grey, corners) if ok else None
    cb = board.charuco()
    corners, ids, _, _ = cv2.aruco.CharucoDetector(cb).detectBoard(grey)
    if ids is None or len(ids) < 6:
        return None
    obj = cb.getChessboardCorners()[ids.ravel()]
    return obj.astype(np.float32), corners.reshape(-1, 2)


def classic_corners(board: Board, grey: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """A chessboard by OpenCV's classic detector, which finds boards the sector-based one misses (and
    the reverse) but may list the corners from the opposite end: only for a caller that makes each
    pair's order agree (:func:`pipeline.calibrate.order.reversed_pairs`; not the N-camera
    calibration, where it moved a ring's camera 0.88 m)."""
    if board.kind != "chessboard":
        return None
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    ok, corners = cv2.findChessboardCorners(grey, (board.cols, board.rows), flags=flags)
    return _chessboard(board, grey, corners) if ok else None


def _chessboard(board: Board, grey: np.ndarray, corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The board's points (metres) and the detector's corners, refined."""
    grid = np.mgrid[0 : board.cols, 0 : board.rows].T.reshape(-1, 2) * board.square
    return np.column_stack([grid, np.zeros(len(grid))]).astype(np.float32), refine(grey, corners.reshape(-1, 2))


def _either_corners(board: Board, grey: np.ndarray, classic: list[int]) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`find_corners`, else :func:`classic_corners` (its finds counted in ``classic[0]``)."""
    got = find_corners(board, grey)
    if got is None and (got := classic_corners(board, grey)) is not None:
        classic[0] += 1
    return got


def refine(grey: np.ndarray, corners: np.ndarray) -> np.ndarray:
    """``cornerSubPix`` on the detector's corners, in a window under a third of the smallest square:
    on rendered boards with exact truth, the SB detector's own estimates are biased on slanted
    squares (focal lengths 0.3 % short, tested), the gradient refinement is not."""
    d = np.linalg.norm(corners[:, None] - corners[None], axis=2)
    np.fill_diagonal(d, np.inf)
    half = int(np.clip(d.min(axis=1).min() / 6, 2, 7))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    out = cv2.cornerSubPix(grey, corners.reshape(-1, 1, 2).astype(np.float32), (half, half), (-1, -1), crit)
    return out.reshape(-1, 2)


def _common(left: tuple[np.ndarray, np.ndarray], right: tuple[np.ndarray, np.ndarray]):
    """The corners both views found (a partly visible ChArUco board finds different ones)."""
    kl = {tuple(np.round(p, 6)): i for i, p in enumerate(left[0])}
    pairs = [(kl[tuple(np.round(p, 6))], j) for j, p in enumerate(right[0]) if tuple(np.round(p, 6)) in kl]
    if len(pairs) < 6:
        return None
    i, j = np.array(pairs).T
    return left[0][i], left[1][i], right[1][j]


# -- the calibration ----------------------------------------------------------------------------


@dataclass
class Calibration:
    """What ``calibrate`` found: the rig, its errors, and which pairs it used or left out and why."""

    rig: StereoRig
    rms_left: float
    rms_right: float
    rms_stereo: float
    used: list[str]
    pair_errors: dict[str, float]
    rejected: dict[str, str]
    coverage: tuple[float, float]
    epipolar_px: tuple[float, float]  # rectified |y_left − y_right| of the corners: median, max
    hulls: tuple[list[np.ndarray], list[np.ndarray]] = field(default_factory=lambda: ([], []))
    warnings: list[str] = field(default_factory=list)
    #: pairs whose right view listed the corners in the opposite order (a 180°-symmetric board), reordered
    reordered: list[str] = field(default_factory=list)
    #: views whose board the classic detector found (the sector-based one did not)
    classic: int = 0
    #: each camera's own board images its intrinsics used beside the pairs (left, right), and those
    #: left out (name → why)
    singles: tuple[int, int] = (0, 0)
    singles_skipped: dict[str, str] = field(default_factory=dict)

    @property
    def baseline(self) -> float:
        return self.rig.baseline

    @property
    def second_camera_side(self) -> str:
        """Where the second (right-named) camera sits seen from the first: right, left, above, below."""
        c = self.rig.left.R @ (self.rig.right.center - self.rig.left.center)
        axis = int(np.argmax(np.abs(c[:2])))
        return (("right", "left") if axis == 0 else ("below", "above"))[int(c[axis] < 0)]

    @property
    def second_camera_phrase(self) -> str:
        """Where the second camera sits, as a sentence says it: ``to the left of the first``, ``above the first``."""
        side = self.second_camera_side
        return f"{'to the ' + side + ' of' if side in ('left', 'right') else side} the first"


def calibrate(pairs: list[tuple[str, np.ndarray, np.ndarray]], board: Board,
              singles: tuple[list[tuple[str, np.ndarray]], list[tuple[str, np.ndarray]]] = ([], [])) -> Calibration:
    """Corners in every pair, per-camera then stereo calibration, outlier pairs dropped once.
    ``singles``: each camera's own board images (not simultaneous with the other's), which its
    intrinsics use beside the pairs' views; the extrinsics come from the pairs alone."""
    size = pairs[0][1].shape[::-1]
    found, rejected = {}, {}
    classic = [0]  # views whose board only the classic detector found
    for name, gl, gr in pairs:
        if gl.shape[::-1] != size or gr.shape[::-1] != size:
            rejected[name] = f"image size {gl.shape[1]}×{gl.shape[0]} differs from the first pair's {size[0]}×{size[1]}"
            continue
        cl, cr = _either_corners(board, gl, classic), _either_corners(board, gr, classic)
        both = _common(cl, cr) if cl is not None and cr is not None else None
        if both is None:
            missing = [s for s, c in (("left", cl), ("right", cr)) if c is None]
            rejected[name] = (f"board not found in the {missing[0]} image" if len(missing) == 1 else
                              "board not found in either image" if missing else
                              "too few of the board's corners found in both images")
            continue
        found[name] = both
    if len(found) < 3:
        raise StereotrackError(f"the board was found in both images of {len(found)} pair(s) of {len(pairs)}: "
                               "at least 3 are needed (check --board: chessboards count inner corners)")
    skipped: dict[str, str] = {}  # each camera's own images without a board: not pairs, reported apart
    extra = tuple(_single_views(views, board, size, skipped, classic) for views in singles)
    flipped = reversed_pairs(found, size) if board.kind == "chessboard" else []
    for n in flipped:  # the right view listed the corners from the opposite end: the same points, in the same order
        o, left, right = found[n]
        found[n] = (o, left, right[::-1].copy())
    cal = _solve(found, size, extra)
    errs = cal.pair_errors
    med = float(np.median(list(errs.values())))
    bad = [n for n, e in errs.items() if e > max(OUTLIER_FACTOR * med, 0.5)]
    if bad and len(found) - len(bad) >= 3:
        for n in bad:
            rejected[n] = f"reprojection error {errs[n]:.2f} px, over {OUTLIER_FACTOR:g}× the median {med:.2f} px"
            found.pop(n)
        cal = _solve(found, size, extra)
    cal.rejected, cal.reordered, cal.classic = rejected, [n for n in flipped if n in found], classic[0]
    cal.singles_skipped = skipped
    cal.warnings = _poor(cal)
    return cal


def _single_views(views: list[tuple[str, np.ndarray]], board: Board, size: tuple[int, int],
                  rejected: dict[str, str], classic: list[int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """One camera's own board images: (board points, corners) of each whose board is found (the
    others named in ``rejected``; a view's own order does not matter to its camera's intrinsics)."""
    out = []
    for name, grey in views:
        got = _either_corners(board, grey, classic) if grey.shape[::-1] == size else None
        if got is None:
            rejected[name] = ("board not found" if grey.shape[::-1] == size else
                              f"image size {grey.shape[1]}×{grey.shape[0]} differs from the pairs' {size[0]}×{size[1]}")
        else:
            out.append((got[0], got[1].astype(np.float32)))
    return out


def _solve(found: dict, size: tuple[int, int], extra: tuple[list, ...] = ([], [])) -> Calibration:
    names = list(found)
    obj = [found[n][0] for n in names]
    il = [found[n][1].astype(np.float32) for n in names]
    ir = [found[n][2].astype(np.float32) for n in names]
    flags = cv2.CALIB_FIX_K3  # k1 k2 p1 p2, as OpenCV's stereo_calib sample: k3 over-fits without full coverage
    # each camera's intrinsics from the pairs' views and its own board images; the extrinsics from the pairs
    ol, vl = obj + [o for o, _ in extra[0]], il + [v for _, v in extra[0]]
    orr, vr = obj + [o for o, _ in extra[1]], ir + [v for _, v in extra[1]]
    # OpenCV's type stubs have no None for the outputs the functions allocate (cameraMatrix, R, T):
    # the documented way to ask for them, hence the three ignores
    rms_l, K1, D1, *_ = cv2.calibrateCameraExtended(ol, vl, size, None, None, flags=flags)  # type: ignore[call-overload]
    rms_r, K2, D2, *_ = cv2.calibrateCameraExtended(orr, vr, size, None, None, flags=flags)  # type: ignore[call-overload]
    out = cv2.stereoCalibrateExtended(obj, il, ir, K1, D1, K2, D2, size, None, None,  # type: ignore[call-overload]
                                      flags=cv2.CALIB_FIX_INTRINSIC)
    rms, R, T, per_view = out[0], out[5], out[6], out[-1]
    left = Camera(K1, np.eye(3), np.zeros(3), D1.ravel())
    right = Camera(K2, R, T.ravel(), D2.ravel())
    rig = StereoRig(left, right, (int(size[0]), int(size[1])))
    errors = {n: float(np.sqrt(np.mean(per_view[i] ** 2))) for i, n in enumerate(names)}
    # the board's coverage of each image, over every view its intrinsics used (its own images too)
    hulls = ([cv2.convexHull(p.reshape(-1, 1, 2)).reshape(-1, 2) for p in vl],
             [cv2.convexHull(p.reshape(-1, 1, 2)).reshape(-1, 2) for p in vr])
    return Calibration(rig, float(rms_l), float(rms_r), float(rms), names, errors, {},
                       (_coverage(hulls[0], size), _coverage(hulls[1], size)), _epipolar(rig, il, ir), hulls,
                       singles=(len(extra[0]), len(extra[1])))


def _coverage(hulls: list[np.ndarray], size: tuple[int, int]) -> float:
    """Share of the image inside the union of the board's outlines."""
    mask = np.zeros((size[1], size[0]), np.uint8)
    for h in hulls:
        cv2.fillConvexPoly(mask, np.round(h).astype(np.int32), 1)
    return float(mask.mean())


def _epipolar(rig: StereoRig, il: list[np.ndarray], ir: list[np.ndarray]) -> tuple[float, float]:
    """Rectified vertical disparity of the corners (px): median and max."""
    K1, D1, K2, D2 = rig.left.K, np.asarray(rig.left.D), rig.right.K, np.asarray(rig.right.D)
    R1, R2, P1, P2, *_ = cv2.stereoRectify(K1, D1, K2, D2, rig.image_size, rig.right.R, rig.right.t.reshape(3, 1))
    dy = []
    for a, b in zip(il, ir, strict=True):
        ya = cv2.undistortPoints(a.reshape(-1, 1, 2), K1, D1, R=R1, P=P1, criteria=UNDISTORT_CRITERIA).reshape(-1, 2)
        yb = cv2.undistortPoints(b.reshape(-1, 1, 2), K2, D2, R=R2, P=P2, criteria=UNDISTORT_CRITERIA).reshape(-1, 2)
        dy.append(np.abs(ya[:, 1] - yb[:, 1]))
    d = np.concatenate(dy)
    return float(np.median(d)), float(d.max())


def _poor(cal: Calibration) -> list[str]:
    """One line per cause of a poor calibration."""
    out = []
    for what, rms in (("left camera", cal.rms_left), ("right camera", cal.rms_right), ("stereo", cal.rms_stereo)):
        if rms > POOR_RMS_PX:
            out.append(f"{what} RMS reprojection error {rms:.2f} px (over {POOR_RMS_PX:g} px: blurred or moving board, "
                       "or a wrong --board)")
    for cam, cov in zip(("left", "right"), cal.coverage, strict=True):
        if cov < POOR_COVERAGE:
            out.append(f"the board covered {100 * cov:.0f} % of the {cam} image (under a third: move it into the corners, "
                       "or the lens distortion is guessed outside)")
    if len(cal.used) < MIN_PAIRS:
        out.append(f"{len(cal.used)} usable pairs (fewer than {MIN_PAIRS}: take more, at different angles)")
    return out


# -- outputs ------------------------------------------------------------------------------------


def write_outputs(cal: Calibration, path: Path) -> tuple[Path, Path]:
    """``calib.yaml`` (metres, with ``units: m`` and the image size) and beside it
    ``<stem>_report.md`` with ``<stem>_coverage.png``; the report's and figure's paths."""
    save_calibration(cal.rig, path, units="m")
    fig = path.with_name(f"{path.stem}_coverage.png")
    _coverage_figure(cal, fig)
    report = path.with_name(f"{path.stem}_report.md")
    write_text(report, report_text(cal, path.name, fig.name))
    return report, fig


def report_text(cal: Calibration, calib_name: str, fig_name: str) -> str:
    K1, K2 = cal.rig.left.K, cal.rig.right.K
    lines = [f"# Calibration report: {calib_name}", "",
             *(f"**Warning:** {w}" for w in cal.warnings), *([""] if cal.warnings else []),
             "| quantity | value |", "|---|---:|",
             f"| pairs used | {len(cal.used)} of {len(cal.used) + len(cal.rejected)} |",
             f"| RMS reprojection, left / right / stereo (px) | {cal.rms_left:.3f} / {cal.rms_right:.3f} / "
             f"{cal.rms_stereo:.3f} |",
             f"| rectified epipolar error, median / max (px) | {cal.epipolar_px[0]:.3f} / {cal.epipolar_px[1]:.3f} |",
             f"| baseline (m) | {cal.baseline:.5f} |",
             f"| second camera, seen from the first | {cal.second_camera_side} |",
             f"| focal lengths left fx, fy (px) | {K1[0, 0]:.2f}, {K1[1, 1]:.2f} |",
             f"| focal lengths right fx, fy (px) | {K2[0, 0]:.2f}, {K2[1, 1]:.2f} |",
             f"| board coverage left / right | {100 * cal.coverage[0]:.0f} % / {100 * cal.coverage[1]:.0f} % |",
             f"| views whose board only the classic detector found | {cal.classic} |",
             f"| each camera's own board images used for its intrinsics, left / right | {cal.singles[0]} / "
             f"{cal.singles[1]} |",
             "", f"![board coverage]({fig_name})", "", "## Pairs", "", "| pair | stereo RMS (px) | used |", "|---|---:|---|"]
    turned = ", right view reordered (its corners were listed from the opposite end)"
    lines += [f"| {n} | {e:.3f} | yes{turned if n in cal.reordered else ''} |" for n, e in cal.pair_errors.items()]
    lines += [f"| {n} | — | no: {why} |" for n, why in cal.rejected.items()]
    if cal.singles_skipped:
        lines += ["", "## Single-camera images left out", "", *(f"- {n}: {why}" for n, why in cal.singles_skipped.items())]
    return "\n".join(lines) + "\n"


def _coverage_figure(cal: Calibration, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    w, h = cal.rig.image_size
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6), dpi=100)
    for ax, hulls, name, cov in zip(axes, cal.hulls, ("left", "right"), cal.coverage, strict=True):
        for hull in hulls:
            ax.fill(hull[:, 0], hull[:, 1], alpha=0.15, color="tab:blue", lw=0)
            ax.plot(*np.vstack([hull, hull[:1]]).T, color="tab:blue", lw=0.6)
        ax.set(xlim=(0, w), ylim=(h, 0), aspect="equal", title=f"{name}: board covers {100 * cov:.0f} % of the image")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp)
    plt.close(fig)


def check_replaceable_calibration(out: Path, force: bool = False) -> None:
    """Refuse to replace a calibration stereotrack did not write: an existing ``out`` is replaced
    only when its report (``<stem>_report.md``, which ``calibrate`` writes beside it) is there too,
    or with ``force``; one line naming the file otherwise."""
    if out.exists() and not force and not out.with_name(f"{out.stem}_report.md").is_file():
        raise StereotrackError("exists and was not written by `stereotrack calibrate` (no report beside it): "
                               "choose another -o, or pass --force to replace it", out)


def calibrate_folder(images: str | Path, board: Board, out: str | Path, force: bool = False,
                     singles: tuple[Path | None, Path | None] = (None, None)) -> tuple[Calibration, Path, Path]:
    """The whole command: pairs (and each camera's own board images, folders ``singles``) →
    calibration → calib.yaml and its report (warnings emitted); a calibration stereotrack did not
    write is not replaced (:func:`check_replaceable_calibration`)."""
    check_replaceable_calibration(Path(out), force)
    own = tuple(_folder_images(d) if d is not None else [] for d in singles)
    cal = calibrate(find_pairs(Path(images)), board, (own[0], own[1]))
    if cal.rms_stereo > ABSURD_RMS_PX and not force:
        raise StereotrackError(f"not written: the stereo RMS reprojection error is {cal.rms_stereo:.1f} px (baseline "
                               f"{cal.baseline:.4g} m): the corners do not fit one rig (a wrong --board, a moving board, "
                               "pairs that are not simultaneous); --force writes it anyway", out)
    report, fig = write_outputs(cal, Path(out))
    for w in cal.warnings:
        warnings.warn(f"{out}: poor calibration: {w}", stacklevel=2)
    return cal, report, fig
