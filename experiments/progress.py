"""Progress of long runs: a tqdm bar on a terminal, plain lines on stdout otherwise.

When stdout is a terminal, :func:`progress` shows a transient tqdm bar (on stderr, cleared
when done). Without one (a log file, CI, ``nohup``) a bar would be invisible or garbled, so it
prints a line to stdout at every tenth of the way instead (``desc: 30/72 (4 s)``).
:func:`note` prints a one-off line to stdout (a run starting, a sweep entry, its duration).
stderr is left to errors: bad input prints exactly one line there.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator, Sized
from typing import TextIO, TypeVar

from tqdm import tqdm

__all__ = ["note", "progress"]

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
