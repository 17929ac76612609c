"""What native libraries print: OpenEXR, libpng and libjpeg (through OpenCV) write their complaints
about a corrupt file straight to file descriptor 2, around Python's ``sys.stderr``. Readers run the
library inside :func:`read_quietly` so that a bad file is said once, in the one-line error."""

from __future__ import annotations

import functools
import os
import sys
import tempfile
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TypeVar

from egorelight_cli.errors import EgorelightError

T = TypeVar("T")

#: the process's file descriptors 1 and 2 are redirected by one reader at a time
_REDIRECT_LOCK = threading.Lock()


@contextmanager
def native_output_captured() -> Iterator[dict[int, list[str]]]:
    """Collect what native code (OpenEXR, libpng via OpenCV) prints on file descriptors 1
    and 2 inside the block, ``{1: lines, 2: lines}``, instead of the user's terminal: a corrupt file
    is then said once, in the one-line error. One block at a time in the process (a lock)."""
    with _REDIRECT_LOCK:
        with _redirected() as captured:
            yield captured


@contextmanager
def _redirected() -> Iterator[dict[int, list[str]]]:
    captured: dict[int, list[str]] = {1: [], 2: []}
    streams = {1: sys.stdout, 2: sys.stderr}
    _flush_c_streams()
    for stream in streams.values():
        stream.flush()
    saved = {fd: os.dup(fd) for fd in streams}
    sinks = {fd: tempfile.TemporaryFile(mode="w+b") for fd in streams}
    try:
        for fd, sink in sinks.items():
            os.dup2(sink.fileno(), fd)
        yield captured
    finally:
        _flush_c_streams()  # what the library buffered (C stdio, which C++ iostreams write through)
        for fd, stream in streams.items():
            stream.flush()
            os.dup2(saved[fd], fd)
            os.close(saved[fd])
            sinks[fd].seek(0)
            text = sinks[fd].read().decode(errors="replace")
            sinks[fd].close()
            captured[fd] += [line for line in text.splitlines() if line.strip()]


@functools.lru_cache(maxsize=1)
def _libc():
    """The process's C library (ctypes), None where it cannot be found."""
    import ctypes

    try:
        return ctypes.CDLL(None)
    except OSError:
        return None


def _flush_c_streams() -> None:
    """``fflush(NULL)``: every C stdio stream of the process (a no-op where libc is not found)."""
    libc = _libc()
    if libc is not None and hasattr(libc, "fflush"):
        libc.fflush(None)


def read_quietly(path: Path, read: Callable[[], T], what: str) -> T:
    """``read()`` with native output captured: on failure a one-line EgorelightError naming
    ``path`` with the library's first complaint on stderr; on success what it printed (warnings)
    is printed as it was."""
    try:
        with native_output_captured() as captured:
            result = read()
    except Exception as exc:
        said = captured[2][0].split(": ", 1)[-1] if captured[2] else str(exc)
        raise EgorelightError(f"cannot read {what} ({said})", path) from None
    for fd, stream in ((1, sys.stdout), (2, sys.stderr)):
        for line in captured[fd]:
            print(line, file=stream)
    return result
