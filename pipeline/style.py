"""One colour and line style per method and per marker, shared by the report's figures and the
rerun recording, so a curve is the same method everywhere."""

from __future__ import annotations

import zlib

#: 20 distinguishable colours (matplotlib's tab10 and the dark half of tab20b/tab20c), RGB 0–255
PALETTE: list[tuple[int, int, int]] = [
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
    (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207), (57, 59, 121), (99, 121, 57),
    (140, 109, 49), (132, 60, 57), (123, 65, 115), (49, 130, 189), (230, 85, 13), (49, 163, 84),
    (117, 107, 177), (99, 99, 99)]
LINE_STYLES = ["-", "--", "-.", ":"]
TRUTH_RGB = (0, 0, 0)


def _index(method: str) -> int:
    """The method's position in the registry (stable across runs); unknown names hash."""
    from pipeline.estimators import registry

    names = list(registry())
    return names.index(method) if method in names else len(names) + zlib.crc32(method.encode()) % 97


def method_rgb(method: str) -> tuple[int, int, int]:
    """The method's colour (RGB 0–255): registry order through the palette."""
    return PALETTE[_index(method) % len(PALETTE)]


def method_colour(method: str) -> tuple[float, float, float]:
    """The method's colour for matplotlib (0–1)."""
    return tuple(c / 255 for c in method_rgb(method))  # type: ignore[return-value]


def method_linestyle(method: str) -> str:
    """Solid for the first 20 methods; dashed and dotted when the palette wraps."""
    return LINE_STYLES[(_index(method) // len(PALETTE)) % len(LINE_STYLES)]


def marker_rgb(colours: dict[str, list[int]], marker: str, fallback_index: int = 0) -> tuple[int, int, int]:
    """A marker's own colour as the detect stage recorded it (``detect.json``'s ``marker_colours``;
    the four points of a target share their colour), else a palette colour."""
    for name in (marker, marker.rsplit("_", 1)[0]):
        if name in colours:
            return tuple(int(c) for c in colours[name][:3])  # type: ignore[return-value]
    return PALETTE[fallback_index % len(PALETTE)]
