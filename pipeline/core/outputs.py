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


@dataclass(frozen=True)
class Outputs:
    """Paths of one output folder's files (nothing is read or made here)."""

    folder: Path

    @classmethod
    def of(cls, clip_folder: str | Path, out_dir: str | Path | None = None) -> Outputs:
        """``out_dir`` when given, else the clip folder's ``out/``."""
        return cls(Path(out_dir) if out_dir else Path(clip_folder) / OUT)

    @property
    def detections(self) -> Path:
        return self.folder / DETECTIONS

    @property
    def detect_info(self) -> Path:
        return self.folder / DETECT_INFO

    @property
    def estimates_dir(self) -> Path:
        return self.folder / ESTIMATES

    def estimates(self, method: str) -> Path:
        """One method's estimates table."""
        return self.folder / ESTIMATES / f"{method}.csv"

    @property
    def metrics(self) -> Path:
        return self.folder / METRICS

    @property
    def report_md(self) -> Path:
        return self.folder / REPORT_MD

    @property
    def report_html(self) -> Path:
        return self.folder / REPORT_HTML

    def figure(self, name: str) -> Path:
        """A report figure (PNG)."""
        return self.folder / FIGURES / f"{name}.png"

    @property
    def recording(self) -> Path:
        return self.folder / RECORDING

    @property
    def manifest(self) -> Path:
        return self.folder / MANIFEST

    @property
    def export_dir(self) -> Path:
        return self.folder / EXPORT
