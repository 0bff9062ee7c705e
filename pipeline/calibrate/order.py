"""One corner order for both views of a pair. A chessboard whose pattern looks the same turned by
180° (odd × odd inner corners, or a symmetric print) can be listed from opposite corners in the two
views of one pair; calibrating such a pair as it comes pairs each corner with its mirror image and
drags the baseline (Zhang's method needs the same board point in both views: Z. Zhang, TPAMI
22(11), 2000). Each view's board pose (``solvePnP`` through that camera's own intrinsics, which do
not depend on the order) gives the pair's relative pose; a reversed view's differs from every
other pair's by the board's half turn. The order kept for each pair is the one whose relative pose
agrees with the most pairs."""

from __future__ import annotations

import cv2
import numpy as np

#: relative rotations within this angle (degrees) of each other are one rig
AGREE_DEG = 5.0


def reversed_pairs(found: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], size: tuple[int, int]) -> list[str]:
    """The pairs (of ``found``: name → board points, left corners, right corners) whose right view
    lists the corners in the opposite order to their left view: those where the reversed order
    gives a relative pose that agrees with more pairs. Only boards of a full grid can be reversed
    (a ChArUco board names its corners)."""
    names = list(found)
    if len(names) < 3:
        return []
    obj = [found[n][0] for n in names]
    flags = cv2.CALIB_FIX_K3
    _, K1, D1, *_ = cv2.calibrateCamera(obj, [found[n][1].astype(np.float32) for n in names], size, None, None,
                                        flags=flags)
    _, K2, D2, *_ = cv2.calibrateCamera(obj, [found[n][2].astype(np.float32) for n in names], size, None, None,
                                        flags=flags)
    rel = {}
    for n in names:
        o, left, right = found[n]
        Rl = _pose(o, left, K1, D1)
        rel[n] = (_pose(o, right, K2, D2) @ Rl.T, _pose(o, right[::-1], K2, D2) @ Rl.T)
    candidates = [r for n in names for r in rel[n]]
    support = [sum(min(_angle(c, rel[n][0]), _angle(c, rel[n][1])) < AGREE_DEG for n in names) for c in candidates]
    ref = candidates[int(np.argmax(support))]
    return [n for n in names if _angle(ref, rel[n][1]) < _angle(ref, rel[n][0])]


def _pose(obj: np.ndarray, img: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """The board's rotation in the camera (world = board)."""
    _, rvec, _ = cv2.solvePnP(obj, img.astype(np.float64), K, D)
    return cv2.Rodrigues(rvec)[0]


def _angle(A: np.ndarray, B: np.ndarray) -> float:
    """The angle (degrees) of the rotation taking ``A`` to ``B``."""
    c = (np.trace(A.T @ B) - 1.0) / 2.0
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))
