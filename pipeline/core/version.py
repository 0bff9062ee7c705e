"""The installed stereotrack version, recorded in every metrics.json and manifest."""

from __future__ import annotations


def stereotrack_version() -> str:
    """The installed stereotrack version (``0+unknown`` when run from a bare checkout)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("stereotrack")
    except PackageNotFoundError:
        return "0+unknown"
