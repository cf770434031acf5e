"""The progress of a command's long loops (pwm.parallel.Progress) on stderr: on a terminal one
line per stage that rich redraws (what, done/total, elapsed, time left); elsewhere (CI, logs,
pipes) a plain line at each tenth of a stage, or after PLAIN_EVERY_S without one, never control
codes."""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import TextIO

from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress as Bar,
    SpinnerColumn,
    TaskID,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from pwm.parallel import Progress

# Where stderr is no terminal: a line at each tenth of a stage, and one at least this often (s)
# while a stage is under way, so that a log shows the run is alive.
PLAIN_EVERY_S = 30.0
STEPS = 10


def _clock(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 3600}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class PlainProgress:
    """Progress as plain lines on `stream` (see the module), `unit` naming the items."""

    def __init__(self, stream: TextIO, *, unit: str, now: Callable[[], float] = time.monotonic) -> None:
        self.stream, self.unit, self.now = stream, unit, now
        self.stages: dict[str, tuple[float, int]] = {}  # stage: its start, and the tenth last shown
        self.shown_at = now()

    def __call__(self, stage: str, done: int, total: int) -> None:
        if total <= 0:
            return  # a stage with nothing to do says nothing
        now = self.now()
        if stage not in self.stages:
            self.stages[stage] = (now, -1)
        started, shown = self.stages[stage]
        tenth = STEPS * done // total
        if tenth <= shown and now - self.shown_at < PLAIN_EVERY_S and done < total:
            return
        if tenth <= shown and done >= total:
            return  # the last line of the stage is out already
        self.stages[stage] = (started, tenth)
        self.shown_at = now
        elapsed = now - started
        left = f", about {_clock(elapsed * (total - done) / done)} left" if 0 < done < total else ""
        self.stream.write(f"{stage}: {done}/{total} {self.unit} ({100 * done // total}%), "
                          f"{_clock(elapsed)} elapsed{left}\n")
        self.stream.flush()


@contextmanager
def progress_bar(*, unit: str = "maplets", stream: TextIO | None = None) -> Iterator[Progress]:
    """A Progress that shows itself on `stream` (default stderr) while the block runs: rich's bar
    where it is a terminal, PlainProgress lines elsewhere. Log lines written meanwhile go above
    the bar."""
    stream = stream or sys.stderr
    console = Console(file=stream)
    if not console.is_terminal:
        yield PlainProgress(stream, unit=unit)
        return
    bar = Bar(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn(unit),
              TimeElapsedColumn(), TextColumn("left"), TimeRemainingColumn(), console=console)
    tasks: dict[str, TaskID] = {}

    def advance(stage: str, done: int, total: int) -> None:
        if total <= 0:
            return
        if stage not in tasks:
            tasks[stage] = bar.add_task(stage, total=total)
        bar.update(tasks[stage], completed=done, total=total)

    with bar, _logs_through(console):
        yield advance


@contextmanager
def working(what: str, *, stream: TextIO | None = None) -> Iterator[None]:
    """For a long step that does not count its items: a spinner with the time elapsed on a
    terminal, one plain line elsewhere."""
    stream = stream or sys.stderr
    console = Console(file=stream)
    if not console.is_terminal:
        stream.write(f"{what} ...\n")
        stream.flush()
        yield
        return
    with Bar(SpinnerColumn(), TextColumn(what), TimeElapsedColumn(), console=console, transient=True) as bar, \
            _logs_through(console):
        bar.add_task(what, total=None)
        yield


@contextmanager
def _logs_through(console: Console) -> Iterator[None]:
    """The root logger's stream handlers writing through rich's console while a bar is drawn, so
    that a log line is printed above the bar, not into it."""
    handlers = [h for h in logging.getLogger().handlers
                if isinstance(h, logging.StreamHandler) and h.stream is console.file]
    for handler in handlers:
        handler.setStream(_ConsoleStream(console))
    try:
        yield
    finally:
        for handler in handlers:
            handler.setStream(console.file)


class _ConsoleStream:
    """A text stream that prints through a rich console (log lines above a live bar)."""

    def __init__(self, console: Console) -> None:
        self.console = console

    def write(self, text: str) -> int:
        self.console.print(text.rstrip("\n"), markup=False, highlight=False, soft_wrap=True)
        return len(text)

    def flush(self) -> None:
        pass
