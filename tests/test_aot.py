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
    """A fresh cache directory; returns the directory of this source version's kernels."""
    monkeypatch.setattr(_config, "CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(_aot, "_memo", {})
    monkeypatch.setattr(_aot, "_pruned", False)
    monkeypatch.setattr(_aot, "_groups_seen", set())
    monkeypatch.setattr(_aot, "_warm_started", False)
    monkeypatch.setattr(_aot, "_called", set())
    return tmp_path / "jtet-aot" / _aot._source_hash()


def new_process(monkeypatch, name: str) -> None:
    """Forget what this process built and called, as a new process would."""
    monkeypatch.setattr(_aot, "_memo", {})
    monkeypatch.setattr(_aot, "_groups_seen", set())
    monkeypatch.setattr(_aot, "_warm_started", False)
    monkeypatch.setattr(_aot, "_called", set())
    monkeypatch.setattr(_aot, "_PROCESS", name)


ARGS = (np.linspace(0, 1, 12).reshape(4, 3), np.arange(15.0).reshape(3, 5))


def test_export_then_reload_gives_identical_results(cache):
    import jax

    expected = np.asarray(jax.jit(_kernel)(*ARGS))
    first = np.asarray(_aot.cached_call("k", (1,), _kernel, *ARGS))
    # the kernel and its key, no temporary file left, and the group's record of calls
    files = sorted(cache.iterdir(), key=lambda f: f.suffix)
    assert [f.suffix for f in files] == [".bin", ".calls", ".key"]
    assert files[0].stem == files[2].stem and files[0].stem.startswith(files[1].stem + "-")
    _aot._memo.clear()  # a new process: the kernel comes from the file
    second = np.asarray(_aot.cached_call("k", (1,), _kernel, *ARGS))
    assert np.array_equal(first, expected) and np.array_equal(second, expected)


def test_settings_and_shapes_make_separate_entries(cache):
    _aot.cached_call("k", (1,), _kernel, *ARGS)
    _aot.cached_call("k", (2,), _kernel, *ARGS)
    _aot.cached_call("k", (1,), _kernel, ARGS[0][:2], ARGS[1])
    assert len(list(cache.glob("*.bin"))) == 3


def test_corrupt_file_falls_back_to_tracing(cache):
    import jax

    _aot.cached_call("k", (1,), _kernel, *ARGS)
    (path,) = cache.glob("*.bin")
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


def test_prefetch_builds_each_kernel_once_and_calls_reuse_it(cache, monkeypatch):
    import jax

    built = []
    real = _aot._build
    monkeypatch.setattr(
        _aot, "_build", lambda key, fn, args: built.append(key) or real(key, fn, args)
    )
    structs = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in ARGS]
    specs = [("k", (s,), _kernel, structs) for s in (1, 2, 3)]
    _aot.prefetch(specs + specs)  # duplicates are built once
    assert len(built) == 3 and len(list(cache.glob("*.bin"))) == 3
    out = np.asarray(_aot.cached_call("k", (2,), _kernel, *ARGS))
    _aot.prefetch(specs)  # all built: nothing to do
    assert len(built) == 3
    assert np.array_equal(out, np.asarray(jax.jit(_kernel)(*ARGS)))


def test_threads_asking_for_one_kernel_share_one_build(cache, monkeypatch):
    import threading

    calls = []
    real = _aot._build
    gate = threading.Event()

    def slow_build(key, fn, args):
        calls.append(key)
        gate.wait(5)
        return real(key, fn, args)

    monkeypatch.setattr(_aot, "_build", slow_build)
    outs = []
    threads = [
        threading.Thread(target=lambda: outs.append(_aot.cached_call("k", (1,), _kernel, *ARGS)))
        for _ in range(3)
    ]
    for t in threads:
        t.start()
    gate.set()
    for t in threads:
        t.join()
    assert len(calls) == 1 and len(outs) == 3
    assert all(np.array_equal(np.asarray(o), np.asarray(outs[0])) for o in outs)


def test_failed_build_is_retried_by_the_next_caller(cache, monkeypatch):
    real = _aot._build
    monkeypatch.setattr(_aot, "_build", lambda *a: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        _aot.cached_call("k", (1,), _kernel, *ARGS)
    assert not _aot._building  # nobody waits for the failed build
    monkeypatch.setattr(_aot, "_build", real)
    assert np.isfinite(np.asarray(_aot.cached_call("k", (1,), _kernel, *ARGS))).all()


def test_prune_keeps_recent_versions_and_the_current_one(cache):
    import os

    root = cache.parent
    _aot.cached_call("k", (1,), _kernel, *ARGS)  # the current version's directory
    for i in range(5):  # older versions, version0 the oldest
        d = root / f"version{i}"
        d.mkdir()
        (d / "x.bin").write_bytes(b"x")
        os.utime(d, (1000.0 + i, 1000.0 + i))
    (root / "flat.bin").write_bytes(b"old layout")
    os.utime(cache, (10.0, 10.0))  # the current one stays even when oldest
    removed = _aot.prune(keep=3)
    left = sorted(p.name for p in root.iterdir())
    assert left == sorted([cache.name, "version3", "version4"])
    assert len(removed) == 4


def test_new_export_prunes_old_versions_once(cache, monkeypatch):
    root = cache.parent
    root.mkdir(parents=True)
    for i in range(_aot.KEEP_VERSIONS + 2):
        (root / f"version{i}").mkdir()
    _aot.cached_call("k", (1,), _kernel, *ARGS)
    assert len(list(root.iterdir())) == _aot.KEEP_VERSIONS
    assert _aot._pruned


def test_parallel_map_inside_a_worker_runs_serially():
    if _config.WORKERS < 2:
        pytest.skip("one worker thread")
    out = _config.parallel_map(lambda i: _config.parallel_map(lambda j: i * 10 + j, [0, 1]), [1, 2])
    assert out == [[10, 11], [20, 21]]


def test_ring_prefetch_builds_what_solve_rings_uses(cache):
    from jtet._kernels import klincsek as kl

    kl.prefetch([4, 6, kl.PRUNE_MIN_M], "min_sine", prune=True)
    built = set(_aot._memo)
    # sizes 4 and 6 share the padded kernel; PRUNE_MIN_M has its own solve and screen
    names = sorted(k[0] for k in built)
    assert names == ["screen_chunks", "solve_chunks", "solve_padded_chunks"]
    rng = np.random.default_rng(0)
    n = kl.CALL_CHUNKS * kl.CHUNK * 2 + 5  # three kernel calls per kernel
    for m in (4, 6, kl.PRUNE_MIN_M):
        ring = rng.random((n, m, 3))
        kl.solve_rings(rng.random((n, 3)), rng.random((n, 3)), ring, np.full(n, -1.0))
    sizes = rng.integers(3, kl.PRUNE_MIN_M + 1, n)  # one batch of mixed sizes
    ring = rng.random((n, kl.PRUNE_MIN_M, 3))
    kl.solve_rings(rng.random((n, 3)), rng.random((n, 3)), ring, np.zeros(n), sizes=sizes)
    assert set(_aot._memo) == built


def test_quality_in_fixed_calls_matches_one_evaluation(monkeypatch):
    import jax

    from jtet import _quality

    monkeypatch.setattr(_quality, "TET_CHUNK", 8)
    rng = np.random.default_rng(1)
    points = rng.random((30, 3))
    tets = rng.integers(0, 30, (21, 4))  # three calls, the last one padded
    corners = _quality.soa_corners(points, tets)
    # one evaluation built with the kernels' XLA options (other options may round differently)
    one_call = jax.jit(_quality.radius_ratio, compiler_options=_aot.compiler_options() or None)
    expected = np.asarray(one_call(*corners))
    assert np.array_equal(_quality.tet_quality(points, tets, "radius_ratio"), expected)
    angles, lo, hi = _quality.tet_dihedrals(points, tets)
    assert angles.shape == (21, 6) and np.array_equal(lo, angles.min(axis=1))
    assert np.array_equal(hi, angles.max(axis=1))
    assert _quality.tet_quality(points, tets[:0]).shape == (0,)


def test_siblings_load_the_other_exported_shapes_in_the_background(cache):
    import time

    small = (ARGS[0][:2], ARGS[1])
    _aot.cached_call("k", (1,), _kernel, *ARGS)
    _aot.cached_call("k", (1,), _kernel, *small)
    _aot.cached_call("k", (2,), _kernel, *small)  # another group: not a sibling
    _aot._memo.clear()  # a new process
    _aot.cached_call("k", (1,), _kernel, *ARGS, siblings=True)
    other = _aot._key("k", (1,), small)
    deadline = time.monotonic() + 60
    while other not in _aot._memo and time.monotonic() < deadline:
        time.sleep(0.05)
    assert set(_aot._memo) == {_aot._key("k", (1,), ARGS), other}
    assert _aot.STATS["loaded"] >= 2


def test_prefetch_calls_takes_a_cached_call_partial(cache):
    import functools

    import jax

    call = functools.partial(_aot.cached_call, "k", (1,), _kernel, siblings=True)
    structs = [[jax.ShapeDtypeStruct((n, 3), np.float64), jax.ShapeDtypeStruct((3, 5), np.float64)]
               for n in (2, 4)]  # fmt: skip
    _aot.prefetch_calls(call, structs)
    assert set(_aot._memo) == {_aot._key("k", (1,), s) for s in structs}
    assert np.array_equal(np.asarray(call(*ARGS)), np.asarray(jax.jit(_kernel)(*ARGS)))


def test_warm_start_loads_the_most_recently_used_kernels(cache, monkeypatch):
    import os
    import time

    import jax

    shapes = [(ARGS[0][:n], ARGS[1]) for n in (1, 2, 3, 4)]
    for i, args in enumerate(shapes):
        _aot.cached_call("k", (1,), _kernel, *args)
        path = cache / _aot._filename(_aot._key("k", (1,), args))
        os.utime(path, (1e9 + i, 1e9 + i))  # used in this order
    (cache / _aot._filename(_aot._key("k", (1,), shapes[0]))).with_suffix(".key").unlink()
    _aot._memo.clear()  # a new process
    loaded = _aot.warm_start(limit=3)  # the three most recent, all with a key file
    assert loaded == [_aot._key("k", (1,), args) for args in shapes[1:]]
    assert _aot.warm_start() == []  # once per process
    deadline = time.monotonic() + 60
    while len(_aot._memo) < 3 and time.monotonic() < deadline:
        time.sleep(0.05)
    assert set(_aot._memo) == set(loaded)
    # a call finds its kernel loaded: no tracing (the function would fail if traced)
    monkeypatch.setattr(_aot, "_build", lambda *a: 1 / 0)
    out = _aot.cached_call("k", (1,), None, *shapes[3])
    assert np.array_equal(np.asarray(out), np.asarray(jax.jit(_kernel)(*shapes[3])))


def test_warm_start_loads_only_the_groups_asked_for(cache):
    # a cache that runs with other settings filled (other quality measures, other
    # kernels) must not cost this run loads of kernels it never calls
    import os

    args = [(ARGS[0][:n], ARGS[1]) for n in (1, 2, 3)]
    for i, (settings, a) in enumerate([((1,), args[0]), ((2,), args[1]), ((1,), args[2])]):
        _aot.cached_call("k", settings, _kernel, *a)
        os.utime(cache / _aot._filename(_aot._key("k", settings, a)), (1e9 + i, 1e9 + i))
    _aot.cached_call("other", (1,), _kernel, *args[0])  # the most recent of all
    _aot._memo.clear()  # a new process
    loaded = _aot.warm_start(limit=32, groups={("k", (1,))})
    # every shape of the group, in the order they were last used; nothing else
    assert loaded == [_aot._key("k", (1,), args[0]), _aot._key("k", (1,), args[2])]
    for thread in list(_aot._background):
        thread.join()
    # ``limit`` counts the group's kernels only: the most recently called of them
    _aot._memo.clear()
    _aot._warm_started = False
    _aot._called.clear()
    _aot._PROCESS = "second"
    _aot.cached_call("k", (1,), _kernel, *args[2])
    _aot._memo.clear()
    _aot._warm_started = False
    assert _aot.warm_start(limit=1, groups={("k", (1,))}) == [_aot._key("k", (1,), args[2])]
    for thread in list(_aot._background):
        thread.join()


def test_loads_skip_shapes_no_recent_process_called(cache, monkeypatch):
    # a shape one run called (a batch size tried once) stops being loaded into later
    # runs once CALLS_KEPT processes in a row did not call it
    a, b = (ARGS[0][:2], ARGS[1]), ARGS
    ka, kb = _aot._key("k", (1,), a), _aot._key("k", (1,), b)
    new_process(monkeypatch, "p0")
    _aot.cached_call("k", (1,), _kernel, *a)
    _aot.cached_call("k", (1,), _kernel, *b)
    for i in range(1, _aot.CALLS_KEPT + 2):
        new_process(monkeypatch, f"p{i}")
        # the record holds the last CALLS_KEPT processes: p0 (a and b) drops out at the end
        expected = [ka] if i > _aot.CALLS_KEPT else [ka, kb]
        assert _aot.warm_start(groups={("k", (1,))}) == expected
        for thread in list(_aot._background):
            thread.join()
        _aot.cached_call("k", (1,), _kernel, *a)  # this run calls a only
    # the siblings of a first call follow the same record
    new_process(monkeypatch, "siblings")
    _aot.cached_call("k", (1,), _kernel, *a, siblings=True)
    for thread in list(_aot._background):
        thread.join()
    assert set(_aot._memo) == {ka}
    # with no record (caches written before .calls files), every shape counts
    for f in cache.glob("*.calls"):
        f.unlink()
    new_process(monkeypatch, "unrecorded")
    assert sorted(_aot.warm_start(groups={("k", (1,))}), key=repr) == sorted([ka, kb], key=repr)
    for thread in list(_aot._background):
        thread.join()


def test_exit_while_warm_start_loads_is_clean(tmp_path):
    """A process that exits while warm-start threads are still loading kernels exits
    normally: a thread inside XLA during interpreter shutdown aborted the process (SIGABRT
    after a correct result, e.g. a short ``jtet stats``)."""
    import os
    import subprocess
    import sys

    env = {**os.environ, "JTET_COMPILATION_CACHE": str(tmp_path)}
    # exports every kernel of a run, the smoothing kernel too (~0.4 s to load)
    fill = "import jtet; jtet.improve(jtet.demo_mesh(), max_passes=1)"
    subprocess.run([sys.executable, "-c", fill], env=env, check=True, capture_output=True)
    # exit while the loads run (each takes 0.05-0.5 s, inside XLA most of that time)
    start = "import time; from jtet import _aot; print(len(_aot.warm_start())); time.sleep({})"
    for pause in (0.1, 0.3, 0.6, 1.0):
        cmd = [sys.executable, "-c", start.format(pause)]
        out = subprocess.run(cmd, env=env, capture_output=True)
        assert out.returncode == 0, out.stderr.decode()[-500:]
        assert int(out.stdout) > 0  # there were kernels to load


def test_background_prefetch_builds_what_the_passes_use(cache, monkeypatch):
    # improve's background builds (one thread per kernel) must be exactly the kernels its
    # passes then call, or a new process compiles them twice
    import jtet
    from jtet import _driver, _smooth

    opts = jtet.Options(max_ring=5)
    specs = _driver._pass_kernel_specs(opts)
    groups = {spec[:2] for spec in specs}
    _aot.prefetch_in_background(specs)  # returns at once
    for thread in list(_aot._background):
        thread.join()
    built = set(_aot._memo)
    assert sorted(k[0] for k in built) == ["smooth_star", "solve_padded_chunks", "solve_trees"]
    mesh = jtet.demo_mesh()
    assert np.bincount(mesh.tets.ravel()).max() <= _smooth.DEFAULT_CAPACITIES[0]
    asked = set()
    key_of = _aot._key

    def recording_key(*args):
        asked.add(key_of(*args))
        return key_of(*args)

    monkeypatch.setattr(_aot, "_key", recording_key)
    for step in _driver.STEPS.values():
        step(mesh, opts, mesh.quality(opts.quality), None)
    assert built <= asked  # (the demo also has larger trees: a second tree capacity)
    # the warm start of a run loads the groups of every pass kernel it calls
    per_tet = ("tet_all_measures", tuple(jtet.MEASURES))
    assert {k[:2] for k in asked} <= groups | {per_tet}
    assert groups == {k[:2] for k in built}
    with pytest.raises(jtet.JtetError, match="unknown smoothing options"):
        _smooth.pass_kernel_specs("min_sine", n_trails=3)


def test_a_refused_mesh_compiles_nothing(cache):
    # improve's checks come before any build: a mesh it refuses must not leave kernel
    # compilations running that the process's exit would then wait for (the warm start
    # before the checks only loads from disk, and this cache is empty)
    import jtet

    mesh = jtet.demo_mesh()
    doubled = jtet.TetMesh(mesh.points, np.concatenate([mesh.tets, mesh.tets[:1]]))
    threads_before = set(_aot._background)
    with pytest.raises(jtet.MeshInputError, match="non-conforming"):
        jtet.improve(doubled)
    assert _aot._memo == {} and _aot._building == {}
    assert not any(t.is_alive() for t in set(_aot._background) - threads_before)
    assert not list(cache.parent.glob("*/*.bin"))  # nothing exported either


def test_key_names_dtypes_as_str_does():
    """Kernel keys memoize the dtype names; they must be ``str(dtype)`` (the keys are
    also written to the cache's ``.calls`` files), on first use and from the memo."""
    args = [np.zeros((2, 3)), np.zeros(4, np.int32), np.zeros((1,), bool), jnp.zeros(2)]
    want = ("k", (1,), tuple((tuple(a.shape), str(a.dtype)) for a in args))
    assert _aot._key("k", (1,), args) == want
    assert _aot._key("k", (1,), args) == want  # the memoized names


def test_build_options_xla_refuses_are_dropped(cache, monkeypatch):
    """An XLA that does not know a build option (another JAX release) builds with its
    defaults: the kernel still comes from the cache, with the plain jit's results."""
    import jax

    assert _aot.compiler_options() == _aot.COMPILER_OPTIONS  # this JAX knows them
    seen = []  # the options each build passes to jax.jit
    real_jit = jax.jit
    monkeypatch.setattr(
        _aot.jax,
        "jit",
        lambda f, **kw: seen.append(kw.get("compiler_options")) or real_jit(f, **kw),
    )
    _aot.cached_call("k", (0,), _kernel, *ARGS)
    assert _aot.COMPILER_OPTIONS in seen
    monkeypatch.setattr(_aot, "COMPILER_OPTIONS", {"xla_no_such_option_anywhere": True})
    _aot.compiler_options.cache_clear()
    try:
        assert _aot.compiler_options() == {}
        got = np.asarray(_aot.cached_call("k", (1,), _kernel, *ARGS))
        key = _aot._key("k", (1,), ARGS)  # built from the exported file, not a plain-jit fallback
        assert (
            isinstance(_aot._memo[key], jax.stages.Compiled)
            and (cache / _aot._filename(key)).exists()
        )
        np.testing.assert_allclose(got, np.asarray(real_jit(_kernel)(*ARGS)), rtol=1e-14)
    finally:
        _aot.compiler_options.cache_clear()
