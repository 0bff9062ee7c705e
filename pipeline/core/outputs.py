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


#: hidden files stereotrack leaves in a folder given with ``-o`` (outputs) and in every export folder:
#: what marks them as its own (names a user does not write by accident, as ``metrics.json`` could be)
OUTPUT_MARK = ".stereotrack-output"
EXPORT_MARK = ".stereotrack-export"
#: one of these in a folder given with ``-o`` (or nothing at all there) makes it one stereotrack may
#: write into; any other folder is refused, untouched
OURS = (DETECT_INFO, OUTPUT_MARK, EXPORT_MARK)

#: a batch's attempt at one clip's outputs, renamed to the final folder when the clip is complete
PARTIAL = ".{name}.partial-{attempt}"


def partial_folder(final: Path, attempt: str) -> Path:
    """The hidden folder beside ``final`` that one attempt at it writes into."""
    return final.parent / PARTIAL.format(name=final.name, attempt=attempt)


def final_folder(folder: Path) -> Path:
    """The folder an attempt's outputs will be in once complete: ``OUT/<clip>`` for a batch's
    ``OUT/.<clip>.partial-<id>``, else ``folder`` itself (what a report's replay command names)."""
    import re

    m = re.fullmatch(r"\.(.+)\.partial-[0-9a-f]+", folder.name)
    return folder.parent / m.group(1) if m else folder


class _File:
    """A file of the output folder, by name: ``Outputs(folder).metrics`` is ``folder/metrics.json``;
    ``what`` says what it holds (the docs' list of outputs is generated from it)."""

    def __init__(self, name: str, what: str) -> None:
        self.name, self.what = name, what

    def __get__(self, outputs: Outputs | None, owner: type | None = None):
        return self if outputs is None else outputs.folder / self.name


@dataclass(frozen=True)
class Outputs:
    """Paths of one output folder's files (nothing is read or made here)."""

    folder: Path

    detections = _File(DETECTIONS, "every detection, undistorted pixels (`detect`)")
    detect_info = _File(DETECT_INFO, "frames, frame size, the marker colour ranges used and their display colours, "
                        "and the detect stage's checks")
    estimates_dir = _File(ESTIMATES, "one table per method, `<method>.csv` (`estimate`)")
    metrics = _File(METRICS, "per method: errors against the truth, reprojection, NIS/NEES summaries, gating and "
                    "restart counts, speed; the run's checks")
    report_md = _File(REPORT_MD, "the report in Markdown, its figures in `figures/`")
    report_html = _File(REPORT_HTML, "the report, self-contained (figures embedded, nothing fetched)")
    figures_dir = _File(FIGURES, "the Markdown report's SVG figures")
    recording = _File(RECORDING, "the rerun recording (`rerun run.rrd`)")
    manifest = _File(MANIFEST, "the settings and checksums of a batch's clip folder: what makes it complete")
    export_dir = _File(EXPORT, "`<method>.trc`, `.c3d` or `.csv` after `stereotrack export`")

    @classmethod
    def files(cls) -> list[_File]:
        """Every file and folder an output folder can hold, in the order the stages write them."""
        return [v for v in vars(cls).values() if isinstance(v, _File)]

    @classmethod
    def of(cls, clip_folder: str | Path, out_dir: str | Path | None = None) -> Outputs:
        """``out_dir`` when given, else the clip folder's ``out/``."""
        return cls(Path(out_dir) if out_dir else Path(clip_folder) / OUT)

    def estimates(self, method: str) -> Path:
        """One method's estimates table."""
        return self.folder / ESTIMATES / f"{method}.csv"

    def figure(self, name: str) -> Path:
        """A report figure (SVG)."""
        return self.folder / FIGURES / f"{name}.svg"
