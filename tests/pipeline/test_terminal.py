"""What the terminal's progress lines say (pipeline.app.cli_common)."""

from __future__ import annotations

import time

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
