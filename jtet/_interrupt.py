"""Ctrl-C that cannot be lost.

Python raises KeyboardInterrupt wherever the main thread is; where that is a
garbage-collection callback (JAX registers one), the exception is printed and swallowed,
and a run went on to the end as if nothing happened (seen in CI). ``catch_ctrl_c()``
replaces Python's default SIGINT handler with one that still raises but also records the
signal; ``pressed()`` tells the optimizer's loop, which checks it between operations.
Nested uses share the outermost handler and its record (the CLI wraps a whole command,
``improve`` its own run). A user's own handler, and calls from other threads, are left
alone.
"""

from __future__ import annotations

import contextlib
import signal
import threading

_pressed = False


def _handler(signum, frame):
    global _pressed
    _pressed = True
    raise KeyboardInterrupt


def pressed() -> bool:
    """Whether Ctrl-C arrived since the outermost ``catch_ctrl_c()`` began."""
    return _pressed


@contextlib.contextmanager
def catch_ctrl_c():
    global _pressed
    if (
        threading.current_thread() is not threading.main_thread()
        or signal.getsignal(signal.SIGINT) is not signal.default_int_handler
    ):
        yield  # nested (our handler is in place), a user's handler, or not the main thread
        return
    _pressed = False
    previous = signal.signal(signal.SIGINT, _handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _pressed = False  # the record never outlives the handler that made it
