"""Tables written twice (Markdown and HTML) from one description: numbers right-aligned, each
column's best value marked, so report.md, report.html and the batch summary never disagree."""

from __future__ import annotations

import html
import math
import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any


def number(spec: str, scale: float = 1.0, suffix: str = "") -> Callable[[Any], str]:
    """A formatter: ``value × scale`` with ``spec`` (``"—"`` for missing or non-finite values)."""
    def fmt(v: Any) -> str:
        if v is None or (isinstance(v, float) and not math.isfinite(v)):
            return "—"
        if not isinstance(v, (int, float)) or isinstance(v, bool):
            return str(v)
        v = v * scale
        return f"{round(v) if spec.endswith('d') else v:{spec}}{suffix}"
    return fmt


@dataclass
class Column:
    """A column: its title, one value per row, how values print, and which is best: ``"min"``,
    ``"max"``, or a number the best value is closest to (1 for a normalized NEES); None: no best.
    ``good``: the range a value must lie in to be marked at all (a filter's consistency: the
    closest of many failures is no best)."""
    title: str
    values: Sequence[Any]
    fmt: Callable[[Any], str] = str
    best: str | float | None = None
    good: tuple[float, float] | None = None

    def best_row(self) -> int | None:
        """The row holding the best value (None without a rule, or with fewer than two values)."""
        ok = [(i, float(v)) for i, v in enumerate(self.values)
              if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)]
        if self.good is not None:
            ok = [(i, v) for i, v in ok if self.good[0] <= v <= self.good[1]]
        if self.best is None or len(ok) < 2 - (self.good is not None):
            return None
        if self.best == "min":
            return min(ok, key=lambda t: t[1])[0]
        if self.best == "max":
            return max(ok, key=lambda t: t[1])[0]
        target = float(self.best)  # a number to be near
        return min(ok, key=lambda t: abs(t[1] - target))[0]


@dataclass
class Table:
    """Row labels (the first column, text) and numeric columns."""
    label: str
    rows: Sequence[str]
    columns: list[Column]
    notes: list[str] = field(default_factory=list)
    #: per row, an optional link for its label (HTML only), e.g. a clip's report
    links: Sequence[str | None] = ()

    def cells(self) -> list[list[tuple[str, bool]]]:
        """(text, is best) for every row and column; rows that print the best value all are."""
        text = [[c.fmt(c.values[i]) for c in self.columns] for i in range(len(self.rows))]
        best = [c.best_row() for c in self.columns]
        return [[(text[i][j], b is not None and text[i][j] == text[b][j]) for j, b in enumerate(best)]
                for i in range(len(self.rows))]


def inline(text: str) -> str:
    """Escaped HTML of one line of Markdown's inline marks (``**bold**``, ```code```)."""
    text = html.escape(text)
    text = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", text)
    return re.sub(r"`(.+?)`", r"<code>\1</code>", text)


def to_markdown(t: Table) -> str:
    """A Markdown table: numbers right-aligned, each column's best value in bold."""
    head = f"| {t.label} | " + " | ".join(c.title for c in t.columns) + " |"
    rule = "|---|" + "---:|" * len(t.columns)
    body = [f"| {r} | " + " | ".join(f"**{s}**" if b else s for s, b in row) + " |"
            for r, row in zip(t.rows, t.cells(), strict=True)]
    return "\n".join([head, rule, *body, *([""] + [f"- {n}" for n in t.notes] if t.notes else [])])


def to_html(t: Table) -> str:
    """An HTML table: numbers right-aligned, each column's best value marked (class ``best``)."""
    e = html.escape
    links = list(t.links) or [None] * len(t.rows)
    head = "<tr><th>" + e(t.label) + "</th>" + "".join(f"<th>{e(c.title)}</th>" for c in t.columns) + "</tr>"
    body = []
    for r, link, row in zip(t.rows, links, t.cells(), strict=True):
        name = f'<a href="{e(link)}">{e(r)}</a>' if link else e(r)
        tds = "".join(f'<td class="num best">{e(s)}</td>' if b else f'<td class="num">{e(s)}</td>' for s, b in row)
        body.append(f"<tr><th scope=row>{name}</th>{tds}</tr>")
    notes = "".join(f"<p class=note>{inline(n)}</p>" for n in t.notes)
    return f"<div class=wide><table><thead>{head}</thead><tbody>{''.join(body)}</tbody></table></div>{notes}"
