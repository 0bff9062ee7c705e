"""What happens to a rendered frame before it is a file: sensor noise and blur, and the writers
(an MP4 or a folder of PNGs, written atomically; optionally on a thread of their own, so that
encoding overlaps rasterising where that pays)."""

from __future__ import annotations

import queue
import shutil
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import cv2
import numpy as np

from pipeline.core.errors import ClipError

Format = Literal["mp4", "png"]


class SensorNoise:
    """Additive Gaussian sensor noise (σ in grey levels), seeded per clip and camera.

    Drawing a fresh normal deviate per pixel per frame costs more than rendering the frame, so a
    bank of eight noise fields slightly larger than the image is drawn once and each frame takes
    one of them at a random offset (both chosen from ``default_rng([seed, camera, frame])``):
    still white in space, independent enough in time for tracking, and the same bits every run.
    """

    MARGIN = 64

    def __init__(self, shape: tuple[int, int, int], sigma: float, seed: int, camera: int, bank: int = 8) -> None:
        self.shape, self.sigma, self.seed, self.camera = shape, sigma, seed, camera
        if sigma > 0:
            h, w, c = shape
            self.bank = np.empty((bank, h + self.MARGIN, w + self.MARGIN, c), np.int16)
            for i in range(bank):  # OpenCV's generator is several times faster than numpy's here
                cv2.setRNGSeed(int(np.random.SeedSequence([seed, 30_000 + camera, i]).generate_state(1)[0]) & 0x7FFFFFFF)
                cv2.randn(self.bank[i], np.zeros(c), np.full(c, float(sigma)))  # per channel

    def apply(self, img: np.ndarray, frame: int) -> np.ndarray:
        if self.sigma <= 0:
            return img
        rng = np.random.default_rng([self.seed, 20_000 + self.camera, frame])
        i, dy, dx = rng.integers(len(self.bank)), *rng.integers(0, self.MARGIN, 2)
        h, w, _ = self.shape
        return cv2.add(img, self.bank[i, dy : dy + h, dx : dx + w], dtype=cv2.CV_8U)


def postprocess(img: np.ndarray, blur_sigma: float, noise: SensorNoise, frame: int) -> np.ndarray:
    """Optical blur (Gaussian, σ in px), then sensor noise."""
    if blur_sigma > 0:
        img = cv2.GaussianBlur(img, (0, 0), blur_sigma)
    return noise.apply(img, frame)


class FrameWriter:
    """Writes one camera's frames to ``<name>.mp4`` or a ``<name>/`` folder of PNGs, atomically:
    into a hidden partial file/folder first, moved into place by :meth:`close`."""

    def __init__(self, clip_dir: Path, name: str, fmt: Format, fps: float, size: tuple[int, int]) -> None:
        self.final = clip_dir / (f"{name}.mp4" if fmt == "mp4" else name)
        self.fmt = fmt
        self.tmp = clip_dir / f".{name}.partial{'.mp4' if fmt == 'mp4' else ''}"
        if self.tmp.is_dir():
            shutil.rmtree(self.tmp)
        self.count = 0
        if fmt == "mp4":
            self.writer = cv2.VideoWriter(str(self.tmp), cv2.VideoWriter.fourcc(*"mp4v"), fps, size)
            if not self.writer.isOpened():
                raise ClipError("OpenCV cannot open an MP4 writer (mp4v); use --format png", self.final)
        else:
            self.tmp.mkdir(parents=True)

    def write(self, rgb: np.ndarray, index: int | None = None) -> None:
        """Append a frame; a PNG is named by ``index`` (default: the next number), so a dropped
        frame leaves a gap in the numbering, as real frame dumps do."""
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        if self.fmt == "mp4":
            self.writer.write(bgr)
        else:
            name = f"{self.count if index is None else index:06d}.png"
            cv2.imwrite(str(self.tmp / name), bgr, [cv2.IMWRITE_PNG_COMPRESSION, 1])
        self.count += 1

    def close(self) -> None:
        if self.fmt == "mp4":
            self.writer.release()
            self.tmp.replace(self.final)
        else:
            if self.final.is_dir():
                shutil.rmtree(self.final)
            self.tmp.rename(self.final)

    def abort(self) -> None:
        if self.fmt == "mp4":
            self.writer.release()
            self.tmp.unlink(missing_ok=True)
        elif self.tmp.is_dir():
            shutil.rmtree(self.tmp, ignore_errors=True)


class BackgroundWriter:
    """Blur, noise and encoding of one camera's frames on a thread of their own (``threaded``; else
    on the caller's, as each frame comes), in frame order:
    OpenCV releases the GIL in all three, so the next frame renders while this one is encoded
    (on a GPU the render loop then waits on neither). The video writer is opened, written,
    closed or discarded on that thread alone. The first error is raised by the next :meth:`put`
    or by :meth:`close`; :meth:`abort` drops what is queued and removes the partial file."""

    def __init__(self, open_writer: Callable[[], FrameWriter], blur_sigma: float, noise: SensorNoise,
                 depth: int = 4, threaded: bool = True) -> None:
        self.blur_sigma, self.noise = blur_sigma, noise
        self.queue: queue.Queue = queue.Queue(maxsize=depth)
        self.error: BaseException | None = None
        self.commit = False
        self.inline = None if threaded else open_writer()  # unthreaded: everything on the caller's thread
        self.thread: threading.Thread | None = None
        if threaded:
            self.thread = threading.Thread(target=self._loop, args=(open_writer,), name="frame-writer", daemon=True)
            self.thread.start()

    def _loop(self, open_writer: Callable[[], FrameWriter]) -> None:
        writer = None
        try:
            writer = open_writer()
            while (item := self.queue.get()) is not None:
                img, k = item
                writer.write(postprocess(img, self.blur_sigma, self.noise, k), index=k)
            if self.commit:
                writer.close()
                return
        except BaseException as exc:  # handed to the rendering thread
            self.error = exc
            while self.queue.get() is not None:  # drain until the renderer says stop
                pass
        if writer is not None:
            writer.abort()

    def _raise(self) -> None:
        if self.error is not None:
            raise self.error

    def put(self, img: np.ndarray, frame: int) -> None:
        if self.inline is not None:
            self.inline.write(postprocess(img, self.blur_sigma, self.noise, frame), index=frame)
            return
        self._raise()
        self.queue.put((img, frame))

    def close(self) -> None:
        """Wait for every queued frame, then move the file into place."""
        if self.inline is not None:
            self.inline.close()
            return
        assert self.thread is not None
        self.commit = True
        self.queue.put(None)
        self.thread.join()
        self._raise()

    def abort(self) -> None:
        if self.inline is not None:
            self.inline.abort()
        elif self.thread is not None and self.thread.is_alive():
            self.commit = False
            self.queue.put(None)
            self.thread.join()


def writer_threaded(renderer) -> bool:
    """Whether post-processing and encoding get a thread of their own: on a GPU, where the
    rendering thread mostly waits; not under a software rasteriser (llvmpipe), which keeps the
    cores busy itself (measured in benchmarks/render.py: a thread there did not pay)."""
    return not getattr(renderer, "software", True)
