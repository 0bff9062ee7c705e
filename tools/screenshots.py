"""Screenshots of what a person sees: a recording in rerun's web viewer, or an HTML report
(report.html, summary.html), in headless Chromium.

    python tools/screenshots.py RUN.rrd [-o DIR] [--wait 120] [--settle 5] [--chromium /usr/bin/chromium]
    python tools/screenshots.py out/report.html [-o DIR] [--full-page]

Starts the rerun viewer that the pinned rerun-sdk ships (``rerun --serve-web``) on local ports, opens it
with Playwright driving Debian's ``chromium`` (``pip install playwright``; not a project dependency),
waits until the first camera pane shows an image (polled, not a fixed sleep: the time is printed),
lets the other panes fill for ``--settle`` seconds and saves ``DIR/<name>.png``. Not run in CI.
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("recording", type=Path)
    ap.add_argument("-o", "--out", type=Path, default=Path("screenshots"))
    ap.add_argument("--wait", type=float, default=120.0,
                    help="the most seconds to wait for the first camera image (the screenshot is taken once it shows)")
    ap.add_argument("--settle", type=float, default=5.0, help="seconds after the first image before the screenshot")
    ap.add_argument("--chromium", default=shutil.which("chromium") or "/usr/bin/chromium")
    ap.add_argument("--size", default="1600x1000")
    ap.add_argument("--rerun", default=shutil.which("rerun") or str(Path(sys.executable).with_name("rerun")),
                    help="the rerun viewer executable (the one the project's rerun-sdk installs)")
    ap.add_argument("--full-page", action="store_true", help="HTML: the whole page, not the first screen")
    args = ap.parse_args()
    if args.recording.suffix == ".html":
        return shoot_html(args)
    from playwright.sync_api import sync_playwright

    rerun = args.rerun
    web, grpc = 19090, 19876
    server = subprocess.Popen([str(rerun), "--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", str(web),
                               "--port", str(grpc), str(args.recording)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        time.sleep(3)
        w, h = (int(v) for v in args.size.split("x"))
        args.out.mkdir(parents=True, exist_ok=True)
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=args.chromium, args=["--use-gl=swiftshader", "--no-sandbox"])
            page = browser.new_page(viewport={"width": w, "height": h})
            t0 = time.perf_counter()
            page.goto(f"http://127.0.0.1:{web}/?url=rerun%2Bhttp://127.0.0.1:{grpc}/proxy")
            first = wait_for_image(page, t0, args.wait)
            time.sleep(args.settle)  # the other panes fill from the same stream
            path = args.out / f"{args.recording.parent.parent.name or args.recording.stem}.png"
            page.screenshot(path=str(path))
            browser.close()
        said = f"{first:.1f} s" if first is not None else f"not within {args.wait:g} s"
        print(f"first camera image on screen after {said} (from opening the page); wrote {path}")
    finally:  # the rerun entry point runs the viewer binary as a child: end the whole group
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=10)


def wait_for_image(page, t0: float, limit: float) -> float | None:
    """Seconds from ``t0`` until the first camera pane (the top of the right column, where the
    blueprint puts it) shows an image rather than the viewer's flat background: polled by
    screenshot every half second, up to ``limit`` seconds; None if it never does."""
    import cv2
    import numpy as np

    while time.perf_counter() - t0 < limit:
        shot = cv2.imdecode(np.frombuffer(page.screenshot(), np.uint8), cv2.IMREAD_GRAYSCALE)
        h, w = shot.shape
        pane = shot[int(0.07 * h): int(0.19 * h), int(0.66 * w): int(0.94 * w)]
        if pane.std() > 12.0:  # an image's texture; the empty pane and its text are nearly flat
            return time.perf_counter() - t0
        time.sleep(0.5)
    return None


def shoot_html(args) -> None:
    """A screenshot of a local HTML page (its figures are embedded, so nothing else is served)."""
    from playwright.sync_api import sync_playwright

    w, h = (int(v) for v in args.size.split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / f"{args.recording.parent.name}_{args.recording.stem}.png"
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=args.chromium, args=["--no-sandbox"])
        page = browser.new_page(viewport={"width": w, "height": h})
        page.goto(args.recording.resolve().as_uri())
        page.wait_for_load_state("load")
        page.screenshot(path=str(path), full_page=args.full_page)
        browser.close()
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
