"""What the tool prints while it works: messages and progress bars on stderr.

Verbosity is process-wide: ``-q`` (quiet) silences messages and bars, ``-v`` adds detail.
Progress bars appear only when stderr is a terminal, so logs and CI output stay clean.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable, Iterator
from typing import TypeVar

from tqdm import tqdm

T = TypeVar("T")

QUIET, NORMAL, VERBOSE = -1, 0, 1
_level = NORMAL


def set_verbosity(level: int) -> None:
    global _level
    _level = max(QUIET, min(VERBOSE, int(level)))


def verbosity() -> int:
    return _level


def info(message: str) -> None:
    """A normal progress message (suppressed by ``-q``)."""
    if _level >= NORMAL:
        print(message, file=sys.stderr, flush=True)


def debug(message: str) -> None:
    """Detail shown only with ``-v``."""
    if _level >= VERBOSE:
        print(message, file=sys.stderr, flush=True)


def progress(iterable: Iterable[T], total: int | None = None, desc: str | None = None) -> Iterator[T]:
    """Wrap a long loop in a progress bar when stderr is a terminal and not ``-q``."""
    disable = _level <= QUIET or not sys.stderr.isatty()
    return iter(tqdm(iterable, total=total, desc=desc, disable=disable, leave=False, file=sys.stderr))
