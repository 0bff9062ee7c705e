"""A digest of what a run computed, to show that a change of structure changed no result.

    python tools/digest.py OUT [OUT ...]

For each output folder (a run's ``CLIP/out`` or a batch's output folder, searched for every
``detections.csv``): SHA-256 of ``detections.csv``, each ``estimates/*.csv`` and ``metrics.json`` with
the wall-clock fields (steps per second, seconds per step), the version and paths removed. Prints one
line per file; two trees with the same lines computed the same numbers.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

#: metrics.json keys that change from run to run without any change of result
VOLATILE = {"seconds_per_step", "steps_per_second", "median_steps_per_second", "stereotrack_version", "clip", "path"}


def _stable(value: object) -> object:
    if isinstance(value, dict):
        return {k: _stable(v) for k, v in value.items() if k not in VOLATILE}
    if isinstance(value, list):
        return [_stable(v) for v in value]
    return value


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()[:16]


def digest(out: Path) -> list[str]:
    """``relative path  sha`` for every result file under ``out``."""
    lines = []
    for det in sorted(out.rglob("detections.csv")):
        folder = det.parent
        files = [det, *sorted((folder / "estimates").glob("*.csv"))]
        lines += [f"{f.relative_to(out)}  {_sha(f.read_bytes())}" for f in files]
        metrics = folder / "metrics.json"
        if metrics.is_file():
            text = json.dumps(_stable(json.loads(metrics.read_text())), sort_keys=True).encode()
            lines.append(f"{metrics.relative_to(out)}  {_sha(text)}")
    return lines


if __name__ == "__main__":
    for arg in sys.argv[1:]:
        print("\n".join(digest(Path(arg))))
