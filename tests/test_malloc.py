"""jtet._malloc: freed memory stays in the heap during a run and goes back after it,
measured as the process's resident memory (/proc/self/statm), not taken on trust."""

from __future__ import annotations

import numpy as np
import pytest

import jtet
from jtet import _malloc


def _resident_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


@pytest.fixture
def kept(monkeypatch):
    monkeypatch.delenv("JTET_MALLOC", raising=False)
    if not _malloc.keep_freed_memory():
        pytest.skip("needs glibc on Linux")


def test_freed_arrays_stay_until_released(kept):
    """Eight 16 MB arrays (under the 32 MB mmap threshold: heap memory), written to and
    freed: their 128 MB stay resident, and the release hands them back. Without the
    settings glibc trims the heap's top once 2x its mmap threshold (<= 64 MB) is free.
    Margins of 100 of 128 MB leave room for other threads' allocations."""
    _malloc.release_freed_memory()
    base = _resident_mb()
    arrays = [np.ones(2 << 20) for _ in range(8)]  # 8 x 2M float64 = 8 x 16 MB
    assert _resident_mb() - base > 100
    del arrays
    assert _resident_mb() - base > 100, "freed heap memory was handed back at once"
    _malloc.release_freed_memory()
    assert _resident_mb() - base < 28


def test_improve_keeps_and_then_releases(monkeypatch):
    """improve() sets the thresholds (unless JTET_MALLOC=0) and trims at its end."""
    calls = []
    monkeypatch.setattr(_malloc, "_kept", False)
    monkeypatch.setattr(_malloc, "release_freed_memory", lambda: calls.append("release"))
    monkeypatch.setenv("JTET_MALLOC", "0")
    mesh = jtet.demo_mesh()
    jtet.improve(mesh, max_passes=1, perturb=0)
    assert not _malloc._kept and calls == ["release"]
    monkeypatch.delenv("JTET_MALLOC")
    jtet.improve(mesh, max_passes=1, perturb=0)
    assert _malloc._kept == bool(_malloc._glibc())
    assert calls == ["release", "release"]
