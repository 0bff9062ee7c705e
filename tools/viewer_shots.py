"""Screenshots of recordings in rerun's own viewer, run headless (no browser, no display), and the
docs' set of them.

    python tools/viewer_shots.py RUN.rrd [MORE.rrd ...] [--frame N] [-o OUT.png]
    python tools/viewer_shots.py --docs [--realdata ../shared/realdata]

The viewer that the pinned rerun-sdk installs is started with ``--headless`` and driven through
``rerun.experimental.ViewerClient`` (open, set the time cursor, screenshot); it needs a Vulkan
driver, which a machine without a GPU has in Mesa's lavapipe (Debian: ``apt install
mesa-vulkan-drivers``). A screenshot is taken once two in a row are the same (the panes have
filled). For each, the share of the 3-D pane's width and height that the tracks span is measured
on a screenshot of that pane alone (pixels brighter than the background and grid).

``--docs`` runs the six cases of the docs (the default scenario at first open and at frame 75,
``realistic``, ``four_point``, the sample clip as a real rig ships it — videos and calib.yaml, no
truth — and a batch of the sample clips) into a temporary folder, writes
``docs/figures/viewer_*.png`` and ``docs/viewer.md`` with the measured figures. Not run in CI.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

REPO = Path(__file__).resolve().parents[1]
FIGURES = REPO / "docs" / "figures"
#: the title bar of a view's screenshot, left out of the track measurement
TITLE_PX = 28


@dataclass
class Shot:
    name: str
    caption: str
    recordings: list[Path]
    frame: int | None  # None: as the viewer opens it
    width: float = 0.0  # share of the 3-D pane the tracks span
    height: float = 0.0
    settled_s: float = 0.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def track_span(png: bytes) -> tuple[float, float]:
    """The share of a 3-D view's width and height (title bar aside) spanned by its tracks, labels
    and points: the 0.5–99.5 % range of pixels brighter than the dark background and grid."""
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    bright = cv2.cvtColor(img, cv2.COLOR_BGR2HSV)[TITLE_PX:, :, 2] > 90
    ys, xs = np.nonzero(bright)
    if len(xs) < 20:
        return 0.0, 0.0
    h, w = bright.shape
    return float(np.ptp(np.percentile(xs, [0.5, 99.5])) / w), float(np.ptp(np.percentile(ys, [0.5, 99.5])) / h)


def settled(client, view_id=None, limit: float = 60.0) -> tuple[bytes, float]:
    """A screenshot once two taken a second apart are identical (or at ``limit`` seconds)."""
    t0, prev = time.perf_counter(), b""
    while True:
        png = client.take_screenshot(view_id)
        if png == prev or time.perf_counter() - t0 > limit:
            return png, time.perf_counter() - t0
        prev = png
        time.sleep(1.0)


def shoot(shots: list[Shot], out_dir: Path) -> None:
    """Each shot's recordings opened in a fresh headless viewer, the cursor set, the whole viewer
    and its 3-D view captured (``out_dir/<name>.png``) and the tracks' span measured."""
    from rerun.experimental import ViewerClient

    os.environ.setdefault("XDG_RUNTIME_DIR", tempfile.mkdtemp(prefix="xdg"))
    for shot in shots:
        client = ViewerClient.spawn(headless=True, port=_free_port(), hide_welcome_screen=True)
        try:
            client.open([str(r) for r in shot.recordings])
            while client.get_state().loading:
                time.sleep(0.5)
            if shot.frame is not None:
                client.set_time("frame", sequence=shot.frame, play_state="paused")
            png, shot.settled_s = settled(client)
            (out_dir / f"{shot.name}.png").write_bytes(png)
            view3d = next(v for v in client.get_state().views if v.view_class == "3D")
            shot.width, shot.height = track_span(settled(client, view3d.view_id)[0])
        finally:
            client.quit()
        print(f"{shot.name}: tracks span {shot.width:.0%} × {shot.height:.0%} of the 3-D pane "
              f"(settled in {shot.settled_s:.0f} s)", flush=True)


def _st(*args: str) -> None:
    from functools import partial

    from pipeline.core.lifeline import terminate_with_parent

    subprocess.run([str(Path(sys.executable).with_name("stereotrack")), *args], check=True, cwd=REPO,  # ends with this
                   stdout=subprocess.DEVNULL, preexec_fn=partial(terminate_with_parent, os.getpid()))  # script, SIGKILL too


def docs_cases(work: Path) -> list[Shot]:
    """Run the six cases into ``work`` (the sample clips from data/clips) and describe their shots."""
    _st("run", "default", "-o", str(work / "default"))
    _st("run", "realistic", "-o", str(work / "realistic"))
    _st("run", "four_point", "-o", str(work / "four_point"))
    real = work / "own_rig"
    real.mkdir()
    sample = REPO / "data" / "clips" / "sample_small"
    for f in ("left.mp4", "right.mp4", "calib.yaml"):
        shutil.copy(sample / f, real / f)
    colours = json.loads((sample / "clip.json").read_text())["markers"]
    markers = ",".join(f"{m['name']}=#{''.join(f'{c:02x}' for c in m['rgb'])}" for m in colours)
    _st("run", str(real), "--markers", markers)
    _st("batch", str(REPO / "data" / "clips"), "-o", str(work / "batch"))
    rrd = "out/run.rrd"
    return [
        Shot("viewer_default", "`stereotrack run default` as the viewer opens it (frame 0)", [work / "default" / rrd], None),
        Shot("viewer_default_75", "the same recording at frame 75", [work / "default" / rrd], 75),
        Shot("viewer_realistic", "`stereotrack run realistic` (distortion, a late camera, rolling shutters, a "
             "look-alike), frame 75", [work / "realistic" / rrd], 75),
        Shot("viewer_four_point", "`stereotrack run four_point`, frame 50", [work / "four_point" / rrd], 50),
        Shot("viewer_own_rig", "the sample clip as a real rig ships it (two videos and calib.yaml: no truth, "
             "no clip.json), `stereotrack run CLIP --markers ...`, frame 12", [real / rrd], 12),
        Shot("viewer_batch", "`stereotrack batch data/clips` opened as `stereotrack view OUT` opens it "
             "(both clips' recordings; the last opened shown), frame 12",
             sorted((work / "batch").glob("*/run.rrd")), 12),
    ]


def write_page(shots: list[Shot]) -> None:
    """docs/viewer.md: the screenshots and the measured spans."""
    rows = "\n".join(f"| {s.name} | {s.width:.0%} | {s.height:.0%} |" for s in shots)
    figures = "\n\n".join(f"![{s.caption}](figures/{s.name}.png)\n\n*{s.caption[0].upper() + s.caption[1:]}.*"
                          for s in shots)
    (REPO / "docs" / "viewer.md").write_text(f"""# What the recording looks like

Each run's `run.rrd` opens in rerun's viewer (`stereotrack view CLIP`) with the layout built in code
(`pipeline/present/layout.py`):

- the 3-D view framed on the paths (the truth's, else the best method's): of the directions from
  the cameras' side and above, the one whose image of the paths, centred, fills most of the pane
  with no two markers' labels overlapping at the first, middle and last frames
  (`tests/pipeline/test_layout.py`);
- a pane per camera: the detections ringed in their markers' colours, the best method's
  reprojections as crosses, the truth as small grey rings;
- a text panel about the run, and tabs of plots per marker (3-D error, reprojection error, depth
  error with ±σ, track states) showing the run's three best methods, drawn widest first so that a
  method whose series lies on another's shows as a thin line inside it.

The screenshots are rerun's own viewer run headless (software rendering: the "Software rasterizer"
badge), each taken once two screenshots in a row agree. The tracks' span is measured on a
screenshot of the 3-D pane alone: the range of the pixels brighter than its background and grid,
as a share of the pane's width and height.

| screenshot | tracks span: width | height |
|---|---:|---:|
{rows}

{figures}

Generated by `python tools/viewer_shots.py --docs`.
""")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recordings", type=Path, nargs="*")
    ap.add_argument("--frame", type=int, help="the time cursor's frame (default: as the viewer opens it)")
    ap.add_argument("-o", "--out", type=Path, default=Path("screenshot.png"))
    ap.add_argument("--docs", action="store_true", help="run the docs' six cases and rewrite docs/viewer.md")
    args = ap.parse_args()
    if args.docs:
        with tempfile.TemporaryDirectory(prefix="viewer_shots") as work:
            shots = docs_cases(Path(work))
            shoot(shots, FIGURES)
        write_page(shots)
        return
    if not args.recordings:
        ap.error("give recordings, or --docs")
    shot = Shot(args.out.stem, "", args.recordings, args.frame)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    shoot([shot], args.out.parent)


if __name__ == "__main__":
    main()
