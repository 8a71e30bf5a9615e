"""Ctrl-C that is never lost: the sweeping process records a ``SIGINT`` and acts on it at known points.

Python runs a signal handler wherever the main thread happens to be, and an exception raised in
some places is dropped ("Exception ignored in ..."): an ``os.fork`` callback (``logging``'s
``_releaseLock``, registered with ``os.register_at_fork``), a ``__del__`` method, a weakref
callback. A Ctrl-C that landed in one of them vanished, and a study interrupted while forking a
runner ran on to its end and exited 0 (CI at 81cf288).

Inside :func:`guarded` the ``SIGINT`` handler records the interrupt (the time it came) and raises
:class:`KeyboardInterrupt` only inside an :func:`interruptible` block (a wait for the job
runners, for a lock); everywhere else the code raises it at the next :func:`check` (before each
job is sent, after each wait, before each batch of trials), so it is never raised half-way
through a write to the study's database either. A recorded interrupt nobody checked is raised
when the outermost :func:`guarded` block ends without an exception.

A forked child calls :func:`in_child` first: its ``SIGINT`` handling is what it was before the
guard (Python's default raises :class:`KeyboardInterrupt`), and an interrupt that reached it
between the fork and that call is raised there. :data:`INTERRUPTED_EXIT` is the exit code a
runner stopped by Ctrl-C ends with.

Only the main thread installs the handler (Python allows no other), and only over Python's
default one: a process started with ``SIGINT`` ignored (``nohup``, a background job of a
non-interactive shell) or with its own handler keeps it, as before.
"""

from __future__ import annotations

import signal
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from types import FrameType
from typing import Any

__all__ = ["INTERRUPTED_EXIT", "check", "guarded", "in_child", "interruptible", "pending"]

#: Exit code of a runner stopped by Ctrl-C: 128 + ``SIGINT``, as a POSIX shell reports a process
#: ended by that signal.
INTERRUPTED_EXIT = 128 + int(signal.SIGINT)


class _State:
    """The process's one guard: nesting depth, the handler it replaced, the interrupt recorded
    (``time.monotonic()`` when it came, None when none) and the depth of interruptible blocks."""

    def __init__(self) -> None:
        self.depth = 0
        self.previous: Any = None
        self.at: float | None = None
        self.raising = 0


_state = _State()


def _handler(signum: int, frame: FrameType | None) -> None:
    if _state.at is None:
        _state.at = time.monotonic()
    if _state.raising:
        raise KeyboardInterrupt


def pending() -> float | None:
    """When (``time.monotonic()``) a Ctrl-C came that the guarded code has not ended on; None."""
    return _state.at


def check() -> None:
    """Raise :class:`KeyboardInterrupt` when a Ctrl-C was recorded (it stays recorded until the
    outermost :func:`guarded` block ends, so every later check raises too)."""
    if _state.at is not None:
        raise KeyboardInterrupt


@contextmanager
def guarded() -> Iterator[None]:
    """Record ``SIGINT`` within the block (module docstring); nested blocks share the outermost's
    handler. Leaving the block without an exception raises a recorded interrupt; the handler
    before the outermost block is restored and the record cleared."""
    if _state.depth == 0:
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        previous = signal.getsignal(signal.SIGINT)
        if previous is not signal.default_int_handler:  # ignored, or someone else's: left alone
            yield
            return
        _state.previous, _state.at, _state.raising = previous, None, 0
        signal.signal(signal.SIGINT, _handler)
    _state.depth += 1
    try:
        yield
    except BaseException:
        _leave()
        raise
    if _leave() is not None:
        raise KeyboardInterrupt


def _leave() -> float | None:
    """One guarded block less; the outermost restores the handler first, then clears the record
    (a Ctrl-C between the two is still this block's). The record, as it was."""
    _state.depth -= 1
    at = _state.at
    if _state.depth == 0:
        signal.signal(signal.SIGINT, _state.previous)
        at = _state.at
        _state.previous, _state.at, _state.raising = None, None, 0
    return at


@contextmanager
def interruptible() -> Iterator[None]:
    """A block (a blocking wait) in which a Ctrl-C raises :class:`KeyboardInterrupt` at once;
    one recorded before it raises on entry."""
    check()
    _state.raising += 1
    try:
        yield
    finally:
        _state.raising -= 1


def in_child() -> None:
    """In a child forked inside :func:`guarded`: ``SIGINT`` handled as before the guard; a
    Ctrl-C recorded since the fork (or in the fork's own callbacks) raised here."""
    if _state.depth == 0:
        return
    signal.signal(signal.SIGINT, _state.previous)
    at = _state.at
    _state.depth, _state.previous, _state.at, _state.raising = 0, None, None, 0
    if at is not None:
        raise KeyboardInterrupt
