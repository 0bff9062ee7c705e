"""A planar calibration board's geometry and texture: what ``stereotrack calibrate`` looks for and
what the board renderer draws (one definition for both)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

TEXELS_PER_SQUARE = 64


@dataclass(frozen=True)
class Board:
    """A planar calibration target. ``chessboard``: ``cols × rows`` inner corners (OpenCV's pattern
    size), squares of ``square`` m, one square of white margin. ``charuco``: ``cols × rows``
    squares, ArUco markers of ``marker`` m from dictionary ``dictionary``."""

    kind: str
    cols: int
    rows: int
    square: float
    marker: float = 0.0
    dictionary: str = "DICT_4X4_50"

    @property
    def squares(self) -> tuple[int, int]:
        """Squares across and down."""
        return (self.cols + 1, self.rows + 1) if self.kind == "chessboard" else (self.cols, self.rows)

    @property
    def margin(self) -> float:
        """The white border around the squares (m): a detector needs a quiet zone."""
        return self.square

    @property
    def size(self) -> tuple[float, float]:
        """Width and height of the whole board (squares and margin), metres."""
        nx, ny = self.squares
        return nx * self.square + 2 * self.margin, ny * self.square + 2 * self.margin

    def charuco(self):
        """The OpenCV ``CharucoBoard`` of a ChArUco board."""
        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard(self.squares, self.square, self.marker, d)

    def texture(self) -> np.ndarray:
        """The board as a grey image, ``TEXELS_PER_SQUARE`` texels per square, margin included."""
        nx, ny = self.squares
        t = TEXELS_PER_SQUARE
        if self.kind == "charuco":
            img = self.charuco().generateImage((nx * t + 2 * t, ny * t + 2 * t), marginSize=t)
            return img.astype(np.uint8)
        img = np.full(((ny + 2) * t, (nx + 2) * t), 255, np.uint8)
        for j in range(ny):
            for i in range(nx):
                if (i + j) % 2 == 0:
                    img[(j + 1) * t : (j + 2) * t, (i + 1) * t : (i + 2) * t] = 0
        return img
