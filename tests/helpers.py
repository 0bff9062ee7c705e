"""Helpers the test modules share: the sample clip as a real rig ships it, the CLI run in-process,
and the checks of a one-line error."""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
from pathlib import Path

import numpy as np
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


def opensim_tokens(line: str) -> list[str]:
    """OpenSim 4.x's ``FileAdapter::tokenize`` on tabs: consecutive tabs give empty tokens, but the
    text after the last tab is a token only when not empty (a row's empty last cell is dropped)."""
    parts = line.split("\t")
    return parts[:-1] if parts[-1] == "" else parts


def read_trc(path: Path) -> tuple[dict, list[str], np.ndarray]:
    """An independent TRC reader (the layout OpenSim documents, rows tokenized as OpenSim's reader
    does and required to hold every value): header values, marker names, frames × markers × 3."""
    lines = path.read_text().split("\n")
    keys, values = lines[1].split("\t"), lines[2].split("\t")
    head = dict(zip(keys, values, strict=True))
    names = [n for n in lines[3].split("\t")[2:] if n]
    rows = [opensim_tokens(ln) for ln in lines[5:] if ln.strip()]
    assert all(len(r) == 2 + 3 * len(names) for r in rows), "a row OpenSim reads a value short"
    data = np.array([[float(c) if c else np.nan for c in r[2:]] for r in rows]).reshape(len(rows), len(names), 3)
    p_names, p_data = pose2sim_trc(path)
    assert p_names == names and p_data.shape == data.shape, "Pose2Sim's layout reads other markers or frames"
    np.testing.assert_array_equal(p_data, data)  # every value, NaN for NaN: the two readers agree exactly
    return head, names, data


def pose2sim_trc(path: Path) -> tuple[list[str], np.ndarray]:
    """A TRC read the way Pose2Sim reads one: the marker names every third cell of the fourth line
    from the third, the values by ``pandas.read_csv(sep="\\t", skiprows=4)`` without the first two
    columns (a row with too many cells is an error there; a short one is filled with NaN)."""
    import pandas as pd

    with open(path) as f:
        header = [next(f) for _ in range(5)]
    names = [m.strip() for m in header[3].split("\t")[2::3] if m.strip()]
    df = pd.read_csv(path, sep="\t", skiprows=4, encoding="utf-8")
    values = df.drop(df.columns[[0, 1]], axis=1).to_numpy(dtype=float)
    return names, values.reshape(len(df), len(names), 3)


#: metrics.json fields that time a run (wall clock), not what it computed
TIMING_KEYS = {"seconds_per_step", "steps_per_second"}


def untimed(obj):
    """A metrics.json value without its timing fields (:data:`TIMING_KEYS`): what two runs of the
    same computation agree on."""
    if isinstance(obj, dict):
        return {k: untimed(v) for k, v in obj.items() if k not in TIMING_KEYS}
    if isinstance(obj, list):
        return [untimed(v) for v in obj]
    return obj
