"""Progress of long computations, reported phase by phase (compiling, tuning, Monte Carlo,
plotting). The library is quiet unless a reporter is installed with `reporting(...)`."""

from __future__ import annotations

import contextlib
import contextvars
import sys
import threading
from typing import Iterator, Protocol, TextIO


class Phase(Protocol):
    """A running phase: `update(n)` records `n` more units of work done."""

    def update(self, n: int = 1) -> object: ...


class Reporter(Protocol):
    """Receives phases: `phase(name, total, unit)` is a context manager around the work
    that yields a `Phase` (`total=None`: the amount of work is not known in advance)."""

    def phase(self, name: str, total: int | None = None, unit: str = "it") -> contextlib.AbstractContextManager[Phase]: ...


class _NoPhase:
    def update(self, n: int = 1) -> None:
        return None


class Quiet:
    """The default reporter: reports nothing."""

    @contextlib.contextmanager
    def phase(self, name: str, total: int | None = None, unit: str = "it") -> Iterator[Phase]:
        yield _NoPhase()


class TqdmReporter:
    """One `tqdm` bar per phase on `file` (default `sys.stderr`), with rate and ETA when
    the phase has a total. The bar is redrawn every `refresh` seconds even when no work
    is recorded, so a long compilation still shows its elapsed time."""

    def __init__(self, file: TextIO | None = None, refresh: float = 0.5):
        self.file = file
        self.refresh = refresh

    @contextlib.contextmanager
    def phase(self, name: str, total: int | None = None, unit: str = "it") -> Iterator[Phase]:
        from tqdm import tqdm

        fmt = None if total is not None else "{desc}: {elapsed}{postfix}"
        bar = tqdm(total=total, desc=name, unit=unit, file=self.file or sys.stderr, bar_format=fmt,
                   dynamic_ncols=True, leave=True, mininterval=self.refresh)
        done = threading.Event()

        def tick():
            while not done.wait(self.refresh):
                bar.refresh()

        ticker = threading.Thread(target=tick, daemon=True)
        ticker.start()
        try:
            yield bar
        finally:
            done.set()
            ticker.join()
            bar.close()


_CURRENT: contextvars.ContextVar[Reporter] = contextvars.ContextVar("jdrkf_progress_reporter", default=Quiet())


def current() -> Reporter:
    """The reporter installed in this context (`Quiet()` unless `reporting` installed one)."""
    return _CURRENT.get()


def reporter(show: bool = False) -> Reporter:
    """The installed reporter; if none is and `show` is true, tqdm bars on stderr."""
    installed = current()
    return TqdmReporter() if show and isinstance(installed, Quiet) else installed


@contextlib.contextmanager
def reporting(reporter: Reporter) -> Iterator[Reporter]:
    """Install `reporter` for the code inside the `with` block (context-local: threads
    and other contexts keep theirs)."""
    token = _CURRENT.set(reporter)
    try:
        yield reporter
    finally:
        _CURRENT.reset(token)


def phase(name: str, total: int | None = None, unit: str = "it") -> contextlib.AbstractContextManager[Phase]:
    """Report a phase to the current reporter: `with phase("tuning", total=steps) as p: ... p.update()`."""
    return current().phase(name, total, unit)

