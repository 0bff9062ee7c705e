"""The report's figures as SVG text, drawn directly: axes with round-number ticks (linear or log),
lines that break at NaN, dots, a shaded band and one legend per figure. A report's five figures
take milliseconds this way where matplotlib took longer to import than the detect stage runs, and
the SVG scales in report.html and in any Markdown viewer of report.md."""

from __future__ import annotations

import html
import math
from dataclasses import dataclass, field, replace

import numpy as np

#: SVG stroke dash patterns per matplotlib-style line style (in units of the line width)
DASHES = {"-": None, "--": (3.7, 1.6), "-.": (6.4, 1.6, 1.0, 1.6), ":": (1.0, 1.65)}
FONT = "font-family='DejaVu Sans,Segoe UI,Helvetica,Arial,sans-serif'"
#: pixels around an axes box: room for tick labels, the axis labels and the title
PAD_LEFT, PAD_RIGHT, PAD_TOP, PAD_BOTTOM = 75, 20, 30, 50
LEGEND_WIDTH = 190
#: pixel coordinates are clipped to ±OFF: a value far off the axes stays off them, finite
OFF = 1e5


def nice_ticks(lo: float, hi: float, target: int = 6) -> np.ndarray:
    """Round-number ticks (steps of 1, 2, 2.5 or 5 × 10^k) inside [lo, hi], about ``target`` of them."""
    span = hi - lo
    raw = span / max(target, 1)
    mag = 10.0 ** math.floor(math.log10(raw))
    step = next(m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw)
    first = math.ceil(lo / step - 1e-9) * step
    ticks = first + step * np.arange(math.floor((hi - first) / step + 1e-9) + 1)
    return np.round(ticks / step) * step


def log_ticks(lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """(labelled, unlabelled) ticks of a log axis over [lo, hi] (values, not logs): decades, and
    2 and 5 of each decade labelled when the range spans under two decades; a narrower range than
    that labels what it has."""
    d0, d1 = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    every = [m * 10.0 ** d for d in range(d0, d1 + 1) for m in range(1, 10)]
    inside = np.array([v for v in every if lo <= v * (1 + 1e-9) and v <= hi * (1 + 1e-9)])
    lead = np.round(inside / 10.0 ** np.floor(np.log10(inside)), 6) if inside.size else inside
    named = np.isin(lead, (1.0, 2.0, 5.0)) if math.log10(hi) - math.log10(lo) < 2 else lead == 1.0
    if not named.any():  # a range inside one step of 1–9: label every step, else round numbers of the range
        return (inside, inside[:0]) if inside.size else (nice_ticks(lo, hi, 3), inside)
    if d1 - d0 > 10:  # a diverged filter's many decades: every k-th decade, no minor ticks
        decades = 10.0 ** np.arange(d0, d1 + 1)
        decades = decades[(decades >= lo) & (decades <= hi)]
        return decades[:: -(-len(decades) // 8)], inside[:0]
    return inside[named], inside[~named]


def label(v: float) -> str:
    """A tick label: the shortest plain form (no powers of ten, no -0)."""
    v = 0.0 if abs(v) < 1e-12 else v
    return f"{v:.6g}".replace("-", "−")


def _dash(style: str, width: float) -> str:
    d = DASHES.get(style)
    return f" stroke-dasharray='{' '.join(f'{width * x:.2f}' for x in d)}'" if d else ""


@dataclass
class Entry:
    """One legend entry: a line (with its style) or a dot."""
    colour: str
    style: str = "-"
    width: float = 1.0
    opacity: float = 1.0
    dot: bool = False
    fill: bool = False


@dataclass
class Axes:
    """One plot box: data limits, scale, and the SVG elements drawn into it."""
    box: tuple[float, float, float, float]  # x, y, width, height in pixels
    xlim: tuple[float, float] | None = None
    ylim: tuple[float, float] | None = None
    ylog: bool = False
    yinvert: bool = False
    title: str = ""
    xlabel: str = ""
    ylabel: str = ""
    items: list[tuple[str, np.ndarray, np.ndarray, dict]] = field(default_factory=list)
    legend: dict[str, Entry] = field(default_factory=dict)

    def line(self, x, y, colour: str, style: str = "-", width: float = 1.0, opacity: float = 1.0,
             name: str | None = None) -> None:
        """A line through (x, y), broken where a value is NaN (or not positive on a log axis)."""
        self._add("line", x, y, Entry(colour, style, width, opacity), name)

    def dots(self, x, y, colour: str, radius: float = 1.3, name: str | None = None) -> None:
        """A dot at each finite (x, y)."""
        self._add("dots", x, y, Entry(colour, width=radius, dot=True), name)

    def band(self, y0: float, y1: float, colour: str = "#d9d9d9", name: str | None = None) -> None:
        """A horizontal band from y0 to y1 across the axes, under everything else."""
        self.items.insert(0, ("band", np.array([y0, y1]), np.array([y0, y1]), {"colour": colour}))
        if name:
            self.legend.setdefault(name, Entry(colour, fill=True))

    def _add(self, kind: str, x, y, entry: Entry, name: str | None) -> None:
        x, y = np.asarray(x, float), np.asarray(y, float)
        self.items.append((kind, x, y, {"entry": entry, "name": name}))
        if name:
            self.legend.setdefault(name, entry)

    def names(self) -> list[str | None]:
        """The name of each line and set of dots drawn, in drawing order (one legend entry per name)."""
        return [opts.get("name") for kind, _, _, opts in self.items if kind != "band"]

    def limits(self) -> tuple[tuple[float, float], tuple[float, float]]:
        """The axes' limits: those set, else the drawn data's range padded by 5 %."""
        def auto(values: list[np.ndarray], log: bool) -> tuple[float, float]:
            v = np.concatenate([a[np.isfinite(a) & ((a > 0) if log else True)] for a in values] or [np.empty(0)])
            if not v.size:
                return (1.0, 10.0) if log else (0.0, 1.0)
            if log:  # within 10^±250: a diverged filter's 1e300 must not overflow the padding
                lo, hi = np.clip(np.log10([v.min(), v.max()]), -250.0, 250.0)
                pad = 0.05 * max(hi - lo, 0.1)
                return 10 ** (lo - pad), 10 ** (hi + pad)
            lo, hi = np.clip([v.min(), v.max()], -1e300, 1e300).tolist()  # padded without overflow
            pad = 0.05 * (hi - lo) if hi > lo else max(abs(lo), 1.0) * 0.05
            return lo - pad, hi + pad

        lines = [it for it in self.items if it[0] != "band"]  # a band spans every x; its y counts
        xlim = self.xlim or auto([it[1] for it in lines], False)
        ylim = self.ylim or auto([it[2] for it in self.items], self.ylog)
        return xlim, ylim

    def equal_aspect(self) -> None:
        """Widen the shorter data range so that a unit is as long on both axes (image tracks)."""
        (x0, x1), (y0, y1) = self.limits()
        _, _, w, h = self.box
        per_px = max((x1 - x0) / w, (y1 - y0) / h)
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        self.xlim = cx - per_px * w / 2, cx + per_px * w / 2
        self.ylim = cy - per_px * h / 2, cy + per_px * h / 2

    def transform(self) -> tuple:
        """Functions data → pixel for x and y."""
        (x0, x1), (y0, y1) = self.limits()
        bx, by, w, h = self.box
        fy = (lambda v: np.log10(np.where(v > 0, v, np.nan))) if self.ylog else (lambda v: v)
        ly0, ly1 = (math.log10(y0), math.log10(y1)) if self.ylog else (y0, y1)
        top = (ly0, ly1) if self.yinvert else (ly1, ly0)

        def X(v):
            return bx + (np.asarray(v, float) - x0) / (x1 - x0) * w

        def Y(v):
            return by + (fy(np.asarray(v, float)) - top[0]) / (top[1] - top[0]) * h
        return X, Y


def _path(px: np.ndarray, py: np.ndarray) -> str:
    """SVG path data through the points, a new subpath after every non-finite point (formatted
    from Python floats: numpy's scalars format several times slower)."""
    ok = np.isfinite(px) & np.isfinite(py)
    start = ok & ~np.concatenate([[False], ok[:-1]])  # the first point after a break begins a subpath
    cmd = np.where(start, "M", "L")[ok].tolist()
    xs, ys = px[ok].round(1).tolist(), py[ok].round(1).tolist()
    return "".join(f"{c}{a:g} {b:g}" for c, a, b in zip(cmd, xs, ys, strict=True))


def _draw_item(kind: str, px: np.ndarray, py: np.ndarray, opts: dict, box: tuple) -> str:
    if kind == "band":
        bx, _, w, _ = box
        top, bottom = np.nanmin(py), np.nanmax(py)
        return f"<rect x='{bx:g}' y='{top:.1f}' width='{w:g}' height='{bottom - top:.1f}' fill='{opts['colour']}'/>"
    e: Entry = opts["entry"]
    if kind == "dots":
        ok = np.isfinite(px) & np.isfinite(py)
        d = "".join(f"M{a:g} {b:g}h0" for a, b in zip(px[ok].round(1).tolist(), py[ok].round(1).tolist(), strict=True))
        return (f"<path d='{d}' stroke='{e.colour}' stroke-width='{2 * e.width:g}' stroke-linecap='round' "
                "fill='none'/>")
    alpha = f" stroke-opacity='{e.opacity:g}'" if e.opacity < 1 else ""
    return (f"<path d='{_path(px, py)}' fill='none' stroke='{e.colour}' stroke-width='{e.width:g}'"
            f"{_dash(e.style, e.width)}{alpha} stroke-linejoin='round'/>")


def _text(x: float, y: float, s: str, anchor: str = "middle", size: int = 12, extra: str = "") -> str:
    return (f"<text x='{x:.1f}' y='{y:.1f}' text-anchor='{anchor}' font-size='{size}' {extra}>"
            f"{html.escape(s)}</text>")


def _ticks(ax: Axes) -> list[str]:
    """Grid lines, tick marks and labels of both axes."""
    X, Y = ax.transform()
    (x0, x1), (y0, y1) = ax.limits()
    bx, by, w, h = ax.box
    out = []
    for v in nice_ticks(x0, x1, max(3, round(w / 60))):
        p = float(X(v))
        out += [f"<line x1='{p:.1f}' x2='{p:.1f}' y1='{by:g}' y2='{by + h:g}' class='st-grid'/>",
                _text(p, by + h + 16, label(v))]
    if ax.ylog:
        named, minor = log_ticks(y0, y1)
        for v in minor:
            p = float(Y(v))
            out.append(f"<line x1='{bx:g}' x2='{bx + w:g}' y1='{p:.1f}' y2='{p:.1f}' class='st-grid st-minor'/>")
    else:
        named = nice_ticks(min(y0, y1), max(y0, y1), max(3, round(h / 45)))
    for v in named:
        p = float(Y(v))
        out += [f"<line x1='{bx:g}' x2='{bx + w:g}' y1='{p:.1f}' y2='{p:.1f}' class='st-grid'/>",
                _text(bx - 6, p + 4, label(v), "end")]
    return out


@dataclass
class Figure:
    """A grid of :class:`Axes` and one legend right of them, written out as an SVG document."""
    width: int
    height: int
    rows: int = 1
    cols: int = 1
    ident: str = "fig"
    axes: list[Axes] = field(default_factory=list)

    def __post_init__(self) -> None:
        plot_w = self.width - LEGEND_WIDTH
        cw, rh = plot_w / self.cols, self.height / self.rows
        self.axes = [Axes((c * cw + PAD_LEFT, r * rh + PAD_TOP, cw - PAD_LEFT - PAD_RIGHT, rh - PAD_TOP - PAD_BOTTOM))
                     for r in range(self.rows) for c in range(self.cols)]

    def legend_labels(self) -> set[str]:
        """Every name in the figure's legend."""
        return {n for ax in self.axes for n in ax.legend}

    def _legend(self) -> list[str]:
        entries: dict[str, Entry] = {}
        for ax in self.axes:
            for n, e in ax.legend.items():
                entries.setdefault(n, e)
        x = self.width - LEGEND_WIDTH + 10
        gap = min(18.0, (self.height - 20) / max(len(entries), 1))  # a long legend packed closer, never cut
        y = (self.height - gap * (len(entries) - 1)) / 2
        out = []
        for i, (n, e) in enumerate(entries.items()):
            cy = y + gap * i
            if e.fill:
                out.append(f"<rect x='{x}' y='{cy - 6:.1f}' width='24' height='12' fill='{e.colour}'/>")
            elif e.dot:
                out.append(f"<circle cx='{x + 12}' cy='{cy:.1f}' r='3' fill='{e.colour}'/>")
            else:
                alpha = f" stroke-opacity='{e.opacity:g}'" if e.opacity < 1 else ""
                out.append(f"<line x1='{x}' x2='{x + 24}' y1='{cy:.1f}' y2='{cy:.1f}' stroke='{e.colour}' "
                           f"stroke-width='{max(e.width, 1.5):g}'{_dash(e.style, max(e.width, 1.5))}{alpha}/>")
            out.append(_text(x + 30, cy + 4, n, "start", size=12 if gap >= 14 else max(7, int(gap - 2))))
        return out

    def _axes_svg(self, i: int, ax: Axes) -> list[str]:
        xlim, ylim = ax.limits()
        ax = replace(ax, xlim=xlim, ylim=ylim)  # the data's range found once, not by every call below
        X, Y = ax.transform()
        bx, by, w, h = ax.box
        clip = f"{self.ident}-c{i}"
        out = [f"<clipPath id='{clip}'><rect x='{bx:g}' y='{by:g}' width='{w:g}' height='{h:g}'/></clipPath>",
               *_ticks(ax), f"<g clip-path='url(#{clip})'>"]
        with np.errstate(all="ignore"):  # far off the axes (a runaway): kept finite, the clip path hides it
            out += [_draw_item(kind, np.clip(X(x), -OFF, OFF), np.clip(Y(y), -OFF, OFF), opts, ax.box)
                    for kind, x, y, opts in ax.items]
        out += ["</g>", f"<rect x='{bx:g}' y='{by:g}' width='{w:g}' height='{h:g}' fill='none' stroke='#444'/>",
                _text(bx + w / 2, by - 10, ax.title, size=13), _text(bx + w / 2, by + h + 38, ax.xlabel),
                _text(bx - 58, by + h / 2, ax.ylabel, extra=f"transform='rotate(-90 {bx - 58:.1f} {by + h / 2:.1f})'")]
        return out

    def svg(self) -> str:
        """The figure as a standalone SVG document."""
        body = [line for i, ax in enumerate(self.axes) for line in self._axes_svg(i, ax)] + self._legend()
        return (f"<svg xmlns='http://www.w3.org/2000/svg' viewBox='0 0 {self.width} {self.height}' "
                f"width='{self.width}' height='{self.height}' {FONT} fill='#222'>"
                "<style>.st-grid{stroke:#000;stroke-opacity:.12}.st-minor{stroke-opacity:.06}</style>"
                f"<rect width='100%' height='100%' fill='#fff'/>{''.join(body)}</svg>\n")
