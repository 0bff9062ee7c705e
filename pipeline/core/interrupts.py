"""Signals: SIGINT and SIGTERM end a command by a KeyboardInterrupt in its main thread, so that
every lock, temporary file and worker is released on the way out; held while workers start;
checked again at every commit, as a library can swallow the first one."""

from __future__ import annotations

import contextlib
import signal
import threading

_received: int | None = None  # the signal that ended the command
_deferring = 0
_pending: int | None = None


def install_signal_handlers() -> None:
    """SIGINT and SIGTERM raise KeyboardInterrupt in the main thread, so that every lock, temporary
    file and worker is released on the way out (a command's entry point calls this once)."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, _on_signal)


def received_signal() -> int | None:
    """The signal that interrupted this command, if one did."""
    return _received


def _on_signal(signum: int, frame: object) -> None:
    global _received, _pending
    _received = signum
    if _deferring:
        _pending = signum
        return
    _interrupt()


def raise_if_interrupted() -> None:
    """Raise KeyboardInterrupt in the main thread once a signal has come. The handler raises it at
    once, but an exception raised inside a C extension's import is sometimes swallowed there (numpy.random
    loaded lazily swallowed 2 of 200 signals sent as it loaded): every commit and progress tick
    checks again, so a command still stops and writes nothing more."""
    if _received is not None and not _deferring and threading.current_thread() is threading.main_thread():
        raise KeyboardInterrupt


def _interrupt() -> None:
    """Raise KeyboardInterrupt once: a second signal during the clean-up is ignored."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, signal.SIG_IGN)
    raise KeyboardInterrupt


@contextlib.contextmanager
def signals_deferred():
    """Hold SIGINT/SIGTERM while starting worker processes: an interrupt in the middle of handing a
    spawned child its start-up data would leave it to die with a traceback of its own. The signal
    takes effect (KeyboardInterrupt) as the block ends."""
    global _deferring, _pending
    _deferring += 1
    try:
        yield
    finally:
        _deferring -= 1
        if not _deferring and _pending is not None:
            _pending = None
            _interrupt()
