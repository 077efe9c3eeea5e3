"""Ctrl-C that cannot be lost.

Python raises KeyboardInterrupt wherever the main thread is; where that is a
garbage-collection callback (JAX registers one), the exception is printed and swallowed,
and a run went on to the end as if nothing happened (seen in CI, while the input was read
and, later, while jtet itself was still being imported). So jtet counts the signals:
``install()`` (at jtet's import, before JAX's) replaces Python's default SIGINT handler
with one that behaves the same (it raises KeyboardInterrupt) and also counts the signal;
``catch_ctrl_c()`` marks a stretch of work (the CLI wraps a whole command, ``improve`` its
own run) and ``pressed()`` tells the optimizer's loop, which checks it between
operations, whether a signal arrived in it. Nested uses share the outermost one. A
user's own handler, and calls from other threads, are left alone.
"""

from __future__ import annotations

import contextlib
import signal
import threading

_count = 0  # SIGINTs this process's jtet handler has seen
_since = 0  # the count a signal must exceed to be "pressed" in the current stretch
_depth = 0  # nesting depth of catch_ctrl_c() on the main thread


def _handler(signum, frame):
    global _count
    _count += 1
    raise KeyboardInterrupt


def _ours(handler) -> bool:
    return handler is signal.default_int_handler or handler is _handler


def install() -> None:
    """Count SIGINTs from now on, where Python's default handler is in place (main
    thread only; another handler, e.g. a user's or IPython's, is left alone)."""
    if threading.current_thread() is threading.main_thread() and (
        signal.getsignal(signal.SIGINT) is signal.default_int_handler
    ):
        signal.signal(signal.SIGINT, _handler)


def pressed() -> bool:
    """Whether Ctrl-C arrived during the outermost ``catch_ctrl_c()`` (and, if it was
    entered with ``earlier=True``, since the previous one ended or jtet was imported)."""
    return _count > _since


@contextlib.contextmanager
def catch_ctrl_c(earlier: bool = False):
    """Count Ctrl-C during the block (see the module docstring). ``earlier=True`` (the
    CLI, which has nothing before it to protect): a signal since the previous block
    ended, or since jtet's import, counts too. Otherwise only signals from now on count:
    a Ctrl-C that stopped one ``improve()`` must not stop the next one at once."""
    global _since, _depth
    main = threading.current_thread() is threading.main_thread()
    if not main or not _ours(signal.getsignal(signal.SIGINT)):
        yield  # not the main thread, or a user's handler: leave it alone
        return
    if _depth:
        _depth += 1  # nested: the outermost block's record
        try:
            yield
        finally:
            _depth -= 1
        return
    previous = signal.signal(signal.SIGINT, _handler)
    if not earlier:
        _since = _count
    _depth = 1
    try:
        yield
    finally:
        _depth = 0
        signal.signal(signal.SIGINT, previous)
        _since = _count  # the record never outlives the block that read it
