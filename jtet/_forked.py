"""Work run in a forked child process: what a C++ library does to its process there (a
segmentation fault, an abort, a change of working directory, a resource limit) stays in
the child, and the caller gets a result or an exception."""

from __future__ import annotations

import os
import pickle
import signal
import sys
import warnings
from collections.abc import Callable


def can_fork() -> bool:
    """Whether ``call_in_child`` may be used here: Linux, where forking a process whose
    other threads (JAX's) hold no lock the child needs is safe for such work. Elsewhere
    the caller does the work in its own process."""
    return hasattr(os, "fork") and sys.platform.startswith("linux")


def call_in_child(work: Callable[[], object], crashed: Callable[[str], BaseException]):
    """``work()`` run in a forked child of this process; its return value comes back
    pickled over a pipe. An exception it raises is raised here, and so are the warnings
    it gave. A child that dies without an answer raises ``crashed(how)`` here (``how``:
    "crashed", "crashed with SIGSEGV", ...). The child's standard error goes to
    /dev/null (a crash's dump is noise: ``crashed`` says why in one line)."""
    read_end, write_end = os.pipe()
    with warnings.catch_warnings():
        # JAX warns at every fork once its threads run; the child runs no JAX
        warnings.simplefilter("ignore", RuntimeWarning)
        pid = os.fork()
    if pid == 0:  # the child: work, send (status, value, warnings), exit
        os.close(read_end)
        try:
            import faulthandler

            faulthandler.disable()
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 2)
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                value = work()
            out = ("ok", value, [(str(w.message), w.category) for w in caught])
        except BaseException as e:
            out = ("error", e, [])
        try:
            payload = pickle.dumps(out, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as e:
            payload = pickle.dumps(("error", crashed(f"failed ({type(e).__name__}: {e})"), []))
        with os.fdopen(write_end, "wb") as f:
            f.write(payload)
        os._exit(0)
    os.close(write_end)
    try:
        with os.fdopen(read_end, "rb") as f:
            payload = f.read()
    finally:
        _, status = os.waitpid(pid, 0)
    if not payload:
        how = "crashed"
        if os.WIFSIGNALED(status):
            how += f" with {signal.Signals(os.WTERMSIG(status)).name}"
        raise crashed(how)
    kind, value, caught = pickle.loads(payload)
    for message, category in caught:
        warnings.warn(message, category, stacklevel=4)
    if kind == "error":
        raise value
    return value
