"""One colour and line style per method and per marker, shared by the report's figures and the
rerun recording, so a curve is the same method everywhere."""

from __future__ import annotations

import zlib
from typing import NamedTuple

import numpy as np


class LineStyle(NamedTuple):
    """How a series is stroked in the report's figures."""
    colour: str
    style: str
    width: float
    opacity: float

#: 24 colours picked greedily for the largest smallest CIELAB distance (CIE76 ΔE) from each other,
#: from black, white and grey (truth, backgrounds), starting from matplotlib's first five tab10
#: colours: the first 16 are ≥ 38 ΔE apart, all 24 ≥ 33 (``tests`` check it). RGB 0–255.
PALETTE: list[tuple[int, int, int]] = [
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (75, 0, 255),
    (255, 0, 225), (210, 195, 0), (120, 75, 0), (0, 210, 180), (255, 135, 165), (0, 75, 225),
    (180, 195, 120), (0, 225, 0), (180, 0, 120), (30, 105, 60), (255, 180, 135), (0, 210, 255),
    (135, 60, 75), (195, 105, 255), (180, 195, 255), (0, 135, 255), (255, 0, 105), (105, 120, 0)]
LINE_STYLES = ["-", "--", "-.", ":"]
#: truth: black, thick and dashed in the report's figures (no method is black or dashed before the
#: palette wraps); mid grey and small in the recording, visible on its light and dark themes
TRUTH_RGB = (0, 0, 0)
TRUTH_RGB_VIEWER = (128, 128, 128)
TRUTH_STYLE = LineStyle("#000000", "--", 2.2, 0.55)


def lab(rgb) -> np.ndarray:
    """sRGB (0–255, ``… × 3``) → CIELAB (D65), for colour distances."""
    c = np.asarray(rgb, float) / 255
    c = np.where(c > 0.04045, ((c + 0.055) / 1.055) ** 2.4, c / 12.92)
    m = np.array([[0.4124, 0.3576, 0.1805], [0.2126, 0.7152, 0.0722], [0.0193, 0.1192, 0.9505]])
    xyz = c @ m.T / np.array([0.95047, 1.0, 1.08883])
    f = np.where(xyz > 216 / 24389, np.cbrt(xyz), (24389 / 27 * xyz + 16) / 116)
    return np.stack([116 * f[..., 1] - 16, 500 * (f[..., 0] - f[..., 1]), 200 * (f[..., 1] - f[..., 2])], -1)


def delta_e(a, b) -> float:
    """CIE76 colour difference of two sRGB colours (about 2.3 is just noticeable)."""
    return float(np.linalg.norm(lab(a) - lab(b)))


def _index(method: str) -> int:
    """The method's position in the registry (stable across runs); unknown names hash."""
    from pipeline.estimators import registry

    names = list(registry())
    return names.index(method) if method in names else len(names) + zlib.crc32(method.encode()) % 97


def method_rgb(method: str) -> tuple[int, int, int]:
    """The method's colour (RGB 0–255): registry order through the palette."""
    return PALETTE[_index(method) % len(PALETTE)]


def method_hex(method: str) -> str:
    """The method's colour as ``#rrggbb`` (HTML)."""
    return rgb_hex(method_rgb(method))


def rgb_hex(rgb: tuple[int, int, int]) -> str:
    """An RGB colour (0–255) as ``#rrggbb`` (HTML, SVG)."""
    return "#{:02x}{:02x}{:02x}".format(*rgb)


def method_linestyle(method: str) -> str:
    """Solid while the palette lasts; dashed and dotted when it wraps."""
    return LINE_STYLES[(_index(method) // len(PALETTE)) % len(LINE_STYLES)]


def marker_rgb(colours: dict[str, list[int]], marker: str, fallback_index: int = 0) -> tuple[int, int, int]:
    """A marker's own colour as the detect stage recorded it (``detect.json``'s ``marker_colours``;
    the four points of a target share their colour), else a palette colour."""
    for name in (marker, marker.rsplit("_", 1)[0]):
        if name in colours:
            r, g, b = colours[name][:3]
            return int(r), int(g), int(b)
    return PALETTE[fallback_index % len(PALETTE)]
