"""The helper process of the perturbation rounds (jtet._helper_process): a run whose
attempts it shares returns exactly what a run without it returns, also when the helper
dies in the middle of a round."""

from __future__ import annotations

import gc
import os
import threading
import time
import warnings

import pytest
from helpers import shared_mesh_path

import jtet
from jtet import _config, _helper_process, _perturb


def _summary(r):
    """What must not depend on where the attempts ran: the mesh, and the history
    without its timings."""
    history = [{k: v for k, v in e.items() if k != "seconds"} for e in r.history]
    return r.mesh.points.tobytes(), r.mesh.tets.tobytes(), history


@pytest.fixture(scope="module")
def demo():
    return jtet.demo_mesh()


@pytest.fixture(scope="module")
def alone(demo):
    """The demo improved with every attempt run in this process."""
    return jtet.improve(demo, perturb=8)


def _wait_ready(h) -> None:
    deadline = time.monotonic() + 120
    while not h.is_ready and h.alive and time.monotonic() < deadline:
        time.sleep(0.05)
    assert h.is_ready, "the helper did not load within 2 minutes"


@pytest.fixture
def helper(monkeypatch, demo):
    """A helper process, loaded and idle; closed afterwards."""
    if _config.CACHE_DIR is None or _config.WORKERS < 2:
        pytest.skip("the helper needs the compilation cache and two threads")
    monkeypatch.setenv("JTET_HELPER", "1")
    monkeypatch.setattr(_helper_process, "_shared", None)
    monkeypatch.setattr(_helper_process, "_failed", False)
    h = _helper_process.start(jtet.Options())
    assert h is not None and h.alive
    _wait_ready(h)
    yield h
    h.close()


def test_attempts_in_the_helper_give_the_same_run(demo, alone, helper):
    shared = jtet.improve(demo, perturb=8)
    assert helper.done > 0, "the helper ran no attempt"
    assert _summary(shared) == _summary(alone)
    assert not helper.proc.poll(), "the helper stays for the next run"


def test_places_shared_with_the_helper_give_the_same_run(helper, monkeypatch):
    """Rounds with several places (the holeplate, seed 0, places at any size): the helper
    and this process each start places the other has not, and the run is the one
    without a helper."""
    monkeypatch.setattr(_perturb, "PLACES_MIN_TETS", 0)
    mesh = jtet.load(shared_mesh_path("gmsh_holeplate.vtu"))
    monkeypatch.setattr(_helper_process, "_shared", None)
    alone = jtet.improve(mesh, seed=0)
    monkeypatch.setattr(_helper_process, "_shared", helper)
    shared = jtet.improve(mesh, seed=0)
    kept = [e["round"] for e in alone.history if e["op"] == "perturb" and e["successes"]]
    assert len(kept) > len(set(kept)), "no round kept two places"
    assert helper.done > 0, "the helper ran no attempt"
    assert _summary(shared) == _summary(alone)


def _kill_at_third_attempt(helper, monkeypatch):
    """Kill the helper when this process starts its third attempt (by then the helper
    runs one)."""
    attempt = _perturb.RoundState.attempt
    calls = []

    def kill_then_attempt(self, *args, **kwargs):
        calls.append(1)
        if len(calls) == 3:
            helper.proc.kill()
        return attempt(self, *args, **kwargs)

    monkeypatch.setattr(_perturb.RoundState, "attempt", kill_then_attempt)


def test_a_helper_that_dies_while_sharing_places_changes_nothing(helper, monkeypatch):
    monkeypatch.setattr(_perturb, "PLACES_MIN_TETS", 0)
    mesh = jtet.load(shared_mesh_path("gmsh_holeplate.vtu"))
    monkeypatch.setattr(_helper_process, "_shared", None)
    alone = jtet.improve(mesh, seed=0)
    monkeypatch.setattr(_helper_process, "_shared", helper)
    _kill_at_third_attempt(helper, monkeypatch)
    assert _summary(jtet.improve(mesh, seed=0)) == _summary(alone)
    helper.proc.wait(timeout=10)


def test_a_helper_that_dies_in_a_round_changes_nothing(demo, alone, helper, monkeypatch):
    _kill_at_third_attempt(helper, monkeypatch)
    r = jtet.improve(demo, perturb=8)
    assert _summary(r) == _summary(alone)
    helper.proc.wait(timeout=10)
    deadline = time.monotonic() + 10
    while helper.alive and time.monotonic() < deadline:  # the reader sees the pipe end
        time.sleep(0.05)
    assert not helper.alive
    # and no other helper is started after one failed
    assert _helper_process.running() is None
    assert _helper_process.start(jtet.Options()) is None


def test_the_helper_imports_this_jtet_from_any_working_directory(monkeypatch, tmp_path):
    """Started from a directory holding another ``jtet`` (a checkout of another
    version), the helper still imports the optimizer's and gets ready."""
    if _config.CACHE_DIR is None or _config.WORKERS < 2:
        pytest.skip("the helper needs the compilation cache and two threads")
    (tmp_path / "jtet").mkdir()
    (tmp_path / "jtet" / "__init__.py").write_text("raise ImportError('another jtet')\n")
    monkeypatch.chdir(tmp_path)
    h = _helper_process.Helper(jtet.Options())
    try:
        _wait_ready(h)
    finally:
        h.close()


def test_ladder_claims_in_order_until_closed():
    ladder = _helper_process.Ladder(0, 3)
    assert [ladder.claim(), ladder.claim()] == [0, 1]
    ladder.close()
    assert ladder.claim() is None  # a kept attempt ended the round


def test_round_claims_needed_attempts_first_then_speculative_ones():
    """Needed attempts (a place's first; the next of a place whose outcomes all failed
    and none runs) come first, from the last place (the helper) or the first (the
    optimizer); then the next of a place whose running attempt may still fail, first
    place first; none of a place whose outcome looks kept, or that is judged."""
    r = _helper_process.Round(0, ["a", "b", "c"], [None] * 4, lambda place, o: o == "kept")
    assert r.ladders[0].claim() == 0  # the optimizer judges place 0, attempt 0 runs
    assert [r.claim(from_last=True), r.claim(from_last=False)] == [(3, 0), (1, 0)]
    r.put((3, 0), "failed")
    r.put((1, 0), "kept")
    # place 3 failed and runs nothing: its next is needed; place 2 was never started
    assert [r.claim(from_last=True), r.claim(from_last=True)] == [(3, 1), (2, 0)]
    # only speculative ones are left: places 0, 2, 3 run one each (1 looks kept)
    assert [r.claim(from_last=True), r.claim(from_last=False)] == [(0, 1), (0, 2)]
    assert r.claim(from_last=False) == (2, 1)
    r.ladders[2].close()  # judged
    assert r.claim(from_last=False) == (3, 2)
    assert r.claim(from_last=False) is None  # out of attempts
    r.close()
    assert r.ladders[1].outcomes == {0: "kept"}
    assert r.ladders[3].keys_before(5) == frozenset()  # the outcomes had no kicks


def test_ladder_wait_returns_the_outcome_or_gives_up_on_a_dead_helper():
    class Dead:
        alive = False

    class Alive:
        alive = True

    ladder = _helper_process.Ladder(1, 2)
    assert not ladder.wait(0, None)  # no helper runs it: the caller must
    assert not ladder.wait(0, Dead())
    threading.Timer(0.1, ladder.put, (1, "outcome")).start()
    assert ladder.wait(1, Alive())
    assert ladder.outcomes[1] == "outcome"


def test_helper_is_off_without_cache_threads_or_consent(monkeypatch):
    monkeypatch.setenv("JTET_HELPER", "1")
    monkeypatch.setattr(_config, "WORKERS", 1)
    assert not _helper_process.enabled()
    monkeypatch.setattr(_config, "WORKERS", 2)
    monkeypatch.setattr(_config, "CACHE_DIR", None)
    assert not _helper_process.enabled()
    monkeypatch.setattr(_config, "CACHE_DIR", "/tmp")
    monkeypatch.setenv("JTET_HELPER", "0")
    assert not _helper_process.enabled()
    monkeypatch.setenv("JTET_HELPER", "1")
    assert _helper_process.enabled() == (os.name == "posix")


_WRITE_TO_A_DEAD_HELPER = """
import signal, threading
import jtet
from jtet import _helper_process
# what gmsh.initialize() does to the process (measured): SIGPIPE back to its default,
# under which a write to a closed pipe ends the process instead of raising
signal.signal(signal.SIGPIPE, signal.SIG_DFL)
h = _helper_process.Helper(jtet.Options())
h.proc.kill()
h.proc.wait()
h._post(("warm", jtet.Options()))  # the writer thread meets the closed pipe
writer = next(t for t in threading.enumerate() if t.name == "jtet-helper-out")
writer.join(timeout=30)
print("writing" if writer.is_alive() else "dropped" if not h.alive else "alive")
"""


def test_a_write_to_a_dead_helper_does_not_end_the_process():
    """Under SIGPIPE's default action (gmsh.initialize sets it) the optimizer's writes
    to a helper that died must fail like any OSError, not kill the optimizer."""
    import subprocess
    import sys

    env = dict(os.environ, JTET_HELPER="1")
    done = subprocess.run(
        [sys.executable, "-c", _WRITE_TO_A_DEAD_HELPER],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, f"the process ended with {done.returncode}: {done.stderr}"
    assert done.stdout.strip() == "dropped"


# JAX warns that a fork of its threaded process may deadlock; the child here runs no
# JAX and leaves through os._exit
@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")
def test_a_forked_child_leaves_the_helper_to_its_parent(monkeypatch):
    """A child forked after the helper started (multiprocessing's default on Linux) has
    none of the threads that talk to it: it must not use it, nor kill it at its exit."""
    monkeypatch.setattr(_helper_process, "_shared", None)
    h = _helper_process.Helper(jtet.Options())
    monkeypatch.setattr(_helper_process, "_shared", h)
    try:
        with warnings.catch_warnings(record=True) as caught:
            # the CLI shows every warning once ("default"): ResourceWarnings too
            warnings.simplefilter("always")
            pid = os.fork()
            if pid == 0:  # the child: report through the exit status only
                ok = _helper_process.running() is None and not _helper_process._lock.locked()
                gc.collect()
                # the inherited Popen object is kept: dropped, it warned "subprocess ...
                # is still running", which the CLI printed at each read in a child
                ok &= not [w for w in caught if issubclass(w.category, ResourceWarning)]
                h.close()  # what its atexit would do
                os._exit(0 if ok else 1)
        _, status = os.waitpid(pid, 0)
        assert os.waitstatus_to_exitcode(status) == 0
        assert h.proc.poll() is None, "the child killed its parent's helper"
        assert _helper_process.running() is h
    finally:
        h.close()
