"""The progress bar of every long command: its columns and its one style."""

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    Task,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.text import Text

from pipeline.core.interrupts import raise_if_interrupted


class RemainingColumn(TimeRemainingColumn):
    """Time remaining, except for a task whose units take unequal times (``eta=False`` among its
    fields): the estimate stage counts methods × markers, and its methods differ a hundredfold in
    cost, so a rate from the first ones said 3:19 for a 21 s stage."""

    def render(self, task: Task) -> Text:
        if task.fields.get("eta", True) is False:
            return Text("-:--:--", style="progress.remaining")
        return super().render(task)


class CountColumn(MofNCompleteColumn):
    """``done/total``, or nothing for a task that counts nothing (``count=False`` among its fields:
    a batch's per-clip lines, which name the clip's stage, used to sit at ``0/?``)."""

    def render(self, task: Task) -> Text:
        if task.fields.get("count", True) is False:
            return Text("")
        return super().render(task)


class StageProgress(Progress):
    """A progress display that leaves no bar behind when its stage fails: the error line follows
    the command directly, not a frozen ``0/?`` bar above it."""

    def update(self, *args, **kwargs) -> None:
        """Update a task; a signal whose interrupt was lost stops the command here (see
        :func:`~pipeline.core.interrupts.raise_if_interrupted`)."""
        raise_if_interrupted()
        super().update(*args, **kwargs)

    def advance(self, *args, **kwargs) -> None:
        raise_if_interrupted()
        super().advance(*args, **kwargs)

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            super().__exit__(exc_type, exc, tb)
            return
        self.live.transient = True  # erased from a terminal, never printed to a file or pipe
        self.live.stop()  # (Progress.stop would end a line that is no longer there)


def progress_bar(console: Console) -> Progress:
    """The one progress-bar style of every long command."""
    return StageProgress(
        TextColumn("[bold]{task.description}"),
        BarColumn(),
        CountColumn(),
        TimeElapsedColumn(),
        RemainingColumn(),
        console=console,
        transient=False,
    )
