"""Traced kernels kept on disk: a new process skips tracing and lowering them.

JAX's persistent compilation cache (``_config``) stores XLA binaries, but every new process
still traces and lowers each kernel for each batch shape before it can look the binary up:
~2.2 s for one smoothing kernel shape (measured), most of a CLI run on a small mesh. Here a
kernel is exported once per (name, settings, input shapes) with ``jax.export`` and its
serialized StableHLO is stored next to the compilation cache; later processes deserialize it
(milliseconds), and its compilation then hits the persistent cache.

Kernels are compiled when first requested (``cached_call``) or ahead of use (``prefetch``,
several at once on the worker threads: XLA compiles and loads binaries without the GIL,
so two kernels compile in the time of one on two cores). Each kernel is built by one
thread; other threads asking for the same kernel wait for it, those asking for other
kernels do not.

A process that will run the optimizer calls ``warm_start(groups=...)`` first: the kernels
of the run's (name, settings) groups that earlier processes used most recently are then
loaded from disk on background threads while the caller builds its mesh topology and runs
its first passes, instead of one group at a time as the passes first need them.

Files live in ``jtet-aot/<version>/`` where the version hashes jtet's own source and the
JAX version, so an edited kernel is never served stale; directories of other versions
beyond the ``KEEP_VERSIONS`` most recently used are deleted when a new kernel is written.
Any failure (read-only or corrupt cache, an export JAX cannot do) falls back to the plain
jitted function: the cache only ever costs time, never correctness.
"""

from __future__ import annotations

import ast
import atexit
import functools
import hashlib
import os
import shutil
import threading
import time
from pathlib import Path

import jax

from . import _config

KEEP_VERSIONS = 3  # source versions whose kernels stay on disk (the current one included)
WARM_START_KERNELS = 32  # most recently used kernels warm_start() loads (a cube run: 13)

_memo: dict[tuple, object] = {}  # (name, settings, shapes) -> compiled call
_building: dict[tuple, threading.Event] = {}  # kernels some thread is building right now
_lock = threading.Lock()
_background: list[threading.Thread] = []  # sibling / warm-start loads, joined at exit
_stopping = threading.Event()  # set at exit: background loads take no new kernel
_pruned = False  # old versions are pruned at most once per process
_groups_seen: set[tuple] = set()  # (name, settings) whose siblings were loaded
_warm_started = False  # warm_start() runs at most once per process
_called: set[tuple] = set()  # keys this process has called (recorded in ``.calls`` files)
_PROCESS = f"{os.getpid()}-{time.time_ns()}"  # this process in the ``.calls`` files
CALLS_KEPT = 4  # processes whose called kernels a group's ``.calls`` file remembers
# Kernels built by this process: exported (traced + lowered + written) or loaded from disk,
# and seconds spent on both, summed over threads (experiments/bench_improve.py --compile).
STATS = {"exported": 0, "loaded": 0, "export_s": 0.0, "compile_s": 0.0}


@functools.cache
def _source_hash() -> str:
    """Hash of every jtet source file and of the JAX version (kernels change with both)."""
    h = hashlib.sha256(jax.__version__.encode())
    for path in sorted(Path(__file__).parent.rglob("*.py")):
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _root() -> Path | None:
    return None if _config.CACHE_DIR is None else Path(_config.CACHE_DIR) / "jtet-aot"


def _directory() -> Path | None:
    root = _root()
    return None if root is None else root / _source_hash()


def _key(name: str, settings: tuple, args) -> tuple:
    return (name, settings, tuple((tuple(a.shape), _dtype_name(a.dtype)) for a in args))


_DTYPE_NAMES: dict = {}


def _dtype_name(dtype) -> str:
    """``str(dtype)``, memoized: NumPy builds the name in Python (~7 us a call), and every
    kernel call builds its key (12 arguments: 89 -> 5 us a key, measured)."""
    name = _DTYPE_NAMES.get(dtype)
    if name is None:
        name = _DTYPE_NAMES[dtype] = str(dtype)
    return name


def cached_call(name: str, settings: tuple, fn, *args, siblings: bool = False):
    """``jax.jit(fn)(*args)``, with the traced ``fn`` for these argument shapes exported to
    and reloaded from the on-disk cache. ``settings`` must name everything ``fn`` closes
    over (static options); ``name`` the kernel.

    ``siblings=True``: when this kernel is first built in the process, the other shapes of
    the same (name, settings) that earlier processes exported are loaded at the same time
    on background threads (a run needs the shapes the last one needed, e.g. the star
    capacities of smoothing), instead of one after the other as calls first need them.
    """
    key = _key(name, settings, args)
    call = _memo.get(key)
    if call is None:
        if siblings:
            _load_siblings(key, fn)
        call = _get(key, fn, args)
    if key not in _called:
        _record_call(key)
    return call(*args)


def _calls_path(directory: Path, group: tuple) -> Path:
    return directory / f"{_group_prefix(group)}.calls"


def _record_call(key: tuple) -> None:
    """Note in the group's ``.calls`` file that this process called ``key``.

    The file lists, for each of the last ``CALLS_KEPT`` processes that called a kernel
    of the group, the shapes it called. The warm start and the sibling loads read it to
    load only those shapes: kernels of a group that no recent run called (a batch size
    tried once, the test suite's shapes) are not loaded into every later run. A lost
    update between two processes writing at once only costs one of them a later load.
    """
    directory = _directory()
    with _lock:
        if key in _called:
            return
        _called.add(key)
        if directory is None:
            return
        mine = sorted((k for k in _called if k[:2] == key[:2]), key=repr)
        path = _calls_path(directory, key[:2])
        try:
            others = [e for e in _read_calls(path) if e[0] != _PROCESS]
            entries = [(_PROCESS, mine), *others[: CALLS_KEPT - 1]]
            _write_atomic(path, repr(entries).encode())
        except OSError:  # read-only or vanished cache: the loads fall back to every shape
            pass


def _read_calls(path: Path) -> list:
    """[(process, [key, ...]), ...] of a ``.calls`` file, most recent process first; []
    when there is none or it cannot be read."""
    try:
        entries = ast.literal_eval(path.read_text())
        return [(str(p), [tuple(k) for k in keys]) for p, keys in entries]
    except (OSError, ValueError, SyntaxError, TypeError):
        return []


def _recent_keys(directory: Path, group: tuple) -> list[tuple] | None:
    """Keys of ``group`` that the last processes called, most recent first, each once;
    None when no process recorded its calls (then every exported shape counts)."""
    entries = _read_calls(_calls_path(directory, group))
    if not entries:
        return None
    keys = []
    for _, called in entries:
        keys += [k for k in called if k not in keys]
    return keys


def _load_siblings(key: tuple, fn) -> None:
    """Start loading the exported shapes of ``key``'s (name, settings) other than ``key``
    on background threads (only once per (name, settings) and process)."""
    group = key[:2]
    with _lock:
        if group in _groups_seen:
            return
        _groups_seen.add(group)
    directory = _directory()
    if directory is None:
        return
    recent = _recent_keys(directory, group)
    try:
        if recent is None:
            paths = sorted(directory.glob(f"{_group_prefix(group)}-*.bin"))
        else:
            paths = [directory / _filename(k) for k in recent if k != key]
    except OSError:
        return
    for path in paths:
        _start_background(_load_sibling, group, fn, path)


def _start_background(target, *args) -> threading.Thread:
    """Run ``target(*args)`` on a daemon thread that the interpreter's exit waits for
    (``join_background``); returns the started thread."""
    thread = threading.Thread(target=target, args=args, daemon=True)
    with _lock:
        _background.append(thread)
    thread.start()
    return thread


@atexit.register
def join_background() -> None:
    """Let the background loads that are running finish before the interpreter exits and
    start no new one: a thread still inside XLA while Python finalizes aborts the process
    (measured: a short run printed its result, then exited with SIGABRT). A load takes
    0.05-0.5 s; the timeout only guards against a hang."""
    _stopping.set()
    deadline = time.monotonic() + 60.0
    for thread in list(_background):
        thread.join(timeout=max(0.0, deadline - time.monotonic()))


def _load_sibling(group: tuple, fn, path: Path) -> None:
    if _stopping.is_set():
        return
    try:
        exported = jax.export.deserialize(bytearray(path.read_bytes()))
        structs = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exported.in_avals]
        key = _key(*group, structs)
        if key not in _memo and path.name == _filename(key):
            _get(key, fn, structs)
    except Exception:  # noqa: BLE001  (only a head start: the call itself builds it)
        pass


def warm_start(limit: int = WARM_START_KERNELS, groups=None) -> list[tuple]:
    """Start loading, on ``_config.WORKERS`` background threads, the ``limit`` kernels of
    this source version that processes used most recently (each kernel file's time
    stamp is renewed whenever a process builds it), in the order they were last used;
    only once per process. Returns their keys. A kernel a caller asks for meanwhile is
    loaded once: the caller waits for the background thread or the thread skips it.

    ``groups`` (optional collection of (name, settings)): only kernels of these groups.
    A cache that runs with other settings filled (a sweep over quality measures, the
    test suite) then costs no loads of kernels this run never calls: each load takes
    0.05-0.5 s of CPU from the run it overlaps. Of a group, the shapes its last
    ``CALLS_KEPT`` processes called (its ``.calls`` file), most recent first; every
    exported shape if no process recorded its calls.

    A warm cube run loads 4-5 kernels (the per-tet kernel and the pass kernels), 0.05-0.5
    s each summed over threads, most of the overhead of a first run; loaded behind the
    topology build and the first passes they cost less wall time
    (``experiments/results/compile.md``).
    """
    global _warm_started
    with _lock:
        if _warm_started:
            return []
        _warm_started = True
    directory = _directory()
    if directory is None:
        return []
    # groups whose recent processes recorded their calls: exactly those kernels
    todo, unrecorded = [], groups
    if groups is not None:
        unrecorded = set()
        for group in sorted(groups, key=repr):
            recent = _recent_keys(directory, group)
            if recent is None:
                unrecorded.add(group)
            else:
                todo += [(k, directory / _filename(k)) for k in recent]
        todo = [(k, p) for k, p in todo if p.exists()][:limit]
    if unrecorded is None or unrecorded:
        try:
            recent = sorted(directory.glob("*.bin"), key=lambda p: p.stat().st_mtime)
        except OSError:  # a file pruned meanwhile by another process
            recent = []
        found = []
        for path in reversed(recent):  # most recent first, until ``limit`` are taken
            if len(todo) + len(found) == limit:
                break
            try:
                key = ast.literal_eval(path.with_suffix(".key").read_text())
            except (OSError, ValueError, SyntaxError):  # exported before keys were written
                continue
            if path.name == _filename(key) and (unrecorded is None or key[:2] in unrecorded):
                found.append((key, path))
        todo += reversed(found)  # loaded in the order they were last used
    queue = iter(todo)
    for _ in range(min(_config.WORKERS, len(todo))):
        _start_background(_warm_worker, queue)
    return [key for key, _ in todo]


def _warm_worker(queue) -> None:
    """Load the (key, path) items of ``queue`` (shared by the warm-start threads) that no
    thread has built or started to build."""
    while not _stopping.is_set():
        with _lock:
            item = next(queue, None)
            if item is not None and (item[0] in _memo or item[0] in _building):
                continue
        if item is None:
            return
        key, path = item
        try:
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
            _get(key, None, [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in exported.in_avals])
        except Exception:  # noqa: BLE001  (only a head start: the call itself builds it)
            pass


def prefetch(specs: list[tuple]) -> None:
    """Build the kernels ``(name, settings, fn, args)`` that are not built yet, on the
    worker threads (``args``: arrays or ``jax.ShapeDtypeStruct``s of the call's shapes)."""
    todo = {}
    for name, settings, fn, args in specs:
        key = _key(name, settings, args)
        if key not in _memo:
            todo[key] = (fn, args)
    if todo:
        _config.parallel_map(lambda item: _get(item[0], *item[1]), list(todo.items()))


def call_specs(call: functools.partial, args_list: list) -> list[tuple]:
    """``prefetch`` specs of a ``functools.partial(cached_call, name, settings, fn)`` (as
    ``_smooth.batched_smoother`` returns) for every argument list in ``args_list`` (arrays
    or ``jax.ShapeDtypeStruct``s)."""
    name, settings, fn = call.args[:3]
    return [(name, settings, fn, args) for args in args_list]


def prefetch_calls(call: functools.partial, args_list: list) -> None:
    """``prefetch`` of ``call_specs(call, args_list)``: the kernels built at once."""
    prefetch(call_specs(call, args_list))


def prefetch_in_background(specs: list[tuple]) -> None:
    """Build the kernels ``(name, settings, fn, args)`` (as ``prefetch``) on background
    threads, one per kernel, that the interpreter's exit joins; returns at once. For
    kernels the caller needs later: a new process builds them (the smoothing kernel:
    ~9 s cold) while the caller does other work. A caller that asks for one of them
    meanwhile waits for its thread instead of building it again."""

    def build(spec) -> None:
        if _stopping.is_set():
            return
        try:
            prefetch([spec])
        except Exception:  # noqa: BLE001  (only a head start: the call itself builds it)
            pass

    for spec in specs:
        _start_background(build, spec)


def _get(key: tuple, fn, args):
    """The compiled call of ``key``, built by this thread or by the one already on it."""
    while True:
        with _lock:
            call = _memo.get(key)
            if call is not None:
                return call
            event = _building.get(key)
            if event is None:
                event = _building[key] = threading.Event()
                break
        event.wait()  # another thread builds it; if that failed, the loop retries
    try:
        call = _build(key, fn, args)
        with _lock:
            _memo[key] = call
        return call
    finally:
        with _lock:
            del _building[key]
        event.set()


def _group_prefix(group: tuple) -> str:
    return hashlib.sha256(repr(group).encode()).hexdigest()[:16]


def _filename(key: tuple) -> str:
    """``<hash of (name, settings)>-<hash of the whole key>.bin``: the shapes exported for
    one (name, settings) can be listed (``siblings``)."""
    return f"{_group_prefix(key[:2])}-{hashlib.sha256(repr(key).encode()).hexdigest()}.bin"


# XLA:CPU options of every kernel build. Its older (elemental) emitters instead of its MLIR
# fusion emitters: the smoothing kernel compiled in 2.0 instead of 3.4 s of CPU, and ran
# as fast; of the other kernels, the tree DP ran 0.7-0.8x the time, the ring DP and the
# small per-tet shape 1.1-1.2x, which nets out over a run, while keeping the defaults for
# those two cost 0.4-1.4 s more of cold compile (experiments/results/compile.md, session
# 20). Results may differ from the default build's in the last bits (positions ~1e-11
# relative), never in meaning.
COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False}


@functools.cache
def compiler_options() -> dict:
    """``COMPILER_OPTIONS``, or {} when this JAX's XLA does not know one of them (older
    or newer releases): the kernels then build with XLA's defaults."""
    try:
        jax.jit(lambda x: x).lower(0.0).compile(compiler_options=COMPILER_OPTIONS)
    except Exception:  # noqa: BLE001  (JaxRuntimeError "No such compile option", ...)
        return {}
    return dict(COMPILER_OPTIONS)


def _jit(fn):
    """``jax.jit(fn)`` with the kernel build options."""
    return jax.jit(fn, compiler_options=compiler_options() or None)


def _compile(f, structs):
    return _jit(f).lower(*structs).compile()


def _build(key: tuple, fn, args):
    """Load the exported kernel (or export it), then compile it (a persistent-cache hit
    when warm). Falls back to ``jax.jit(fn)`` on any cache problem; ``fn=None`` (a
    warm-start load, no function at hand) raises instead."""
    structs = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in args]
    directory = _directory()
    if directory is None:
        return _jit(fn)
    path = directory / _filename(key)
    try:
        t0 = time.perf_counter()
        loaded = path.exists()
        if loaded:
            exported = jax.export.deserialize(bytearray(path.read_bytes()))
            os.utime(directory)  # recently used: pruning keeps it
            os.utime(path)  # and warm_start loads it
        else:
            exported = jax.export.export(jax.jit(fn))(*structs)
            directory.mkdir(parents=True, exist_ok=True)
            # the key first (warm_start reads it to load the kernel without a call)
            _write_atomic(path.with_suffix(".key"), repr(key).encode())
            _write_atomic(path, exported.serialize())
            _prune_once()
        t1 = time.perf_counter()
        call = _compile(exported.call, structs)
        with _lock:
            STATS["loaded" if loaded else "exported"] += 1
            STATS["export_s"] += t1 - t0
            STATS["compile_s"] += time.perf_counter() - t1
        return call
    except Exception:  # noqa: BLE001  (any cache problem: trace as usual)
        if fn is None:
            raise
        return _jit(fn)


def _write_atomic(path: Path, data: bytes) -> None:
    """Write through a temporary file and a rename: a reader never sees half a file."""
    tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _prune_once() -> None:
    global _pruned
    with _lock:
        if _pruned:
            return
        _pruned = True
    prune()


def prune(keep: int = KEEP_VERSIONS) -> list[Path]:
    """Delete the exported kernels of all but the ``keep`` most recently used source
    versions (the current one always stays), and files of the old flat layout. Returns
    the deleted paths. Safe against concurrent processes: a kernel deleted under a reader
    is only re-exported."""
    root = _root()
    if root is None or not root.is_dir():
        return []
    current = _source_hash()
    versions, files = [], []
    for p in root.iterdir():
        try:
            if p.is_dir() and p.name != current:
                versions.append((p.stat().st_mtime, p))
            elif p.is_file() and p.suffix in (".bin", ".tmp"):  # the old flat layout
                files.append((p.stat().st_mtime, p))
        except OSError:  # removed meanwhile by another process
            pass
    versions.sort(reverse=True)
    removed = []
    for _, p in versions[max(keep - 1, 0) :]:
        shutil.rmtree(p, ignore_errors=True)
        removed.append(p)
    cutoff = time.time() - 3600  # a young .tmp may be an export in flight
    for mtime, p in files:
        if p.suffix == ".tmp" and mtime > cutoff:
            continue
        try:
            p.unlink()
            removed.append(p)
        except OSError:
            pass
    return removed
