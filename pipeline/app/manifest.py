"""A clip's output manifest: the record, written last, that its outputs are complete and of which inputs.

``manifest.json`` lists every output file with its size and SHA-256, every input file the run read
(videos or frame files, calibration, ``markers.yaml``, ``clip.json``, timestamps, truth) with its
size and SHA-256, the stereotrack version and the resolved settings that produced them (as Kubric
writes its flags beside a scene). A batch counts a clip as done only when its manifest is
stereotrack's, every output matches it, every input is unchanged and the settings are the ones asked
for now; anything else is redone, and :func:`verify_manifest` says why.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from pipeline.core.io import write_json
from pipeline.core.outputs import MANIFEST, METRICS
from pipeline.core.version import stereotrack_version

#: The output every complete clip has: a manifest that does not list it is not a complete record.
REQUIRED_OUTPUT = METRICS


def sha256(path: Path) -> str:
    """SHA-256 of a file, read in 1 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _outputs(folder: Path) -> list[Path]:
    return sorted(p for p in folder.rglob("*") if p.is_file() and p.name != MANIFEST and not p.name.startswith("."))


def file_record(path: Path) -> dict[str, Any]:
    """What a manifest keeps of one file: size and SHA-256."""
    return {"size": path.stat().st_size, "sha256": sha256(path)}


def write_manifest(folder: str | Path, settings: dict[str, Any], inputs: dict[str, Path] | None = None) -> Path:
    """Write ``manifest.json`` for every file now in ``folder`` (call it after the last output),
    with the ``inputs`` (name → path) the outputs were made from."""
    folder = Path(folder)
    files = {str(p.relative_to(folder)): file_record(p) for p in _outputs(folder)}
    ins = {name: file_record(p) for name, p in sorted((inputs or {}).items())}
    path = folder / MANIFEST
    write_json(path, {"stereotrack": stereotrack_version(), "settings": settings, "inputs": ins, "files": files})
    return path


def read_manifest(folder: str | Path) -> tuple[dict | None, str | None]:
    """(manifest, None), or (None, why it is not a usable stereotrack manifest)."""
    path = Path(folder) / MANIFEST
    if not path.is_file():
        return None, "no manifest"
    try:
        man = json.loads(path.read_bytes())
    except (OSError, ValueError) as exc:
        return None, f"malformed manifest ({type(exc).__name__})"
    if not isinstance(man, dict) or "stereotrack" not in man:
        return None, "not a stereotrack manifest"
    files, inputs = man.get("files"), man.get("inputs", {})
    if not isinstance(files, dict) or not isinstance(inputs, dict) or not all(
            isinstance(m, dict) for m in (*files.values(), *inputs.values())):
        return None, "malformed manifest (files/inputs are not mappings)"
    if REQUIRED_OUTPUT not in files:
        return None, f"manifest does not list {REQUIRED_OUTPUT} (emptied or incomplete)"
    return man, None


def _changed(path: Path, meta: dict) -> bool:
    return not path.is_file() or path.stat().st_size != meta.get("size") or sha256(path) != meta.get("sha256")


def _settings_diff(asked: dict[str, Any], made: Any) -> str:
    if not isinstance(made, dict):
        return "made with other settings"
    keys = sorted(k for k in set(asked) | set(made) if asked.get(k) != made.get(k))
    return f"made with other settings ({', '.join(keys)})"


def verify_manifest(folder: str | Path, settings: dict[str, Any] | None = None,
                    inputs: dict[str, Path] | None = None) -> str | None:
    """None when ``folder`` is complete per its manifest (made with ``settings`` from ``inputs``,
    where given); otherwise the reason it is not, naming the setting, input or output."""
    folder = Path(folder)
    man, why = read_manifest(folder)
    if man is None:
        return why
    if settings is not None:
        asked = json.loads(json.dumps(settings))
        if asked != man.get("settings"):
            return _settings_diff(asked, man.get("settings"))
    if inputs is not None:
        recorded = man.get("inputs", {})
        for name in sorted(set(recorded) - set(inputs)):
            return f"input {name} was removed"
        for name in sorted(set(inputs) - set(recorded)):
            return f"input {name} is new"
        for name, p in sorted(inputs.items()):
            if _changed(p, recorded[name]):
                return f"input {name} changed"
    for rel, meta in man["files"].items():
        p = folder / rel
        if not p.is_file():
            return f"{rel} missing"
        if _changed(p, meta):
            return f"{rel} does not match its checksum"
    return None
