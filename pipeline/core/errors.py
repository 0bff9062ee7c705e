"""User-facing errors: one line naming the file and the problem, never a numpy traceback."""

from __future__ import annotations

from pathlib import Path


def first_line(exc: BaseException | str) -> str:
    """The first non-empty line of an exception's message (its type's name when it has none), for
    one-line errors built around what a library said."""
    lines = str(exc).strip().splitlines()
    return lines[0].strip() if lines else (type(exc).__name__ if isinstance(exc, BaseException) else "")


class StereotrackError(Exception):
    """An error the command line prints as one line (no traceback) and exits non-zero with."""

    def __init__(self, message: str, path: str | Path | None = None) -> None:
        self.path = Path(path) if path is not None else None
        message = " ".join(line.strip() for line in str(message).splitlines() if line.strip())  # always one line
        super().__init__(f"{path}: {message}" if path is not None else message)


class CalibrationError(StereotrackError):
    """A calibration file is missing, unreadable or inconsistent."""


class ScenarioError(StereotrackError):
    """A scenario file is missing or has an invalid value."""


class ClipError(StereotrackError):
    """A clip folder or its videos/frames are missing, unreadable or inconsistent."""


class RenderBackendError(StereotrackError):
    """No OpenGL backend (EGL or OSMesa) could be created for off-screen rendering."""
