"""Process-wide numerics set-up: float64 for every JAX computation jtet does, compile cache."""

import os
import signal
import threading

from . import _interrupt

# Count Ctrl-C from here on: one that lands in a gc callback (JAX registers one) is
# swallowed there, and only the count tells the CLI and the optimizer (see _interrupt)
_interrupt.install()

# Ctrl-C while jaxlib initializes its extension crashes the interpreter (SIGSEGV / abort /
# ImportError). Hold SIGINT back during the import: a Ctrl-C then arrives right after it
# as a plain KeyboardInterrupt. (Threads XLA starts meanwhile keep it blocked, so the
# signal always goes to the main thread, where Python handles it.)
_main = threading.current_thread() is threading.main_thread() and hasattr(signal, "pthread_sigmask")
if _main:
    _mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
try:
    import jax
finally:
    if _main:
        signal.pthread_sigmask(signal.SIG_SETMASK, _mask)

# Geometry is never computed in float32: jtet's kernels are written for float64 and the
# quality signs (correct / degenerate / inverted) depend on it.
jax.config.update("jax_enable_x64", True)

# A persistent compilation cache keeps a second run from compiling the same kernels again.
_cache_dir = os.environ.get(
    "JTET_COMPILATION_CACHE", os.path.join(os.path.expanduser("~"), ".cache", "jtet", "jax")
)
CACHE_DIR = None  # the cache directory in use (also holds _aot's exported kernels), or None
if _cache_dir and _cache_dir.lower() != "off":
    try:
        os.makedirs(_cache_dir, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", _cache_dir)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
        CACHE_DIR = _cache_dir
    except OSError:  # a read-only home must not stop jtet; it only costs compile time
        pass


# Independent kernel calls (e.g. the batches of one smoothing colour) run in this many
# threads: XLA runs each call on one core, and JAX releases the GIL while it runs, so on
# 2 cores two calls in flight measured 1.4-1.9x one after the other.
WORKERS = max(1, int(os.environ.get("JTET_THREADS", os.cpu_count() or 1)))
_pool = None
_pool_lock = threading.Lock()
_worker = threading.local()  # .busy: this thread is one of the pool's workers


def parallel_map(fn, items: list) -> list:
    """``[fn(x) for x in items]`` on ``WORKERS`` threads, results in order (deterministic:
    the items must not depend on each other)."""
    global _pool
    if WORKERS == 1 or len(items) < 2 or getattr(_worker, "busy", False):
        # (a worker waiting on tasks queued behind itself could deadlock the pool)
        return [fn(x) for x in items]
    with _pool_lock:
        if _pool is None:
            from concurrent.futures import ThreadPoolExecutor

            _pool = ThreadPoolExecutor(WORKERS, thread_name_prefix="jtet", initializer=_mark_worker)
    return list(_pool.map(fn, items))


def _mark_worker() -> None:
    _worker.busy = True


def bucket_capacity(n: int, minimum: int = 256) -> int:
    """Smallest capacity from the fixed set {minimum * 2**k} holding ``n`` items.

    Batches are padded to these sizes so that jitted kernels see few distinct shapes
    and never recompile inside the optimizer's loop.
    """
    cap = minimum
    while cap < n:
        cap *= 2
    return cap
