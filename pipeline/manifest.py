"""A clip's output manifest: the record, written last, that its outputs are complete.

``manifest.json`` lists every output file with its size and SHA-256, the stereotrack version and
the resolved settings that produced them (as Kubric writes its flags beside a scene). A batch counts
a clip as done only when its manifest exists, every file matches it, and the settings are the ones
asked for now; anything else is redone.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from pipeline.io import write_json

MANIFEST = "manifest.json"


def stereotrack_version() -> str:
    """The installed stereotrack version (``0+unknown`` when run from a bare checkout)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("stereotrack")
    except PackageNotFoundError:
        return "0+unknown"


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _outputs(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file() and p.name != MANIFEST and not p.name.startswith("."))


def write_manifest(folder: str | Path, settings: dict[str, Any]) -> Path:
    """Write ``manifest.json`` for every file now in ``folder`` (call it after the last output)."""
    folder = Path(folder)
    files = {str(p.relative_to(folder)): {"size": p.stat().st_size, "sha256": _sha256(p)} for p in _outputs(folder)}
    path = folder / MANIFEST
    write_json(path, {"stereotrack": stereotrack_version(), "settings": settings, "files": files})
    return path


def verify_manifest(folder: str | Path, settings: dict[str, Any] | None = None) -> str | None:
    """None when ``folder`` is complete per its manifest (and made with ``settings``, if given);
    otherwise the reason it is not."""
    folder = Path(folder)
    path = folder / MANIFEST
    if not path.is_file():
        return "no manifest"
    try:
        man = json.loads(path.read_text())
        files = man["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return "unreadable manifest"
    if settings is not None and json.loads(json.dumps(settings)) != man.get("settings"):
        return "made with other settings"
    for rel, meta in files.items():
        p = folder / rel
        if not p.is_file():
            return f"{rel} missing"
        if p.stat().st_size != meta.get("size") or _sha256(p) != meta.get("sha256"):
            return f"{rel} does not match its checksum"
    return None
