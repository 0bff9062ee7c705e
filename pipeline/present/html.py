"""Self-contained HTML pages (report.html, summary.html): one stylesheet, figures inline (SVG),
nothing fetched from elsewhere, so a page can be mailed or opened offline."""

from __future__ import annotations

import html

STYLE = """
body{font:15px/1.45 system-ui,-apple-system,Segoe UI,Roboto,sans-serif;max-width:1180px;margin:2em auto;
padding:0 1em;color:#1b1b1b}
h1{font-size:1.6em;margin-bottom:.2em}h2{font-size:1.2em;margin-top:1.8em;border-bottom:1px solid #ddd}
.wide{overflow-x:auto}table{border-collapse:collapse;margin:.6em 0;font-variant-numeric:tabular-nums}
th,td{padding:.25em .7em;border-bottom:1px solid #eee}th{text-align:left;font-weight:600}
thead th{border-bottom:2px solid #bbb;text-align:right}thead th:first-child{text-align:left}
td.num{text-align:right;white-space:nowrap}td.best{font-weight:700;background:#e6f4ea}
.swatch{display:inline-block;width:.9em;height:.9em;border-radius:2px;margin-right:.4em;vertical-align:-.1em}
.checks{border:2px solid #2e7d32;background:#f1f8f2;padding:.6em 1em;border-radius:6px}
.checks.failed{border-color:#c62828;background:#fdecea}.checks ul{margin:.3em 0;padding-left:0;list-style:none}
.checks li.pass::before{content:"✓ ";color:#2e7d32;font-weight:700}
.checks li.fail::before{content:"✗ ";color:#c62828;font-weight:700}
.note{color:#555;font-size:.9em;margin:.2em 0}code,pre{background:#f4f4f4;border-radius:3px;padding:.1em .3em}
pre{padding:.6em}figure{margin:1em 0}figure img,figure svg{max-width:100%;height:auto}figcaption{color:#555;font-size:.9em}
"""


def page(title: str, body: list[str]) -> str:
    """A complete HTML document."""
    return (f"<!doctype html><html lang=en><head><meta charset=utf-8><title>{html.escape(title)}</title>"
            f"<meta name=viewport content='width=device-width,initial-scale=1'><style>{STYLE}</style></head>"
            f"<body>{''.join(body)}</body></html>\n")


def figure(svg: str, caption: str) -> str:
    """An SVG figure inline (scaled to the page's width), with its caption."""
    svg = svg.replace("<svg ", f"<svg role=img aria-label='{html.escape(caption)}' ", 1)
    return f"<figure>{svg}<figcaption>{html.escape(caption)}</figcaption></figure>"


def swatch(hex_colour: str, name: str) -> str:
    """A method's name after a square of its colour."""
    return f"<span class=swatch style='background:{hex_colour}'></span>{html.escape(name)}"
