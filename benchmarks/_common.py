"""Helpers shared by the benchmark scripts: where their reports go, and printing as they measure."""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

DOCS = Path(__file__).resolve().parent.parent / "docs"


def add_output_args(ap: argparse.ArgumentParser) -> None:
    """``--out DIR`` (default: a new temporary folder) and ``--write-docs`` (write into docs/, the
    tracked copy the docs link to)."""
    ap.add_argument("--out", type=Path, default=None, help="folder for the report and figures (default: a temporary one)")
    ap.add_argument("--write-docs", action="store_true", help="write into docs/ (the tracked report)")


def output_dir(args: argparse.Namespace, prefix: str) -> Path:
    if args.write_docs:
        return DOCS
    return args.out or Path(tempfile.mkdtemp(prefix=f"stereotrack-{prefix}-"))


class LiveDoc(list):
    """Markdown lines, each printed (and flushed) the moment it is added, so a long benchmark
    shows every table row as it is measured."""

    def __init__(self, lines=()) -> None:
        super().__init__()
        self += lines

    def append(self, line: str) -> None:  # type: ignore[override]
        print(line, flush=True)
        super().append(line)

    def __iadd__(self, lines):  # type: ignore[override]
        for line in lines:
            self.append(line)
        return self
