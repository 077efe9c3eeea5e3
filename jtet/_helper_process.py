"""A second Python process that runs perturbation attempts beside the optimizer's own.

A perturbation round (``_perturb``) tries kicks one after the other, each from the same
submesh, until one is kept. Until then its attempts are independent, so two can run at
once: the optimizer's process runs one, this helper the next, and the optimizer judges
the outcomes in the round's order, exactly as if it had run them all itself (the same
output, bit for bit). On a large mesh a round has several places, each with its own
kicks, and the two processes work on different places where they can (``Round``). An
attempt is many small NumPy calls on a ~300-5000-tet submesh that hold the GIL: two
improve() calls on threads ran 1.1x as fast as one after the other, so the second core
needs a second process.

The helper is started by the first run whose perturbation rounds last ``START_AFTER``
seconds (short ones never pay its ~3 s of CPU to import jtet and load the kernels), only
when the persistent compilation cache is on (it loads the kernels the run compiled;
without the cache it would compile them all again) and jtet may use more than one
thread (``JTET_THREADS``; ``JTET_HELPER=0`` turns it off). It stays for later runs of
the process and ends with it (or when its pipe closes). Messages are pickled over its
stdin / stdout; a helper that fails or dies is dropped and its attempt run here. A
child forked from the optimizer's process leaves the helper to its parent.
"""

from __future__ import annotations

import atexit
import os
import pickle
import queue
import socket
import struct
import subprocess
import sys
import threading
import time

# Seconds of perturbation rounds after which a run starts the helper.
START_AFTER = 1.0

_HEADER = struct.Struct("<Q")
# Sends to the helper must not raise SIGPIPE: Python ignores it, but C libraries may
# restore its default action (gmsh.initialize() does), under which a write to a helper
# that died ends the whole process. Blocking the signal on the writing thread does not
# help (Linux sends it to the process); a socket send with this flag fails with EPIPE.
_NO_SIGPIPE = getattr(socket, "MSG_NOSIGNAL", 0)
_shared: Helper | None = None
_lock = threading.Lock()
# a helper ended on its own (crashed, killed): the process starts no other one
_failed = False


def enabled() -> bool:
    """Whether this process may start a helper (see the module docstring)."""
    from . import _config

    return (
        os.name == "posix"
        and _config.CACHE_DIR is not None
        and _config.WORKERS > 1
        and os.environ.get("JTET_HELPER", "1") != "0"
    )


def running() -> Helper | None:
    """The process's helper if one was started (ready or still loading), else None."""
    return _shared if _shared is not None and _shared.alive else None


def start(opts) -> Helper | None:
    """The process's helper, started now if there is none (None if not ``enabled`` or
    one failed before). Returns at once: the helper claims attempts once it has loaded
    jtet and the kernels of ``opts``."""
    global _shared
    with _lock:
        if _shared is not None and _shared.alive:
            return _shared
        if _failed or not enabled():
            return None
        try:
            _shared = Helper(opts)
        except OSError:
            return None
        return _shared


# the parent's helper processes, as forked children inherited them: kept referenced, as
# a ``Popen`` object that is dropped while its process runs warns "subprocess ... is
# still running" (the CLI printed it at each read in a forked child after a run)
_parents_helpers: list = []


def _leave_to_parent() -> None:
    """In a forked child: the parent's helper answers the parent's threads, none of which
    came along. The child forgets it (and must not kill it at exit) and may start its own."""
    global _shared, _lock
    if _shared is not None:
        _shared.alive = False
        _parents_helpers.append(_shared.proc)
        _shared.proc = None  # close() at the child's exit leaves the process alone
        _shared = None
    _lock = threading.Lock()  # it may have been held by a thread that did not come along


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_leave_to_parent)


def _pack(obj) -> bytes:
    """A message as its length and pickle."""
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    return _HEADER.pack(len(data)) + data


def _send(stream, obj) -> None:
    stream.write(_pack(obj))
    stream.flush()


def _receive(stream):
    """The next message, or None at the end of the stream."""
    head = stream.read(_HEADER.size)
    if len(head) < _HEADER.size:
        return None
    (size,) = _HEADER.unpack(head)
    data = stream.read(size)
    if len(data) < size:
        return None
    return pickle.loads(data)


class Ladder:
    """The ``n`` attempts of one place of round ``round_id`` (unique in the process),
    claimed in order by the optimizer and the helper, and their outcomes (shared by the
    optimizer's thread and the helper's reader thread)."""

    def __init__(self, round_id, n: int):
        self.round_id, self.n, self.next, self.closed = round_id, n, 0, False
        self.outcomes: dict = {}  # index -> outcome (None: the helper failed it)
        # index -> the kick's change (``Outcome.key``) of every outcome so far, judged
        # or not: a later attempt whose kick repeats one is judged without its climb
        self.keys: dict = {}
        self.finished = 0  # outcomes put so far
        self.kept = False  # an outcome so far looks kept (``Round``'s ``kept`` test)
        self.cond = threading.Condition()

    def claim(self, needed_only: bool = False, unless_kept: bool = False) -> int | None:
        """The next attempt nobody has started, or None. ``needed_only``: only if it
        will be judged unless a running one is kept, i.e. none runs and none so far
        looks kept; ``unless_kept``: only if none so far looks kept."""
        with self.cond:
            if self.closed or self.next >= self.n or ((needed_only or unless_kept) and self.kept):
                return None
            if needed_only and self.finished < self.next:
                return None
            self.next += 1
            return self.next - 1

    def put(self, index: int, outcome, kept: bool = False) -> None:
        with self.cond:
            self.outcomes[index] = outcome
            self.finished += 1
            self.kept |= kept
            key = getattr(outcome, "key", None)
            if key is not None:
                self.keys[index] = key
            self.cond.notify_all()

    def keys_before(self, index: int) -> frozenset:
        """The kicks' changes of the attempts before ``index`` known so far."""
        with self.cond:
            return frozenset(k for i, k in self.keys.items() if i < index)

    def wait(self, index: int, helper: Helper | None) -> bool:
        """Wait until attempt ``index`` has an outcome; False if the helper that runs it
        ended first."""
        with self.cond:
            while index not in self.outcomes:
                if helper is None or not helper.alive:
                    return False
                self.cond.wait(timeout=0.2)
            return True

    def close(self) -> None:
        """The place is judged: nobody claims its attempts any more."""
        with self.cond:
            self.closed = True


class Round:
    """A perturbation round's places (``_perturb._round``): each has its ``RoundState``
    and its ``Ladder`` of the same ``attempts``; ``kept(place, outcome)`` tells whether
    an outcome would be kept (a guess: the optimizer also checks that it splices back).

    The places share no vertex and are judged apart, so an attempt of any place may run
    at any time, and the optimizer judges the places one after the other. A process
    that would wait or idle first takes a needed attempt (``Ladder.claim``
    ``needed_only``: a place's first, or the next of a place whose outcomes so far all
    failed and none runs), the helper from the last place back and the optimizer from
    the first place on; only then the next attempt of a place whose running attempt may
    still fail, first place first."""

    def __init__(self, round_id, attempts: list, states: list, kept=None):
        self.round_id, self.attempts, self.states = round_id, attempts, states
        self.ladders = [Ladder((round_id, i), len(attempts)) for i in range(len(states))]
        self.kept = kept or (lambda place, outcome: False)

    def claim(self, from_last: bool) -> tuple[int, int] | None:
        """(place, index) of an attempt for a process to run (see the class), or None."""
        places = range(len(self.ladders))
        for place in reversed(places) if from_last else places:
            index = self.ladders[place].claim(needed_only=True)
            if index is not None:
                return place, index
        for place in places:
            index = self.ladders[place].claim(unless_kept=True)
            if index is not None:
                return place, index
        return None

    def put(self, claim: tuple[int, int], outcome) -> None:
        place, index = claim
        kept = outcome is not None and self.kept(place, outcome)
        self.ladders[place].put(index, outcome, kept)

    def close(self) -> None:
        """The round is over: nobody claims anything more."""
        for ladder in self.ladders:
            ladder.close()

    def wake(self) -> None:
        """Wake whoever waits on an outcome (the helper ended)."""
        for ladder in self.ladders:
            with ladder.cond:
                ladder.cond.notify_all()


class Helper:
    """The helper process, seen from the optimizer: ``serve`` hands it a ``Round``; it
    then claims attempts of its places (``Round.claim``) until none is left, and
    their outcomes land in the places' ladders."""

    def __init__(self, opts):
        env = dict(os.environ)
        # the helper imports jtet from where this process did
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        env["PYTHONPATH"] = os.pathsep.join(filter(None, [root, env.get("PYTHONPATH")]))
        # its stdin is a socket, not a pipe, for sends that cannot raise SIGPIPE
        self._to_helper, theirs = socket.socketpair()
        if hasattr(socket, "SO_NOSIGPIPE"):  # the BSDs' and macOS's form of the flag
            self._to_helper.setsockopt(socket.SOL_SOCKET, socket.SO_NOSIGPIPE, 1)
        with theirs:
            self.proc = subprocess.Popen(
                # -P: not the working directory first on its path, whose own ``jtet``
                # (another checkout) would answer this one's messages
                [sys.executable, "-P", "-m", "jtet._helper_process"],
                stdin=theirs,
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                env=env,
                start_new_session=True,  # Ctrl-C in a terminal reaches the optimizer only
            )
        self.alive = True
        self._closing = False
        self.is_ready = False
        self.done = 0  # attempts it ran
        self._round = None  # the Round being served
        self._lock = threading.Lock()  # guards _round and is_ready
        # messages go out on a thread of their own: a round's state is larger than a pipe
        # buffer, and the helper reads only between attempts
        self._outbox: queue.Queue = queue.Queue()
        atexit.register(self.close)
        self._post(("warm", opts))
        threading.Thread(target=self._read, daemon=True, name="jtet-helper-in").start()
        threading.Thread(target=self._write, daemon=True, name="jtet-helper-out").start()

    def serve(self, round_: Round) -> None:
        """Let the helper claim attempts of ``round_``'s places."""
        with self._lock:
            self._round = round_
            if self.is_ready:
                self._post_round()

    def _post_round(self) -> None:
        r = self._round
        self._post(("round", r.round_id, [s.for_pipe() for s in r.states], r.attempts))

    def _read(self) -> None:
        """Reader thread: answers the helper's claims, files its outcomes."""
        try:
            while (msg := _receive(self.proc.stdout)) is not None:
                self._handle(msg)
        except Exception:  # noqa: BLE001  (a broken pipe ends the helper like EOF)
            pass
        if not self._closing:  # it ended on its own
            global _failed
            _failed = True
        self.alive = False
        current = self._round
        if current is not None:  # wake an optimizer waiting for an outcome
            current.wake()

    def _handle(self, msg) -> None:
        kind = msg[0]
        with self._lock:
            if kind == "ready":
                self.is_ready = True
                if self._round is not None:
                    self._post_round()
                return
            current = self._round
            if current is None or current.round_id != msg[1]:
                if kind == "claim":  # a round that ended: nothing to claim
                    self._post(("index", msg[1], None))
                return
            if kind == "claim":
                claim = current.claim(from_last=True)
                known = None if claim is None else current.ladders[claim[0]].keys_before(claim[1])
                self._post(("index", msg[1], claim, known))
                return
        # ("result" | "error", round, (place, index), outcome | message)
        self.done += kind == "result"
        current.put(msg[2], msg[3] if kind == "result" else None)

    def _post(self, msg) -> None:
        self._outbox.put(msg)

    def _write(self) -> None:
        """Writer thread: sends the outbox in order; None closes the helper's stdin."""
        try:
            while (msg := self._outbox.get()) is not None:
                self._to_helper.sendall(_pack(msg), _NO_SIGPIPE)
            self._to_helper.close()  # EOF: the helper's loop ends
        except (OSError, ValueError):
            self.alive = False

    def close(self) -> None:
        """End the helper (at exit): it holds nothing worth waiting for."""
        self._closing = True
        self.alive = False
        proc = getattr(self, "proc", None)
        if proc is None or proc.poll() is not None:
            return
        self._outbox.put(None)
        proc.kill()
        proc.wait()


def _serve(inp, out) -> None:
    """The helper's loop: warm the kernels, then run the attempts it claims."""
    from ._perturb import RoundState

    round_id = attempts = None
    # the round's places as sent, those started here, the kicks' changes run here
    piped, states, keys = [], {}, {}
    while (msg := _receive(inp)) is not None:
        kind = msg[0]
        if kind == "warm":
            _warm(msg[1])
            _send(out, ("ready",))
            continue
        if kind == "round":
            _, round_id, piped, attempts = msg
            states, keys, received = {}, {}, time.perf_counter()
        elif kind == "index":
            if msg[1] != round_id or msg[2] is None:
                continue  # nothing left: idle until the next round
            place, index = claim = msg[2]
            # the kicks tried before this one, here or in the optimizer: a repeat is
            # judged without its climb (``_perturb._judge_round``)
            mine = {k for (p, i), k in keys.items() if p == place and i < index}
            try:
                if place not in states:
                    states[place] = RoundState.start(piped[place], received)
                outcome = states[place].attempt(attempts[index], msg[3] | mine)
                if outcome.key is not None:
                    keys[claim] = outcome.key
                outcome = outcome.for_pipe()
                _send(out, ("result", round_id, claim, outcome))
            except Exception as e:  # noqa: BLE001  (the optimizer runs it itself)
                _send(out, ("error", round_id, claim, repr(e)))
        _send(out, ("claim", round_id))


def _warm(opts) -> None:
    """Load (or compile) the kernels an attempt calls."""
    from ._aot import prefetch
    from ._driver import _pass_kernel_specs
    from ._quality import prefetch_kernels, warm_start_kernels

    specs = _pass_kernel_specs(opts)
    warm_start_kernels({spec[:2] for spec in specs})
    prefetch_kernels()
    prefetch(specs)


if __name__ == "__main__":
    # the protocol owns the original stdout; anything printed goes to stderr
    _out = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    _serve(sys.stdin.buffer, _out)
