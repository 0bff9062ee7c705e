"""A clip's output folder (``CLIP/out``, or a batch's ``OUT/<clip>``): the output twin of
:class:`~pipeline.core.clip.Clip`, and the one place that names every file stereotrack writes
there, so no stage spells an ``out/`` path."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

#: the folder inside a clip folder that its outputs go to by default
OUT = "out"
DETECTIONS = "detections.csv"
DETECT_INFO = "detect.json"
ESTIMATES = "estimates"
METRICS = "metrics.json"
REPORT_MD = "report.md"
REPORT_HTML = "report.html"
FIGURES = "figures"
RECORDING = "run.rrd"
MANIFEST = "manifest.json"
EXPORT = "export"


class _File:
    """A file of the output folder, by name: ``Outputs(folder).metrics`` is ``folder/metrics.json``."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __get__(self, outputs: Outputs | None, owner: type | None = None):
        return self if outputs is None else outputs.folder / self.name


@dataclass(frozen=True)
class Outputs:
    """Paths of one output folder's files (nothing is read or made here)."""

    folder: Path

    detections = _File(DETECTIONS)
    detect_info = _File(DETECT_INFO)
    estimates_dir = _File(ESTIMATES)
    metrics = _File(METRICS)
    report_md = _File(REPORT_MD)
    report_html = _File(REPORT_HTML)
    recording = _File(RECORDING)
    manifest = _File(MANIFEST)
    export_dir = _File(EXPORT)

    @classmethod
    def of(cls, clip_folder: str | Path, out_dir: str | Path | None = None) -> Outputs:
        """``out_dir`` when given, else the clip folder's ``out/``."""
        return cls(Path(out_dir) if out_dir else Path(clip_folder) / OUT)

    def estimates(self, method: str) -> Path:
        """One method's estimates table."""
        return self.folder / ESTIMATES / f"{method}.csv"

    def figure(self, name: str) -> Path:
        """A report figure (PNG)."""
        return self.folder / FIGURES / f"{name}.png"
