"""Modules imported on first use, so that commands that never call them (``--help``, ``methods``,
``scenarios``) do not pay for them: ``cv2 = lazy_module("cv2")`` at the top of a module, with the
real ``import cv2`` under ``TYPE_CHECKING`` for the type checker.

Unlike :class:`importlib.util.LazyLoader`, nothing is put into ``sys.modules`` before it is
loaded, and two threads touching it first at once both get the real module (the import lock
serialises the load; Python 3.11's ``LazyLoader`` can hand the second a half-made module)."""

from __future__ import annotations

import importlib
from typing import Any


class LazyModule:
    """Stands for the module ``name``; the first attribute read imports it, and each attribute
    read is then cached on this object, so later reads cost a plain attribute lookup."""

    def __init__(self, name: str) -> None:
        self._name = name

    def __getattr__(self, attr: str) -> Any:
        value = getattr(importlib.import_module(self._name), attr)
        setattr(self, attr, value)
        return value

    def __repr__(self) -> str:
        return f"<lazy module {self._name!r}>"


def lazy_module(name: str) -> Any:
    """A :class:`LazyModule` for ``name`` (typed ``Any``: declare the real import for the checker)."""
    return LazyModule(name)
