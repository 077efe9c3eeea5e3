"""The on-disk cache of exported kernels (jtet._aot): same results, files, fallbacks."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jtet import _aot, _config


def _kernel(x, y):
    """(4, 3), (3, 5) -> (5,): a while loop and reductions, like the smoothing kernel."""
    import jax

    def body(state):
        i, acc = state
        return i + 1, acc * 0.5 + jnp.sum(jnp.sin(x) @ y, axis=0)

    return jax.lax.while_loop(lambda s: s[0] < x.shape[0], body, (0, jnp.zeros(y.shape[1])))[1]


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setattr(_config, "CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(_aot, "_memo", {})
    return tmp_path / "jtet-aot"


ARGS = (np.linspace(0, 1, 12).reshape(4, 3), np.arange(15.0).reshape(3, 5))


def test_export_then_reload_gives_identical_results(cache):
    import jax

    expected = np.asarray(jax.jit(_kernel)(*ARGS))
    first = np.asarray(_aot.cached_call("k", (1,), _kernel, *ARGS))
    files = sorted(cache.iterdir())
    assert len(files) == 1 and files[0].suffix == ".bin"  # no temporary file left
    _aot._memo.clear()  # a new process: the kernel comes from the file
    second = np.asarray(_aot.cached_call("k", (1,), _kernel, *ARGS))
    assert np.array_equal(first, expected) and np.array_equal(second, expected)


def test_settings_and_shapes_make_separate_entries(cache):
    _aot.cached_call("k", (1,), _kernel, *ARGS)
    _aot.cached_call("k", (2,), _kernel, *ARGS)
    _aot.cached_call("k", (1,), _kernel, ARGS[0][:2], ARGS[1])
    assert len(list(cache.iterdir())) == 3


def test_corrupt_file_falls_back_to_tracing(cache):
    import jax

    _aot.cached_call("k", (1,), _kernel, *ARGS)
    (path,) = cache.iterdir()
    path.write_bytes(b"not a kernel")
    _aot._memo.clear()
    out = np.asarray(_aot.cached_call("k", (1,), _kernel, *ARGS))
    assert np.array_equal(out, np.asarray(jax.jit(_kernel)(*ARGS)))


def test_no_cache_directory_means_plain_jit(tmp_path, monkeypatch):
    monkeypatch.setattr(_config, "CACHE_DIR", None)
    monkeypatch.setattr(_aot, "_memo", {})
    out = _aot.cached_call("k", (1,), _kernel, *ARGS)
    assert np.isfinite(np.asarray(out)).all()
    assert not any(tmp_path.iterdir())
