"""A function mapped over items in processes forked from this one, results in the items' order.

The estimate stage's methods are independent of each other and each runs in plain Python and
numpy (the GIL holds threads to one core); forked workers inherit the clip's observations, the
registered methods and the function itself instead of having them pickled, and start in
milliseconds where a spawned interpreter re-imports the pipeline (about half a second). Workers
die with this process, SIGKILL included (:func:`~pipeline.core.lifeline.die_with_parent`), leave
Ctrl-C to it, and are killed at once when it is interrupted or a job raises."""

from __future__ import annotations

import multiprocessing
import os
import sys
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from typing import Any, TypeVar

from pipeline.core.allocator import trim
from pipeline.core.interrupts import signals_deferred
from pipeline.core.lifeline import die_with_parent, end_pool, ignore_sigint, one_blas_thread

T = TypeVar("T")
R = TypeVar("R")

#: jobs per worker submitted ahead of the result the caller is reading
AHEAD = 2

#: the function and items of the map in progress, read by the forked workers (set before they fork)
_JOB: tuple[Callable[[Any], Any], Sequence[Any]] | None = None


def can_fork() -> bool:
    """Whether workers are forked here: on Linux (macOS can fork, but its system libraries are not
    safe to use in a forked child, and Python spawns there by default; Windows cannot)."""
    return sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()


def forked_map(fn: Callable[[T], R], items: Sequence[T], workers: int) -> Iterator[R]:
    """``fn(item)`` for each item, yielded in the items' order as each is ready: in up to ``workers``
    forked processes, or in this one when ``workers`` ≤ 1, there is one item, or the platform
    cannot fork. ``fn`` returns what pickles; an exception it raises is raised here."""
    workers = min(workers, len(items))
    if workers <= 1 or not can_fork():
        yield from map(fn, items)
        return
    import concurrent.futures as cf

    global _JOB
    _JOB = (fn, items)
    pool = cf.ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("fork"),
                                  initializer=_init, initargs=(os.getpid(),))
    try:
        # the workers fork at the first submit; at most AHEAD jobs per worker are queued or done and
        # unread, so that a caller that streams the results (a long clip's tracks) holds few at a time
        queued = deque(_submit(pool, i) for i in range(min(len(items), AHEAD * workers)))
        for i in range(len(items)):
            result = queued.popleft().result()
            trim()  # what the pool's reader thread unpickled and the caller has dropped (see trim)
            if i + len(queued) + 1 < len(items):
                queued.append(_submit(pool, i + len(queued) + 1))
            if i == len(items) - 1:  # the workers end with the last result, not when the caller drops the map
                pool.shutdown(wait=True)
            yield result
    except BaseException:
        end_pool(pool)
        raise
    finally:
        _JOB = None
        pool.shutdown(wait=True, cancel_futures=True)


def _submit(pool, i: int):
    """``pool.submit(_call, i)`` with signals held: a submit may fork a worker, and a signal that
    lands in fork's handlers is printed with a traceback and swallowed there."""
    with signals_deferred():
        return pool.submit(_call, i)


def _init(parent_pid: int) -> None:
    die_with_parent(parent_pid)
    ignore_sigint()
    one_blas_thread()  # for the BLAS a job loads (scipy's); the one loaded already is the parent's


def _call(i: int) -> Any:
    assert _JOB is not None  # inherited from the parent at fork
    fn, items = _JOB
    return fn(items[i])
