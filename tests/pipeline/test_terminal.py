"""What the terminal's progress lines say (pipeline.app.cli_common)."""

from __future__ import annotations

import os
import re
import time

import pytest
from rich.progress import Progress

from pipeline.app.cli_common import stage_eta
from pipeline.app.progress import CountColumn, RemainingColumn


def test_no_rate_based_eta_for_the_estimate_stage_and_no_count_for_a_clip_line():
    """#41 item 7: the estimate stage's ETA said 3:19 for a 21 s stage (its methods differ a
    hundredfold in cost) and a batch's per-clip lines sat at ``0/?``. The estimate stage shows no
    remaining time, a clip's line no count; other stages keep both."""
    assert not stage_eta("estimate (12 tracks: 12 methods × 1 markers)") and stage_eta("detect (frame pairs)")
    progress = Progress(CountColumn(), RemainingColumn(), auto_refresh=False)
    timed = progress.add_task("detect", total=10)
    blind = progress.add_task("estimate", total=10, eta=False)
    clip = progress.add_task("  c0: detect", total=None, count=False, eta=False)
    for task in (timed, blind):
        progress.update(task, completed=1)
        time.sleep(0.05)
        progress.update(task, completed=2)
    tasks = {t.id: t for t in progress.tasks}
    remaining, count = RemainingColumn(), CountColumn()
    assert remaining.render(tasks[blind]).plain == "-:--:--" and remaining.render(tasks[timed]).plain != "-:--:--"
    assert count.render(tasks[clip]).plain == "" and count.render(tasks[timed]).plain == " 2/10"


@pytest.mark.slow
def test_run_and_batch_end_with_no_bar_at_zero_and_a_table_that_fits(tmp_path):
    """#41 (terminal): `run` and `batch` as a user's 80-column terminal shows them: every progress
    line left on screen is complete (no ``0/`` count, no ``?`` total), and the batch's table is
    whole (no cell cut to ``…``), best method first."""
    import shutil
    import subprocess
    import sys

    from tests.conftest import REPO

    clips = tmp_path / "in"
    for name in ("a", "b"):
        shutil.copytree(REPO / "data" / "clips" / "sample_small", clips / name)
    env = {**os.environ, "COLUMNS": "80"}
    cli = [sys.executable, "-m", "pipeline.app.cli"]
    run = subprocess.run([*cli, "run", str(clips / "a"), "--methods", "triangulation,ekf"], capture_output=True,
                         text=True, env=env, timeout=300)
    batch = subprocess.run([*cli, "batch", str(clips), "-o", str(tmp_path / "out"), "--workers", "1", "--methods",
                            "triangulation,ekf,alphabetagamma"], capture_output=True, text=True, env=env, timeout=300)
    for res in (run, batch):
        assert res.returncode == 0, res.stderr
        bars = [ln for ln in res.stderr.splitlines() if "━" in ln]
        assert bars and not any(re.search(r"\b0/|/\?", ln) for ln in bars), bars
    table = [ln for ln in batch.stdout.splitlines() if ln.startswith("│")]
    assert table and not any("…" in ln for ln in batch.stdout.splitlines()), batch.stdout
    assert table[-1].split("│")[1].strip() == "alphabetagamma"  # the worst last
    replay = next(ln for ln in batch.stdout.splitlines() if ln.startswith("replay every clip:"))
    view = subprocess.run([*cli, *replay.split("stereotrack ", 1)[1].split()], capture_output=True, text=True,
                          env={k: v for k, v in env.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}, timeout=60)
    listed = view.stdout.replace("\n", "")  # rich folds long paths at 80 columns
    assert view.returncode == 0 and listed.count("run.rrd") == 2, view.stdout + view.stderr  # both recordings


def test_a_stage_that_fails_leaves_no_bar_behind(tmp_path):
    """A stage stopped by bad input ends on its one error line: no frozen ``0/?`` bar above it and
    no blank line (piped output, as a log or CI sees it)."""
    import shutil
    import subprocess
    import sys

    from tests.conftest import REPO

    shutil.copytree(REPO / "data" / "clips" / "sample_small", tmp_path / "c")  # no detections.csv yet
    res = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "estimate", str(tmp_path / "c")], capture_output=True,
                         text=True, env={**os.environ, "COLUMNS": "80"}, timeout=120)
    assert res.returncode == 2 and res.stderr.startswith("error: ") and "detections.csv" in res.stderr, res.stderr
    assert "━" not in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr
