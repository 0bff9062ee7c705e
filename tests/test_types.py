"""The library type-checks: mypy with pydantic's plugin (settings in pyproject.toml) finds nothing
in ``pipeline``, ``detectors`` and ``renderers``, so the suite (the README's test command) runs it."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import REPO


@pytest.mark.slow
def test_mypy_is_clean():
    pytest.importorskip("mypy", reason="mypy comes with the test extra (pip install -e '.[test]')")
    res = subprocess.run([sys.executable, "-m", "mypy", "--no-error-summary"], cwd=REPO, capture_output=True, text=True,
                         check=False)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
