"""Progress of long runs: a tqdm bar on a terminal, plain lines on stdout otherwise.

When stdout is a terminal, :func:`progress` shows a transient tqdm bar (on stderr, cleared
when done). Without one (a log file, CI, ``nohup``) a bar would be invisible or garbled, so it
prints a line to stdout at every tenth of the way instead (``desc: 30/72 (4 s)``).
:class:`Tally` counts a sweep's runs -- running, done, failed -- the same way: a bar with the
counts on a terminal, a line per finished run otherwise.
:func:`note` prints a one-off line to stdout (a run starting, a sweep entry, its duration).
stderr is left to errors: bad input prints exactly one line there.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator, Sized
from typing import TextIO, TypeVar

from tqdm import tqdm

__all__ = ["Tally", "note", "progress"]

T = TypeVar("T")


def _stream() -> TextIO:
    return sys.stdout


def _is_terminal(stream: TextIO) -> bool:
    try:
        return stream.isatty()
    except (AttributeError, ValueError):  # closed or replaced streams
        return False


def note(message: str) -> None:
    """One progress line on stdout."""
    print(message, file=_stream(), flush=True)


def progress(items: Iterable[T], desc: str, total: int | None = None) -> Iterator[T]:
    """``items``, reporting progress: a tqdm bar on stderr when stdout is a terminal;
    otherwise a line on stdout at the start and at each tenth of ``total`` (``len(items)``
    when it has one)."""
    stream = _stream()
    if total is None and isinstance(items, Sized):
        total = len(items)
    if _is_terminal(stream):
        yield from tqdm(items, desc=desc, total=total, leave=False, file=sys.stderr)
        return
    start = time.perf_counter()
    step = max(1, (total or 0) // 10)
    of = f"/{total}" if total else ""
    print(f"{desc}: 0{of}", file=stream, flush=True)
    done = 0
    for item in items:
        yield item
        done += 1
        if done % step == 0 or done == total:
            elapsed = time.perf_counter() - start
            print(f"{desc}: {done}{of} ({elapsed:.0f} s)", file=stream, flush=True)


class Tally:
    """Progress over a sweep: how many of ``total`` runs are running, done and failed.

    On a terminal: one tqdm bar on stderr (the counts beside it), the messages of
    :meth:`update` printed above it on stdout. Otherwise a line on stdout at the start and
    after each update: ``desc: 3/8 (running 2, done 2, failed 1; 41 s) -- message``.
    ``done`` may start above 0 (runs whose records were already there). A context manager:
    leaving it clears the bar.
    """

    def __init__(self, desc: str, total: int, done: int = 0, running: int = 0):
        self.desc, self.total = desc, total
        self.running, self.done, self.failed = running, done, 0
        self._start = time.perf_counter()
        stream = _stream()
        self._bar = None
        if _is_terminal(stream):
            self._bar = tqdm(total=total, desc=desc, leave=False, file=sys.stderr)
            self._bar.update(done)
        self._show()

    def _counts(self) -> str:
        return f"running {self.running}, done {self.done}, failed {self.failed}"

    def _show(self, message: str = "") -> None:
        if self._bar is not None:
            if message:
                self._bar.write(f"{self.desc}: {message}", file=_stream())
            self._bar.set_postfix_str(self._counts())
            return
        elapsed = time.perf_counter() - self._start
        of = f"{self.done + self.failed}/{self.total}"
        line = f"{self.desc}: {of} ({self._counts()}; {elapsed:.0f} s)"
        print(line + (f" -- {message}" if message else ""), file=_stream(), flush=True)

    def update(self, running: int, done: int, failed: int, message: str = "") -> None:
        """New counts (each the total so far), with ``message`` saying what changed."""
        finished = done + failed - self.done - self.failed
        self.running, self.done, self.failed = running, done, failed
        if self._bar is not None:
            self._bar.update(finished)
        self._show(message)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> Tally:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
