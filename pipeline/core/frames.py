"""Frame sources: synchronized stereo frame pairs from a clip folder (videos in any container
OpenCV reads, or folders of numbered PNGs), or a single video as a one-camera clip."""

from __future__ import annotations

import multiprocessing
import os
import queue
import re
import threading
import warnings
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.core.errors import ClipError
from pipeline.core.forked import can_fork
from pipeline.core.interrupts import signals_deferred
from pipeline.core.lazy import lazy_module
from pipeline.core.lifeline import die_with_parent, ignore_sigint

if TYPE_CHECKING:
    import cv2
else:
    cv2 = lazy_module("cv2")  # imported on first use: `estimate` reads no frames

VIDEO_EXTS = (".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm")
IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")

_FRAME_NUMBER = re.compile(r"(\d+)$")


def video_codec(path: Path) -> str:
    """A video file's codec tag as FFmpeg reports it, lower case (``avc1``/``h264`` for H.264,
    ``fmp4`` for MPEG-4 Part 2); empty when it is no video OpenCV opens."""
    cap = cv2.VideoCapture(str(path))
    try:
        tag = int(cap.get(cv2.CAP_PROP_FOURCC)) if cap.isOpened() else 0
    finally:
        cap.release()
    return tag.to_bytes(4, "little").decode("ascii", "replace").strip("\x00 ").lower() if tag > 0 else ""


def find_camera_source(clip_dir: Path, name: str) -> Path:
    """``<name>.<video ext>`` or a ``<name>/`` folder of frames inside ``clip_dir``."""
    for ext in VIDEO_EXTS:
        p = clip_dir / f"{name}{ext}"
        if p.is_file():
            return p
    if (clip_dir / name).is_dir():
        return clip_dir / name
    raise ClipError(f"no {name} video ({'/'.join(e[1:] for e in VIDEO_EXTS)}) or {name}/ frame folder", clip_dir)



def index_frame_files(folder: Path) -> dict[int, Path]:
    """Frame number → image file of a folder of numbered frames. The number is the last run of
    digits of the file name (``frame_000012.png`` → 12), so a missing file is a gap, never a
    shift of every later frame; two files with one number are an error naming both."""
    files: dict[int, Path] = {}
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() not in IMAGE_EXTS or p.name.startswith("."):
            continue
        m = _FRAME_NUMBER.search(p.stem)
        if m is None:
            raise ClipError(f"image {p.name} has no frame number in its name (expected e.g. 000012{p.suffix})", folder)
        k = int(m.group(1))
        if k in files:
            raise ClipError(f"images {files[k].name} and {p.name} both claim frame {k}", folder)
        files[k] = p
    return files


class CameraReader:
    """Sequential BGR frames of one camera (a video file or a folder of numbered images).

    For a frame folder, frame ``k`` is the file numbered ``first + k``; a frame whose file is
    missing (a gap in the numbering) is yielded as None, with a warning naming the gap. ``threads``
    caps the video decoder's own threads (None: the backend's default).
    """

    def __init__(self, source: Path, first_index: int | None = None, threads: int | None = None) -> None:
        self.source = Path(source)
        self.threads = threads
        self.files: dict[int, Path] | None = None
        self.cap: cv2.VideoCapture | None = None
        if self.source.is_dir():
            self.files = index_frame_files(self.source)
            if not self.files:
                raise ClipError("frame folder holds no images", self.source)
            self.first = min(self.files) if first_index is None else first_index
            first_file = self.files[min(self.files)]
            first = cv2.imread(str(first_file))
            if first is None:
                raise ClipError(f"cannot decode image {first_file.name}", self.source)
            self.size = (first.shape[1], first.shape[0])
            self.count = max(self.files) - self.first + 1
            self.fps = 0.0
            self.gaps = [k - self.first for k in range(self.first, max(self.files) + 1) if k not in self.files]
        else:
            if not self.source.is_file():
                raise ClipError("file not found", self.source)
            if self.source.stat().st_size == 0:
                raise ClipError("empty video file", self.source)
            self.cap = _open_video(self.source, threads)
            if not self.cap.isOpened():
                raise ClipError("OpenCV cannot open this video (corrupt or unsupported)", self.source)
            ok, first = self.cap.read()
            if not ok or first is None:
                raise ClipError("video has no decodable frames (corrupt or empty)", self.source)
            self._first: np.ndarray | None = first  # kept, not re-read: seeking back fails on a 1-frame video
            self.size = (first.shape[1], first.shape[0])
            self.count = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT) or 0)
            self.fps = float(self.cap.get(cv2.CAP_PROP_FPS) or 0.0)
            self.gaps = []

    def warn_gaps(self) -> None:
        """One warning line for missing frame numbers (those frames count as missed)."""
        if self.gaps:
            shown = ", ".join(str(g + self.first) for g in self.gaps[:5]) + (" …" if len(self.gaps) > 5 else "")
            warnings.warn(f"{self.source}: {len(self.gaps)} frame number(s) missing ({shown}): "
                          "treated as frames with no detection", stacklevel=3)

    def __iter__(self) -> Iterator[np.ndarray | None]:
        if self.files is not None:
            for k in range(self.first, self.first + self.count):
                f = self.files.get(k)
                if f is None:
                    yield None
                    continue
                img = cv2.imread(str(f))
                if img is None:
                    raise ClipError(f"cannot decode image {f.name}", self.source)
                if (img.shape[1], img.shape[0]) != self.size:
                    raise ClipError(f"image {f.name} is {img.shape[1]}×{img.shape[0]}, the folder's frames are "
                                    f"{self.size[0]}×{self.size[1]}", self.source)
                yield img
        else:
            assert self.cap is not None
            if self._first is not None:
                first, self._first = self._first, None
                yield first
            while True:
                ok, img = self.cap.read()
                if not ok:
                    break
                yield img

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()


def _open_video(path: Path, threads: int | None) -> cv2.VideoCapture:
    """A capture of ``path``, its decoder limited to ``threads`` threads where the backend takes
    the setting (else opened as by default)."""
    if threads is not None:
        cap = cv2.VideoCapture(str(path), cv2.CAP_ANY, [cv2.CAP_PROP_N_THREADS, threads])
        if cap.isOpened():
            return cap
    return cv2.VideoCapture(str(path))


def decoder_threads(cameras: int) -> int:
    """Decoder threads per camera when every camera decodes at once: the cores shared out. On two
    cores, two one-thread decoders at once read a 150-frame 640×480 stereo clip in 33 ms with
    65 ms of CPU; two with FFmpeg's default threads took 43–57 ms and 97 ms."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cores // max(cameras, 1))


_DONE = object()


def _prefetch(it: Iterator[Any], depth: int = 8) -> Iterator[Any]:
    """Decode ahead in a background thread (OpenCV releases the GIL while decoding), together with
    the camera's work on each frame (:meth:`StereoFrameSource.frames`), so one camera's decoding and
    detection overlap the other's. Errors are re-raised here."""
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
    """One synchronized frame pair (``right`` is None for a single-camera clip); ``found``: what
    each camera's ``work`` returned for its frame (see :meth:`StereoFrameSource.frames`), None
    for a camera whose frames have ended."""

    index: int
    t: float
    left: np.ndarray | None  # None: this camera's frame is missing (a gap in a frame folder)
    right: np.ndarray | None
    found: tuple = ()
    #: every camera's frame, in the clip's camera order (left, right for a stereo clip)
    images: tuple = ()


#: per-camera work on each of its frames (None: a missing frame), in frame order
Work = Callable[[np.ndarray | None], Any]


#: frames' results a camera's process sends at a time
CHUNK = 8


class _InProcess:
    """What ``work`` makes of each of ``reader``'s frames, decoded and worked on in a process forked
    for this camera (started at once), beside None for its image. Per-frame work of many short
    numpy calls holds the GIL, so cameras in threads take turns; in processes they run side by side.
    The process opens the footage itself (a capture does not survive a fork), dies with this one,
    SIGKILL included, and is killed by :meth:`close`; an error it meets is raised here. With each
    chunk of results comes what the process's copy of ``work`` hands over (``work.handover()``,
    when it has one), given to ``work.take`` here: state the caller reads once the frames end, as
    of the frames received (a caller that stops early, at the shorter camera's end, has it too)."""

    def __init__(self, reader: CameraReader, work: Work) -> None:
        self.reader, self.work = reader, work
        ctx = multiprocessing.get_context("fork")
        self.recv, send = ctx.Pipe(duplex=False)
        self.proc = ctx.Process(target=_camera_process, args=(reader, work, send, os.getpid()), daemon=True,
                                name=f"stereotrack-{reader.source.stem}")
        with signals_deferred():  # a signal inside fork's handlers would be printed and swallowed there
            self.proc.start()
        send.close()
        self.chunk: deque = deque()
        self.ended = False

    def __iter__(self) -> _InProcess:
        return self

    def __next__(self) -> tuple[None, Any]:
        while not self.chunk:
            if self.ended:
                raise StopIteration
            self._receive()
        return None, self.chunk.popleft()

    def _receive(self) -> None:
        try:
            kind, payload = self.recv.recv()
        except EOFError:
            self.close()
            raise ClipError(f"the process reading this footage ended early (exit code {self.proc.exitcode})",
                            self.reader.source) from None
        if kind == "error":
            self.close()
            raise payload
        if kind == "end":
            self.ended = True
            self.close()
            return
        found, state = payload
        self.chunk.extend(found)
        if state is not None:
            self.work.take(state)  # type: ignore[attr-defined]

    def close(self) -> None:
        """End the process (killed unless it is done) and reap it."""
        if self.proc.is_alive() and not self.ended:
            self.proc.kill()
        self.proc.join()
        self.recv.close()


def _camera_process(reader: CameraReader, work: Work, send: Any, parent: int) -> None:
    """A camera's process (:class:`_InProcess`): its footage read afresh, each frame through ``work``,
    the results sent in chunks of :data:`CHUNK` with ``work``'s handover, then ``("end", None)``; or
    ``("error", exc)`` (an error that does not pickle as its message, naming the footage)."""
    die_with_parent(parent)
    ignore_sigint()
    handover = getattr(work, "handover", None)
    try:
        chunk: list = []
        for img in CameraReader(reader.source, getattr(reader, "first", None), reader.threads):
            chunk.append(work(img))
            if len(chunk) == CHUNK:
                send.send(("found", (chunk, handover() if handover is not None else None)))
                chunk = []
        send.send(("found", (chunk, handover() if handover is not None else None)))
        send.send(("end", None))
    except BaseException as exc:  # every error goes to the parent, which raises it
        try:
            send.send(("error", exc))
        except Exception:  # an exception that does not pickle: its message
            send.send(("error", ClipError(f"{type(exc).__name__}: {exc}", reader.source)))
    finally:
        send.close()


def _worked(it: Iterator[np.ndarray | None], work: Work | None) -> Iterator[tuple[np.ndarray | None, Any]]:
    """Each frame beside what ``work`` makes of it (None without work)."""
    for img in it:
        yield img, (work(img) if work is not None else None)


class StereoFrameSource:
    """Stereo pairs of a clip folder, frame k of each camera together; unequal left/right lengths
    are an error unless ``allow_unequal`` (then truncated to the shorter, with a warning) or the
    clip has per-camera frame times (``timestamps.csv``: cameras that dropped frames have
    different lengths, and every frame of both is kept; the estimate stage pairs them by time).
    A path to a single video is a one-camera clip."""

    def __init__(self, clip: str | Path, allow_unequal: bool = False, fps: float | None = None,
                 prefetch: bool = True, cameras: Sequence[str] = ("left", "right")) -> None:
        clip = Path(clip)
        self.cameras = tuple(cameras)
        self.prefetch = prefetch
        if not clip.exists():
            raise ClipError("no such clip folder or video", clip)
        if clip.is_file():
            self.readers = [CameraReader(clip)]
        else:
            srcs = [find_camera_source(clip, name) for name in self.cameras]
            first = None
            if all(s.is_dir() for s in srcs):  # both folders number frames from the same origin
                first = min(min(index_frame_files(s) or [0]) for s in srcs)
            threads = decoder_threads(len(srcs)) if prefetch else None  # the cameras decode at once
            self.readers = [CameraReader(s, first, threads) for s in srcs]
        for r in self.readers:
            r.warn_gaps()
        self.clip = clip
        self.allow_unequal = allow_unequal
        counts = [r.count for r in self.readers]
        self.keep_all = len(self.readers) >= 2 and clip.is_dir() and (clip / "timestamps.csv").is_file()
        self.count = max(counts) if self.keep_all else min(counts)
        if len(self.readers) >= 2 and len(set(counts)) > 1 and min(counts) > 0 and not self.keep_all:
            self._unequal(counts)
        self.fps = fps or self.readers[0].fps or 30.0
        self.size = self.readers[0].size
        #: every camera's frame size (an N-camera rig may mix them)
        self.sizes = [r.size for r in self.readers]
        if len(self.readers) == 2 and self.readers[1].size != self.size:
            raise ClipError(f"{self.cameras[0]} frames are {self.size}, {self.cameras[1]} frames {self.readers[1].size}",
                            clip)

    @property
    def stereo(self) -> bool:
        return len(self.readers) == 2

    def _unequal(self, counts: list[int]) -> None:
        msg = ", ".join(f"{name} has {n} frames" for name, n in zip(self.cameras, counts, strict=True))
        if not self.allow_unequal:
            raise ClipError(msg + " (use --allow-unequal to truncate to the shorter)", self.clip)
        warnings.warn(f"{self.clip}: {msg}; truncating to {min(counts)}", stacklevel=3)

    def __len__(self) -> int:
        return self.count

    def __iter__(self) -> Iterator[StereoFrame]:
        return self.frames()

    def frames(self, work: Sequence[Work | None] | None = None, forked: bool = False) -> Iterator[StereoFrame]:
        """The pairs in order, each camera's frames first through its ``work`` (one callable per
        camera, called on every frame of that camera in order) in the camera's decode thread:
        per-camera work such as detection runs beside the other camera's, off the thread that
        iterates. Results are in :attr:`StereoFrame.found`.

        ``forked``: each camera decodes and works in a process of its own instead (where the
        platform forks, and every camera has work; see :class:`_InProcess`): the images stay
        there (every image None here), the work's results come back."""
        work = list(work or [None] * len(self.readers))
        jobs = [w for w in work if w is not None]
        its: list[Iterator] = []
        k = 0
        end: Any = object()
        try:
            if forked and len(self.readers) > 1 and len(jobs) == len(work) and can_fork():
                for r, w in zip(self.readers, jobs, strict=True):
                    its.append(_InProcess(r, w))  # one at a time: those started are closed if the next fails
            else:
                its = [_worked(iter(r), w) for r, w in zip(self.readers, work, strict=True)]
                its = [_prefetch(it) for it in its] if self.prefetch else its
            while True:
                got = [next(it, end) for it in its]
                if all(i is end for i in got):
                    break
                if k >= self.count and any(i is end for i in got):
                    break  # truncated to the shorter camera
                if any(i is end for i in got) and not self.keep_all:
                    n_left = k if got[0] is end else k + 1
                    if not self.allow_unequal:
                        raise ClipError(f"the cameras' videos end at different frames (around frame {n_left})", self.clip)
                    break
                imgs = [None if i is end else i[0] for i in got]
                found = tuple(None if i is end else i[1] for i in got)
                yield StereoFrame(k, k / self.fps, imgs[0], imgs[1] if len(imgs) > 1 else None, found, tuple(imgs))
                k += 1
        finally:
            for it in its:  # stop the decode-ahead threads before releasing their captures
                close = getattr(it, "close", None)
                if close is not None:
                    close()
            for r in self.readers:
                r.close()
