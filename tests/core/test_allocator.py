"""The allocator settings for streams of frames: they act (no page faults for frames freed and
allocated again), they reach child processes, and a value the user set wins."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from pipeline.core import allocator

#: frames of 1280×720 allocated and freed (the decode threads' pattern): page faults in the last half
CHURN = """import resource, sys
import numpy as np
from pipeline.core import allocator
tuned = allocator.tune() if sys.argv[1] == 'tune' else False
def churn():
    for _ in range(50):
        frames = [np.ones(1280 * 720 * 3, np.uint8) for _ in range(4)]
        del frames
churn()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
churn()
print(tuned, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""

def _glibc() -> bool:
    try:
        return "glibc" in (os.confstr("CS_GNU_LIBC_VERSION") or "")
    except (AttributeError, ValueError, OSError):  # no confstr (Windows), or not this name (macOS)
        return False


needs_glibc = pytest.mark.skipif(not _glibc(), reason="the allocator settings are glibc's")


def _churn(how: str, env: dict[str, str] | None = None) -> tuple[str, int]:
    """(whether ``tune`` set the thresholds, page faults) of the churn in a child whose
    environment is ``env`` (default: this process's, without allocator settings)."""
    if env is None:
        env = {k: v for k, v in os.environ.items() if k not in allocator.ENV}
    out = subprocess.run([sys.executable, "-c", CHURN, how], capture_output=True, text=True, check=True,
                         env=env).stdout.split()
    return out[0], int(out[1])


@needs_glibc
def test_tuned_allocator_keeps_frame_pages():
    """Untuned, glibc hands each freed frame back to the kernel and faults it in again; tuned, the
    pages stay (a thousandth of the faults)."""
    (plain_set, plain), (tuned_set, tuned) = _churn("plain"), _churn("tune")
    assert plain_set == "False" and tuned_set == "True"
    assert plain > 100 * 675 and tuned < plain / 1000  # 675 pages per frame


@needs_glibc
def test_allocator_reaches_children_and_the_user_wins(monkeypatch):
    """Children started within ``child_environment`` get the settings through the environment (the
    same effect as :func:`allocator.tune`); a user's own value is left, and ``tune`` then does
    nothing."""
    from pipeline.core.lifeline import child_environment

    for k in allocator.ENV:
        monkeypatch.delenv(k, raising=False)
    with child_environment():
        assert {k: os.environ[k] for k in allocator.ENV} == allocator.ENV
        _, faults = _churn("plain", dict(os.environ))  # inherited, not set by the child
    assert faults < 100 and not any(k in os.environ for k in allocator.ENV)
    monkeypatch.setenv("MALLOC_TRIM_THRESHOLD_", "1000000")
    with child_environment():
        assert os.environ["MALLOC_TRIM_THRESHOLD_"] == "1000000"
        assert _churn("tune", dict(os.environ))[0] == "False"
