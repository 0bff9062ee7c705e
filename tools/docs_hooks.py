"""mkdocs hook: the file-format tables of the docs, generated from the schemas in the code
(``pipeline.core.clip``, ``pipeline.core.outputs``, ``pipeline.present.summary``) so no column is
described twice. A page asks for them with ``<!-- generated: file formats -->``."""

from __future__ import annotations

from typing import Any

MARKER = "<!-- generated: file formats -->"


def _names(names: list[str]) -> str:
    """A run of columns with one meaning: listed up to three, else ``first … last``."""
    quoted = [f"`{n}`" for n in names]
    return ", ".join(quoted) if len(quoted) <= 3 else f"{quoted[0]} … {quoted[-1]}"


def schema_markdown(schema: Any) -> str:
    """One CSV table's contract: its file, what a row is, who writes it, and its columns in
    order (a run of columns with the same meaning on one line)."""
    runs: list[tuple[list[str], str]] = []
    for name, meaning in schema.columns.items():
        if runs and runs[-1][1] == meaning:
            runs[-1][0].append(name)
        else:
            runs.append(([name], meaning))
    lines = [f"### `{schema.file}`", "", f"One row: {schema.row}. Written by: {schema.written_by}."]
    if schema.extends is not None:
        lines[-1] += f" The columns of `{schema.extends.file}`, then:"
    lines += ["", "| column | meaning |", "|---|---|"]
    lines += [f"| {_names(names)} | {meaning} |" for names, meaning in runs]
    return "\n".join(lines)


def outputs_markdown() -> str:
    """The output folder's files, from :class:`pipeline.core.outputs.Outputs`."""
    from pipeline.core.outputs import Outputs

    lines = ["| file | what it holds |", "|---|---|"]
    lines += [f"| `{f.name}` | {f.what} |" for f in Outputs.files()]
    return "\n".join(lines)


def settings_markdown() -> str:
    """``clip.yaml``'s keys, from :class:`pipeline.core.clip.ClipSettings`."""
    from pipeline.core.clip import CLIP_SETTINGS, ClipSettings
    from pipeline.core.docstrings import attribute_docs

    docs = attribute_docs(ClipSettings)
    lines = [f"### `{CLIP_SETTINGS}`", "", "| key | meaning |", "|---|---|"]
    lines += [f"| `{k}` | {docs.get(k, '')} |" for k in ClipSettings.model_fields]
    return "\n".join(lines)


def file_formats() -> str:
    """Every generated section, in the order a clip is made and read."""
    from pipeline.core.clip import SCHEMAS
    from pipeline.present.summary import METHODS_SUMMARY, SUMMARY

    parts = ["## The output folder", outputs_markdown(), "## Tables", settings_markdown()]
    parts += [schema_markdown(s) for s in (*SCHEMAS, SUMMARY, METHODS_SUMMARY)]
    return "\n\n".join(parts)


def on_page_markdown(markdown: str, **_: Any) -> str:
    """Replace the marker, where a page has it, with the generated tables."""
    return markdown.replace(MARKER, file_formats()) if MARKER in markdown else markdown
