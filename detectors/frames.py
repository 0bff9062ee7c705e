"""Frame sources: synchronized stereo frame pairs from a clip folder (videos in any container
OpenCV reads, or folders of numbered PNGs), or a single video as a one-camera clip."""

from __future__ import annotations

import queue
import threading
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.errors import ClipError

VIDEO_EXTS = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm")
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


def find_camera_source(clip_dir: Path, name: str) -> Path:
    """``<name>.<video ext>`` or a ``<name>/`` folder of frames inside ``clip_dir``."""
    for ext in VIDEO_EXTS:
        p = clip_dir / f"{name}{ext}"
        if p.is_file():
            return p
    if (clip_dir / name).is_dir():
        return clip_dir / name
    raise ClipError(f"no {name} video ({'/'.join(e[1:] for e in VIDEO_EXTS)}) or {name}/ frame folder", clip_dir)


class CameraReader:
    """Sequential BGR frames of one camera (a video file or a folder of numbered images)."""

    def __init__(self, source: Path) -> None:
        self.source = Path(source)
        self.files: list[Path] | None = None
        self.cap: cv2.VideoCapture | None = None
        if self.source.is_dir():
            self.files = sorted(p for p in self.source.iterdir() if p.suffix.lower() in IMAGE_EXTS)
            if not self.files:
                raise ClipError("frame folder holds no images", self.source)
            first = cv2.imread(str(self.files[0]))
            if first is None:
                raise ClipError(f"cannot decode image {self.files[0].name}", self.source)
            self.size = (first.shape[1], first.shape[0])
            self.count = len(self.files)
            self.fps = 0.0
        else:
            if not self.source.is_file():
                raise ClipError("file not found", self.source)
            if self.source.stat().st_size == 0:
                raise ClipError("empty video file", self.source)
            self.cap = cv2.VideoCapture(str(self.source))
            if not self.cap.isOpened():
                raise ClipError("OpenCV cannot open this video (corrupt or unsupported)", self.source)
            ok, first = self.cap.read()
            if not ok or first is None:
                raise ClipError("video has no decodable frames (corrupt or empty)", self.source)
            self.cap.set(cv2.CAP_PROP_POS_FRAMES, 0)
            self.size = (first.shape[1], first.shape[0])
            self.count = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            self.fps = float(self.cap.get(cv2.CAP_PROP_FPS) or 0.0)

    def __iter__(self) -> Iterator[np.ndarray]:
        if self.files is not None:
            for f in self.files:
                img = cv2.imread(str(f))
                if img is None:
                    raise ClipError(f"cannot decode image {f.name}", self.source)
                yield img
        else:
            assert self.cap is not None
            while True:
                ok, img = self.cap.read()
                if not ok:
                    break
                yield img

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()


_DONE = object()


def _prefetch(it: Iterator[np.ndarray], depth: int = 8) -> Iterator[np.ndarray]:
    """Decode ahead in a background thread (OpenCV releases the GIL while decoding), so decoding
    one camera overlaps with decoding the other and with detection. Errors are re-raised here."""
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def run() -> None:
        try:
            for item in it:
                while not stop.is_set():
                    try:
                        q.put(item, timeout=0.1)
                        break
                    except queue.Full:
                        continue
                if stop.is_set():
                    return
            q.put(_DONE)
        except BaseException as exc:
            q.put(exc)

    th = threading.Thread(target=run, daemon=True)
    th.start()
    try:
        while True:
            item = q.get()
            if item is _DONE:
                return
            if isinstance(item, BaseException):
                raise item
            yield item
    finally:
        stop.set()
        th.join(timeout=5)


@dataclass
class StereoFrame:
    """One synchronized frame pair (``right`` is None for a single-camera clip)."""

    index: int
    t: float
    left: np.ndarray
    right: np.ndarray | None


class StereoFrameSource:
    """Synchronized stereo pairs of a clip folder; unequal left/right lengths are an error unless
    ``allow_unequal`` (then truncated to the shorter, with a warning). A path to a single video
    is a one-camera clip."""

    def __init__(self, clip: str | Path, allow_unequal: bool = False, fps: float | None = None,
                 prefetch: bool = True) -> None:
        clip = Path(clip)
        self.prefetch = prefetch
        if not clip.exists():
            raise ClipError("no such clip folder or video", clip)
        if clip.is_file():
            self.readers = [CameraReader(clip)]
        else:
            self.readers = [CameraReader(find_camera_source(clip, "left")), CameraReader(find_camera_source(clip, "right"))]
        self.clip = clip
        self.allow_unequal = allow_unequal
        counts = [r.count for r in self.readers]
        self.count = min(counts)
        if len(self.readers) == 2 and counts[0] != counts[1] and min(counts) > 0:
            self._unequal(counts)
        self.fps = fps or self.readers[0].fps or 30.0
        self.size = self.readers[0].size
        if len(self.readers) == 2 and self.readers[1].size != self.size:
            raise ClipError(f"left frames are {self.size}, right frames {self.readers[1].size}", clip)

    @property
    def stereo(self) -> bool:
        return len(self.readers) == 2

    def _unequal(self, counts: list[int]) -> None:
        msg = f"left has {counts[0]} frames, right has {counts[1]}"
        if not self.allow_unequal:
            raise ClipError(msg + " (use --allow-unequal to truncate to the shorter)", self.clip)
        warnings.warn(f"{self.clip}: {msg}; truncating to {min(counts)}", stacklevel=3)

    def __len__(self) -> int:
        return self.count

    def __iter__(self) -> Iterator[StereoFrame]:
        its = [_prefetch(iter(r)) for r in self.readers] if self.prefetch else [iter(r) for r in self.readers]
        k = 0
        try:
            while True:
                imgs = [next(it, None) for it in its]
                if all(i is None for i in imgs):
                    break
                if any(i is None for i in imgs):
                    n_left = k if imgs[0] is None else k + 1
                    if not self.allow_unequal:
                        raise ClipError(f"left and right videos end at different frames (around frame {n_left})", self.clip)
                    break
                yield StereoFrame(k, k / self.fps, imgs[0], imgs[1] if len(imgs) > 1 else None)  # type: ignore[arg-type]
                k += 1
        finally:
            for it in its:  # stop the decode-ahead threads before releasing their captures
                close = getattr(it, "close", None)
                if close is not None:
                    close()
            for r in self.readers:
                r.close()
