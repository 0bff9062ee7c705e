"""The forked map the estimate stage runs its methods in: the same results,
in order, as a plain map; a job's error raised in the caller; workers that end with it."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import psutil
import pytest

from pipeline.core.errors import StereotrackError
from pipeline.core.forked import can_fork, forked_map
from tests.conftest import REPO

pytestmark = pytest.mark.skipif(not can_fork(), reason="the platform does not fork (workers run in the caller)")

SEEN = {"offset": 10}  # set before the fork: the workers read it, nothing is pickled to them


def _job(i: int) -> tuple[int, int, int]:
    return i, i * i + SEEN["offset"], os.getpid()


def test_results_in_order_from_other_processes():
    got = list(forked_map(_job, list(range(7)), 2))
    assert [(i, v) for i, v, _ in got] == [(i, i * i + 10) for i in range(7)]
    pids = {p for *_, p in got}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2


def test_one_worker_runs_here():
    assert {p for *_, p in forked_map(_job, [1, 2, 3], 1)} == {os.getpid()}


def _fails(i: int) -> int:
    if i == 2:
        raise StereotrackError(f"method {i} broke", "clip/out")
    return i


def test_a_job_s_error_is_raised_in_the_caller_as_it_was():
    with pytest.raises(StereotrackError, match=r"^clip/out: method 2 broke$"):
        list(forked_map(_fails, [0, 1, 2, 3], 2))


@pytest.mark.slow
def test_workers_die_with_a_killed_caller(tmp_path):
    """SIGKILL to the process that forked them: its workers end within a second."""
    script = textwrap.dedent(f"""
        import os, sys, time
        sys.path.insert(0, {str(REPO)!r})
        from pipeline.core.forked import forked_map
        def job(i):
            open({str(tmp_path)!r} + f"/{{os.getpid()}}", "w").close()
            time.sleep(60)
        list(forked_map(job, [0, 1], 2))
    """)
    proc = subprocess.Popen([sys.executable, "-c", script])
    deadline = time.time() + 30
    while len(list(tmp_path.iterdir())) < 2 and time.time() < deadline:
        time.sleep(0.05)
    workers = [psutil.Process(int(p.name)) for p in tmp_path.iterdir()]
    assert len(workers) == 2
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    _gone, alive = psutil.wait_procs(workers, timeout=3)
    assert not [p for p in alive if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]


def test_a_signal_that_lands_while_a_worker_forks_ends_the_map_without_a_traceback():
    """The CI's `run` SIGTERM: a signal landing in fork's own handlers (logging's lock release)
    raised KeyboardInterrupt there, which Python printed as "Exception ignored" with a traceback
    and swallowed (3 of 20 signals sent at random into a loop of maps, 0 of 20 now). Here the
    signal is sent from inside those handlers, every time."""
    script = textwrap.dedent(f"""
        import os, signal, sys
        sys.path.insert(0, {str(REPO)!r})
        from pipeline.core.forked import forked_map
        from pipeline.core.interrupts import install_signal_handlers
        install_signal_handlers()
        os.register_at_fork(after_in_parent=lambda: os.kill(os.getpid(), signal.SIGTERM))
        try:
            list(forked_map(abs, [1, 2, 3], 2))
        except KeyboardInterrupt:
            sys.exit(143)
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert res.returncode == 143 and "Traceback" not in res.stderr and "Exception ignored" not in res.stderr, res.stderr


def test_the_workers_end_with_the_last_result():
    """A caller that reads every result with ``next`` (as the estimate stage does) and keeps the map
    finds no worker left once it has the last one: they are not left idle until the map is dropped."""
    me = psutil.Process()
    before = {p.pid for p in me.children()}  # what earlier tests left (a viewer), not the map's
    runs = forked_map(_job, [1, 2, 3], 2)
    got = [next(runs) for _ in range(3)]
    assert [v for _, v, _ in got] == [11, 14, 19]
    assert {p for *_, p in got} - before  # the workers were children of this process
    assert not [p for p in me.children() if p.pid not in before and p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
