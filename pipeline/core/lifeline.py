"""Processes that die with their parent, and one writer per output folder (signals: :mod:`pipeline.core.interrupts`).

* :func:`die_with_parent` — called first thing in every child process stereotrack starts (batch
  pool workers, render workers): a daemon thread polls the parent's PID and ends the child with
  ``os._exit`` once the parent is gone, however it ended (SIGKILL included: the child is then
  re-parented and ``getppid`` changes). (``PR_SET_PDEATHSIG`` is not used: it fires when the
  spawning *thread* ends, which for a pool's management thread is not the parent's death.)
* :class:`OutputLock` — an exclusive ``flock`` on ``OUT/.stereotrack.lock`` holding the holder's
  PID, host and command, removed on a clean release. The kernel drops a ``flock`` when its holder
  dies, so a lock file left by a killed run is taken over (with a warning naming the dead
  holder), while a live holder makes a second writer fail at once with a message naming it.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import threading
import time
import warnings
from pathlib import Path

from pipeline.core.errors import StereotrackError

#: What every child process stereotrack starts reads at start-up, and the command line's own
#: process before it loads numpy (:func:`one_blas_thread`): one BLAS / OpenMP thread each. The
#: estimators' matrices are tiny (3×3 to 12×12): on a loaded 2-core machine a threaded BLAS makes
#: small ``expm`` and ``solve`` calls 2–15× slower, and the workers already fill the cores. With
#: two BLAS threads the default methods took 3.1 s of one process on the default clip, with one
#: 1.8–2.4 s, the same numbers.
CHILD_THREADS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def one_blas_thread() -> None:
    """:data:`CHILD_THREADS` in this process's environment (a value the user set wins): BLAS
    libraries loaded after this read it; call it before numpy is imported."""
    for k, v in CHILD_THREADS.items():
        os.environ.setdefault(k, v)


@contextlib.contextmanager
def child_environment(extra: dict[str, str] | None = None):
    """Within the block, child processes start with :data:`CHILD_THREADS`, the allocator settings
    for frames (:mod:`pipeline.core.allocator`) and ``extra`` in their environment (a value the
    user set wins); this process's own settings are restored after."""
    from pipeline.core.allocator import ENV as allocator

    wanted = {**CHILD_THREADS, **allocator, **(extra or {})}
    saved = {k: os.environ.get(k) for k in wanted}
    for k, v in wanted.items():
        os.environ.setdefault(k, v)
    try:
        yield
    finally:
        for k, before in saved.items():
            if before is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = before


LOCK_NAME = ".stereotrack.lock"
#: How often a child checks that its parent is alive (s): the bound on how long it can outlive it.
POLL_S = 0.2


def die_with_parent(parent_pid: int) -> None:
    """End this process as soon as ``parent_pid`` is no longer its parent (see module docstring)."""
    if os.getppid() != parent_pid:
        os._exit(1)  # the parent died before we got here

    def watch() -> None:
        while True:
            time.sleep(POLL_S)
            if os.getppid() != parent_pid:
                os._exit(1)

    threading.Thread(target=watch, name="stereotrack-lifeline", daemon=True).start()


def terminate_with_parent(parent_pid: int) -> None:
    """For ``subprocess`` ``preexec_fn`` (``partial(terminate_with_parent, os.getpid())``): the
    child (a viewer binary, not Python) gets SIGTERM when its parent ``parent_pid`` dies, SIGKILL
    included (Linux ``PR_SET_PDEATHSIG``; elsewhere nothing). A parent that died between the fork
    and the ``prctl`` sends no signal: the child then sees another parent and exits before the
    program starts (a loaded CI machine left a viewer running for minutes that way)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # 1 = PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent_pid:
        os._exit(1)


def end_pool(pool) -> None:
    """End a ``ProcessPoolExecutor`` now (an interrupted command): kill its workers instead of
    waiting for their jobs, cancel what is queued, and reap them."""
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for p in procs:
        with contextlib.suppress(OSError, ValueError):
            p.kill()
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        with contextlib.suppress(OSError, ValueError, AssertionError):
            p.join(timeout=5)


def ignore_sigint() -> None:
    """In a worker process: leave Ctrl-C (sent to the whole process group) to the parent command,
    which ends its workers itself and prints the one ``interrupted`` line."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)


def still_parented(parent_pid: int) -> bool:
    """Whether the process that started this one is still alive (checked before committing work)."""
    return os.getppid() == parent_pid


class OutputLock:
    """Exclusive lock on an output folder for the lifetime of one command (a context manager)."""

    def __init__(self, folder: str | Path, what: str = "stereotrack") -> None:
        self.folder = Path(folder)
        self.path = self.folder / LOCK_NAME
        self.what = what
        self.fd: int | None = None

    def __enter__(self) -> OutputLock:
        import fcntl

        from pipeline.core.io import ensure_dir

        ensure_dir(self.folder)
        while True:
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            except OSError as exc:
                raise StereotrackError(f"cannot create the lock file ({exc.strerror})", self.path) from None
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except OSError:
                holder = _read_holder(fd)
                os.close(fd)
                raise StereotrackError(
                    f"output folder is in use by {holder.get('command', 'another stereotrack')} "
                    f"(PID {holder.get('pid', '?')} on {holder.get('host', '?')}, since {holder.get('since', '?')}); "
                    "wait for it or choose another output folder", self.folder) from None
            # the holder we waited on may have released (and unlinked) the file meanwhile: the lock
            # counts only if the path still names the inode we locked
            try:
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        old = _read_holder(fd)
        if old.get("pid"):
            warnings.warn(f"{self.folder}: taking over the lock of PID {old['pid']} on {old.get('host', '?')} "
                          f"({old.get('command', 'stereotrack')} since {old.get('since', '?')}), which ended without "
                          "releasing it", stacklevel=2)
        me = {"pid": os.getpid(), "host": socket.gethostname(), "command": self.what,
              "since": time.strftime("%Y-%m-%d %H:%M:%S")}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(me).encode(), 0)
        os.fsync(fd)
        self.fd = fd
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def release(self) -> None:
        """Remove the lock file (while still holding it) and drop the lock."""
        if self.fd is None:
            return
        with contextlib.suppress(OSError):
            os.unlink(self.path)
        os.close(self.fd)
        self.fd = None


def _read_holder(fd: int) -> dict:
    try:
        raw = os.pread(fd, 4096, 0)
        return json.loads(raw) if raw.strip() else {}
    except (OSError, ValueError):
        return {}
