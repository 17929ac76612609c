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
from typing import IO, TypeVar

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
    _flush(streams.values())
    opened = _open_sinks(streams)
    if opened is None:  # a closed stdout/stderr or no room for the sinks: native output goes where it went
        yield captured
        return
    saved, sinks = opened
    try:
        for fd, sink in sinks.items():
            os.dup2(sink.fileno(), fd)
        yield captured
    finally:
        _flush_c_streams()  # what the library buffered (C stdio, which C++ iostreams write through)
        _flush(streams.values())
        for fd in streams:
            os.dup2(saved[fd], fd)
            os.close(saved[fd])
            sinks[fd].seek(0)
            text = sinks[fd].read().decode(errors="replace")
            sinks[fd].close()
            captured[fd] += [line for line in text.splitlines() if line.strip()]


def _flush(streams) -> None:
    """Flush Python's text streams (None where the process was started without one)."""
    for stream in streams:
        if stream is not None:
            stream.flush()


def _open_sinks(fds) -> tuple[dict[int, int], dict[int, IO[bytes]]] | None:
    """Per file descriptor of ``fds`` a duplicate (to restore it) and an anonymous temporary file
    (to catch what is written); None, with nothing left open, where either cannot be made."""
    saved: dict[int, int] = {}
    sinks: dict[int, IO[bytes]] = {}
    try:
        for fd in fds:  # a closed one: a file opened here would take its number
            os.fstat(fd)
        for fd in fds:
            saved[fd] = os.dup(fd)
            sinks[fd] = tempfile.TemporaryFile(mode="w+b")
    except OSError:
        for duplicate in saved.values():
            os.close(duplicate)
        for sink in sinks.values():
            sink.close()
        return None
    return saved, sinks


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
    captured: dict[int, list[str]] = {1: [], 2: []}
    try:
        with native_output_captured() as captured:
            result = read()
    except Exception as exc:
        said = captured[2][0].split(": ", 1)[-1] if captured[2] else str(exc)
        raise EgorelightError(f"cannot read {what} ({said})", path) from None
    for fd, stream in ((1, sys.stdout), (2, sys.stderr)):
        for line in captured[fd] if stream is not None else ():
            print(line, file=stream)
    return result
