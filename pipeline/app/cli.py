"""The ``stereotrack`` command line (typer + rich). I/O and presentation only: every command calls
the library functions the tests call."""

import sys
import warnings
from pathlib import Path

from rich.markup import escape

from pipeline.core.errors import StereotrackError, first_line

# isort: off
# the commands register with the app as their modules load, in this order (``--help`` lists them so)
from pipeline.app import cli_commands, cli_batch, cli_rig  # noqa: F401
# isort: on
from pipeline.app.cli_common import app, console

_shown: set[str] = set()


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings as one line ``warning: FILE: problem`` (no source line, no category), each once; a
    library's warning (numpy's, say) names the library and the stereotrack line that caused it."""
    text = str(message)
    ours = issubclass(category, UserWarning) and bool({"pipeline", "detectors", "renderers"} & set(Path(filename).parts))
    if not ours:
        text = f"{Path(filename).name}:{lineno}: {category.__name__}: {text}"
    if text in _shown:
        return
    _shown.add(text)
    console.print(f"[yellow]warning:[/] {escape(text)}", highlight=False, soft_wrap=True)


def _error(text: str) -> None:
    console.print(f"[bold red]error:[/] {escape(text)}", highlight=False, soft_wrap=True)


def main() -> None:
    """Console-script entry point: user errors become one line on stderr and exit code 2; SIGINT and
    SIGTERM one line and exit 130/143, with locks released and temporary files and workers gone."""
    import os

    from pipeline.core import allocator
    from pipeline.core.interrupts import install_signal_handlers
    from pipeline.core.lifeline import one_blas_thread

    one_blas_thread()  # before numpy loads: the estimators' matrices are tiny (see CHILD_THREADS)
    allocator.tune()  # frames churn through the allocator: keep their pages (see the module)
    warnings.showwarning = _show_warning
    # multiprocessing's resource tracker (a process started with this interpreter's -W options) still
    # cleans up what an interrupted pool leaves, but its "leaked semaphore" lines are noise after the
    # one line an interrupt prints: a worker starting as the signal comes registers a semaphore the
    # finalizers of _release_semaphores cannot know of (seen once in about forty interrupted batches)
    sys.warnoptions.append("ignore::UserWarning:multiprocessing.resource_tracker")
    install_signal_handlers()
    try:
        app()
    except StereotrackError as exc:
        _interrupted_if_signalled()  # an error that followed a signal is the signal's
        _error(str(exc))
        sys.exit(2)
    except OSError as exc:  # an output path that cannot be written, a disk that filled up
        _interrupted_if_signalled()
        where = f"{exc.filename}: " if exc.filename else ""
        _error(where + str(exc.strerror or exc))
        sys.exit(2)
    except KeyboardInterrupt:
        _interrupted()
    except SystemExit as exc:
        if exc.code in (0, None, 130):  # typer turns KeyboardInterrupt into Exit(130); a signal whose
            _interrupted_if_signalled()  # interrupt a library swallowed ends the command here at the latest
        raise
    except Exception as exc:  # a bug, not a bad input: still one line, the traceback on request
        _interrupted_if_signalled()
        if os.environ.get("STEREOTRACK_DEBUG"):
            raise
        import traceback

        last = traceback.extract_tb(exc.__traceback__)[-1]
        _error(f"internal error: {type(exc).__name__}: {first_line(exc) if str(exc).strip() else ''} "
               f"({Path(last.filename).name}:{last.lineno}); rerun with STEREOTRACK_DEBUG=1 for the traceback")
        sys.exit(1)
    else:
        _interrupted_if_signalled()


def _interrupted_if_signalled() -> None:
    from pipeline.core.interrupts import received_signal

    if received_signal() is not None:
        _interrupted()


def _interrupted() -> None:
    import os
    import signal

    from pipeline.core.interrupts import received_signal

    sig = received_signal() or signal.SIGINT
    console.print(f"[bold red]interrupted[/] ({signal.Signals(sig).name}): stopped; nothing half-written was kept",
                  highlight=False)
    # Every lock, temporary file and worker is gone by now (released on the way up). Leave at once with
    # the documented status: about one interrupted render-batch in ten under load was otherwise ended by
    # a KeyboardInterrupt during the interpreter's shutdown (exit status −2, whatever the signal).
    _release_semaphores()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(128 + sig)


def _release_semaphores() -> None:
    """Unlink the named semaphores of the worker pools' queues and locks (their finalizers, which a
    normal exit runs and ``os._exit`` skips), so that multiprocessing's resource tracker does not
    print "leaked semaphore objects" after an interrupted batch or render."""
    import contextlib
    from multiprocessing import util

    with contextlib.suppress(Exception):
        util._run_finalizers(0)  # type: ignore[attr-defined]  # priority ≥ 0: closes, unlinks; no joins (< 0)


if __name__ == "__main__":
    main()
