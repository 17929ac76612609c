"""How the tool reacts to SIGINT (Ctrl-C) and SIGTERM (a scheduler's kill, ``timeout``).

Both unwind the stack as an exception, so every ``with ArtifactWriter`` block discards its
temporary work and the CLI ends with one line: SIGINT raises ``KeyboardInterrupt`` (Python's
default; it leaves a command as :class:`Interrupted`), SIGTERM raises :class:`Terminated` once
:func:`terminate_as_exception` is in place (the CLI's ``main`` does it). The few renames that swap a finished artifact into place run under
:func:`signals_deferred`, so neither signal can stop them half-way; only SIGKILL or a power cut
can, and the next writer of that output repairs what they leave
(:func:`~egorelight_cli.atomic_output.remove_stale_temporaries`).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

#: the signals deferred by :func:`signals_deferred`
INTERRUPTS = (signal.SIGINT, signal.SIGTERM)


class Terminated(BaseException):
    """The process received SIGTERM (a BaseException, like KeyboardInterrupt: ``except Exception``
    clauses let it pass)."""


class Interrupted(BaseException):
    """Ctrl-C inside a command: the ``KeyboardInterrupt`` renamed on its way out of the command, so
    that click passes it on instead of printing an empty line and raising its ``Abort``."""


def _raise_terminated(signum, frame) -> None:
    raise Terminated()


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextmanager
def terminate_as_exception() -> Iterator[None]:
    """Within the block SIGTERM raises :class:`Terminated`; the previous handler is restored after.
    A no-op outside the main thread (Python handles signals there only)."""
    if not _in_main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@contextmanager
def signals_deferred() -> Iterator[None]:
    """SIGINT and SIGTERM arriving within the block are held and delivered, to the handlers the
    process had, as soon as it ends (a no-op outside the main thread)."""
    if not _in_main_thread():
        yield
        return
    caught: list[int] = []

    def hold(signum, frame) -> None:
        caught.append(signum)

    previous: dict[int, Callable | int | None] = {s: signal.signal(s, hold) for s in INTERRUPTS}
    try:
        yield
    finally:
        for signum, handler in previous.items():  # None: a handler set from C, which Python cannot reinstate
            signal.signal(signum, handler if handler is not None else signal.SIG_DFL)
        if caught:
            signal.raise_signal(caught[0])
