"""Traced kernels kept on disk: a new process skips tracing and lowering them.

JAX's persistent compilation cache (``_config``) stores XLA binaries, but every new process
still traces and lowers each kernel for each batch shape before it can look the binary up:
~2.2 s for one smoothing kernel shape (measured), most of a CLI run on a small mesh. Here a
kernel is exported once per (name, settings, input shapes) with ``jax.export`` and its
serialized StableHLO is stored next to the compilation cache; later processes deserialize it
(milliseconds), and its compilation then hits the persistent cache.

Keys include a hash of jtet's own source and the JAX version, so an edited kernel is never
served stale. Any failure (read-only or corrupt cache, an export JAX cannot do) falls back
to the plain jitted function: the cache only ever costs time, never correctness.
"""

from __future__ import annotations

import functools
import hashlib
import os
import threading
from pathlib import Path

import jax

from . import _config

_memo: dict[tuple, object] = {}  # (name, settings, shapes) -> jitted call
_lock = threading.Lock()


@functools.cache
def _source_hash() -> str:
    """Hash of every jtet source file and of the JAX version (kernels change with both)."""
    h = hashlib.sha256(jax.__version__.encode())
    for path in sorted(Path(__file__).parent.rglob("*.py")):
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _directory() -> Path | None:
    return None if _config.CACHE_DIR is None else Path(_config.CACHE_DIR) / "jtet-aot"


def cached_call(name: str, settings: tuple, fn, *args):
    """``jax.jit(fn)(*args)``, with the traced ``fn`` for these argument shapes exported to
    and reloaded from the on-disk cache. ``settings`` must name everything ``fn`` closes
    over (static options); ``name`` the kernel."""
    key = (name, settings, tuple((a.shape, str(a.dtype)) for a in args))
    call = _memo.get(key)
    if call is None:
        with _lock:  # one thread exports / loads a kernel; the others wait for it
            call = _memo.get(key)
            if call is None:
                call = _load_or_export(key, fn, args)
                _memo[key] = call
    return call(*args)


def _load_or_export(key: tuple, fn, args):
    directory = _directory()
    jitted = jax.jit(fn)
    if directory is None:
        return jitted
    digest = hashlib.sha256(repr((key, _source_hash())).encode()).hexdigest()
    path = directory / f"{digest}.bin"
    try:
        if path.exists():
            return jax.jit(jax.export.deserialize(bytearray(path.read_bytes())).call)
        structs = [jax.ShapeDtypeStruct(a.shape, a.dtype) for a in args]
        exported = jax.export.export(jitted)(*structs)
        directory.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")
        tmp.write_bytes(exported.serialize())
        os.replace(tmp, path)  # atomic: a reader never sees half a file
        return jax.jit(exported.call)
    except Exception:  # noqa: BLE001  (any cache problem: trace as usual)
        return jitted
