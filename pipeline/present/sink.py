"""The recording's file sink, made safe for a full disk: rerun's own flush, its disconnect and its
exit-time hooks wait for ever on a sink that stopped writing, and a sink that dropped data leaves a
file its reader does not open. Neither is ever left as an output."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from pipeline.core.errors import StereotrackError


def _ignore(*_args, **_kwargs) -> None:
    """Stands in for what a stalled sink would wait on for ever."""


def flushed(rec: Any, tmp: Path, stalled_s: float = 15.0) -> bool:
    """Wait for ``rec``'s file sink to write everything to ``tmp``; False when it stopped writing
    (``stalled_s`` seconds without the file growing). A stalled stream is then defused: rerun's exit
    hook and the stream's finaliser, which would wait on it for ever, do nothing; do not disconnect it."""
    import time

    size, since = -1, time.monotonic()
    while True:
        began = time.monotonic()
        try:
            rec.flush(timeout_sec=1.0)
            return True
        except Exception:  # the flush timed out (or failed at once): is the file still growing?
            now = tmp.stat().st_size if tmp.exists() else 0
            if now != size:
                size, since = now, time.monotonic()
            elif time.monotonic() - since >= stalled_s:
                import rerun as rr

                rr.unregister_shutdown()
                rec._flush = rec._disconnect_orphaned_recordings = _ignore
                return False
            time.sleep(max(0.0, 0.5 - (time.monotonic() - began)))  # a flush that failed at once does not spin


def check_reads_back(tmp: Path, path: Path) -> None:
    """The recording written to ``tmp`` opens with rerun's own reader (it ends in its footer); a
    file the sink could not finish (a full disk) is an error naming ``path``, never an output."""
    import warnings

    from rerun.chunk import RrdReader

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            ok = bool(RrdReader(tmp).recordings())
        except (RuntimeError, OSError, ValueError):
            ok = False
    if not ok or any("no footer" in str(w.message) for w in caught):
        tmp.unlink(missing_ok=True)
        raise StereotrackError("the recording could not be written completely (rerun's reader does not open it; "
                               "is the disk full?)", path)
