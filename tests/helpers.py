"""Helpers the test modules share: the sample clip as a real rig ships it, the CLI run in-process,
and the checks of a one-line error."""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path

import pytest

from tests.conftest import REPO

SAMPLE = REPO / "data" / "clips" / "sample_small"
RED = "red:170-10:99:80"  # the sample clip's red marker, as the scenario's colour gives it


def real_copy(dest: Path, with_truth: bool = False) -> Path:
    """The sample clip as a real rig ships it: two videos and calib.yaml (truth kept on request)."""
    dest.mkdir(parents=True)
    for f in ("left.mp4", "right.mp4", "calib.yaml", *(("truth.csv",) if with_truth else ())):
        shutil.copy(SAMPLE / f, dest / f)
    return dest


def cli(monkeypatch, capsys, *args: str) -> tuple[int, str, str]:
    """Run the ``stereotrack`` entry point in-process: (exit code, stdout, stderr)."""
    from pipeline.app.cli import main

    monkeypatch.setattr(sys, "argv", ["stereotrack", *map(str, args)])
    with pytest.raises(SystemExit) as exc:
        main()
    cap = capsys.readouterr()
    return int(exc.value.code or 0), cap.out, cap.err


def assert_one_line_error(rc: int, out: str, err: str, expected: str, code: int = 2, case: str = "") -> None:
    """A command that failed as a user error should: exit ``code``, one ``error:`` line holding
    ``expected``, no traceback."""
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert rc == code, (case, err)
    assert len(errors) == 1 and expected in errors[0], (case, err)
    assert "Traceback" not in err + out, case


def snapshot(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest() if p.is_file() else "dir"
            for p in sorted(folder.rglob("*"))}


def failed_checks(out: Path) -> dict[str, str]:
    return {c["name"]: c["message"] for c in json.loads((out / "metrics.json").read_text())["checks"] if not c["ok"]}
