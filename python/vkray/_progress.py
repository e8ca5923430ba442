"""Progress bars for long queries (``progress=True``): tqdm's when it is installed, else a line
on stderr at most twice a second."""

from __future__ import annotations

import contextlib
import contextvars
import importlib
import sys
import time
from typing import Any, Callable, Iterator, Optional, TypeVar

T = TypeVar("T")


class Progress:
    """A callable the core calls with (done, total) between chunks; `close` ends the bar."""

    def __init__(self, what: str, unit: str = "ray") -> None:
        self._what = what
        self._unit = unit
        self._bar: Any = None
        self._last = 0.0
        self._line_open = False  # a line printed without its end (the fallback's)
        self._tqdm: Optional[Any] = None
        try:
            self._tqdm = importlib.import_module("tqdm.auto").tqdm
        except ImportError:
            pass

    def __call__(self, done: int, total: int) -> None:
        if self._tqdm is not None:
            if self._bar is None:
                self._bar = self._tqdm(total=total, desc=f"vkray {self._what}", unit=self._unit, unit_scale=True)
            elif self._bar.total != total:
                self._bar.reset(total=total)
            self._bar.n = done
            self._bar.refresh()
            return
        now = time.monotonic()
        if now - self._last >= 0.5 or done == total:
            self._last = now
            print(f"\rvkray {self._what}: {done}/{total}", end="\n" if done == total else "", file=sys.stderr)
            self._line_open = done != total

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        if self._line_open:  # stopped part way (an error, Ctrl-C): the next output starts a line
            print(file=sys.stderr)
            self._line_open = False


#: A callable the core calls with (done, total) between chunks, or raises from to stop the work.
Reporter = Callable[[int, int], None]

# Set by `reporting`: the reporter that takes the place of every query's own progress bar.
_reporter: contextvars.ContextVar[Optional[Reporter]] = contextvars.ContextVar("vkray_reporter", default=None)


@contextlib.contextmanager
def reporting(reporter: Reporter) -> Iterator[None]:
    """Within it, every query of this thread reports to `reporter` instead of showing a bar.

    `vkray.DeviceGroup` runs a query's pieces in worker threads this way: it adds their progress
    up into one bar, and stops them all (its reporter raises) when one fails or Ctrl-C reaches
    the calling thread, which the core's signal checks in other threads never see."""
    token = _reporter.set(reporter)
    try:
        yield
    finally:
        _reporter.reset(token)


def call(progress: bool, what: str, work: Callable[[Optional[Reporter]], T], unit: str = "ray") -> T:
    """Runs `work` with the reporter `reporting` set, else with a progress bar (of `unit`s) when
    the caller asked for one, else None; closes the bar however `work` ends."""
    reporter = _reporter.get()
    if reporter is not None:
        return work(reporter)
    bar = Progress(what, unit) if progress else None
    try:
        return work(bar)
    finally:
        if bar is not None:
            bar.close()
