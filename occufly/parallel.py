"""One executor interface for fan-out work (per-frame export, evaluation).

``get_executor()`` returns an object with

- ``map(fn, items, progress=None) -> list``: results in the order of ``items``; ``progress``
  (a :data:`occufly.progress.ProgressFn`) is called as tasks *complete*;
- ``submit(fn, *args, **kwargs) -> future`` with ``.result()``;
- ``close()`` / context manager.

Backends: :class:`SerialExecutor` (``workers=0`` or ``1``: in-process, for debugging and
small jobs), :class:`LocalExecutor` (a ``ProcessPoolExecutor``, the default) and
:class:`DaskExecutor` (``dask.distributed.Client`` connected to ``dask_address``). The same
task functions run on all of them: they must be importable top-level functions whose
arguments and results pickle; workers on a cluster must see the same file paths.
"""

from __future__ import annotations

import ctypes
import multiprocessing as mp
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterable
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from typing import Any

from occufly.errors import OccuflyError
from occufly.fsutil import pid_alive
from occufly.progress import ProgressFn


class SerialExecutor:
    """Runs everything in the calling process."""

    kind = "serial"
    workers = 1

    def submit(self, fn: Callable, *args: Any, **kwargs: Any) -> Future:
        fut: Future = Future()
        try:
            fut.set_result(fn(*args, **kwargs))
        except BaseException as e:  # noqa: BLE001 - delivered through the future
            fut.set_exception(e)
        return fut

    def map(self, fn: Callable, items: Iterable, progress: ProgressFn | None = None) -> list:
        items = list(items)
        out = []
        for i, item in enumerate(items):
            out.append(fn(item))
            if progress:
                progress((i + 1) / max(len(items), 1), f"{i + 1}/{len(items)}")
        return out

    def close(self) -> None:
        return None

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class LocalExecutor(SerialExecutor):
    """A local process pool. ``initializer(*initargs)`` runs in every worker first (e.g. a
    parent-death watchdog, :func:`die_with_parent`)."""

    kind = "local"

    def __init__(self, workers: int | None = None, *, initializer: Callable | None = None,
                 initargs: tuple = ()) -> None:
        self.workers = int(workers or os.cpu_count() or 1)
        # forkserver: workers start from a clean process, never a fork of a threaded caller
        # (web server, Dask client, progress bars); spawn where forkserver does not exist
        methods = mp.get_all_start_methods()
        ctx = mp.get_context("forkserver" if "forkserver" in methods else "spawn")
        self._pool = ProcessPoolExecutor(max_workers=self.workers, mp_context=ctx,
                                         initializer=initializer, initargs=initargs)

    def submit(self, fn: Callable, *args: Any, **kwargs: Any) -> Future:
        return self._pool.submit(fn, *args, **kwargs)

    def map(self, fn: Callable, items: Iterable, progress: ProgressFn | None = None) -> list:
        items = list(items)
        futs = {self._pool.submit(fn, item): i for i, item in enumerate(items)}
        out: list = [None] * len(items)
        try:
            for n, fut in enumerate(as_completed(futs), start=1):
                out[futs[fut]] = fut.result()
                if progress:
                    progress(n / max(len(items), 1), f"{n}/{len(items)}")
        except BaseException:
            for f in futs:
                f.cancel()
            raise
        return out

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


class DaskExecutor(SerialExecutor):
    """A ``dask.distributed`` cluster (scheduler address such as ``tcp://host:8786``)."""

    kind = "dask"

    def __init__(self, address: str) -> None:
        try:
            from distributed import Client
        except ImportError as e:  # pragma: no cover - distributed is a dependency
            raise OccuflyError(f"--dask needs the 'distributed' package ({e})") from None
        try:
            self.client = Client(address, timeout="10s")
        except (OSError, TimeoutError) as e:
            raise OccuflyError(f"cannot connect to the Dask scheduler at {address!r}: {e}") from None
        self.address = address
        self.workers = max(1, len(self.client.scheduler_info().get("workers", {})))

    def submit(self, fn: Callable, *args: Any, **kwargs: Any):
        return self.client.submit(fn, *args, pure=False, **kwargs)

    def map(self, fn: Callable, items: Iterable, progress: ProgressFn | None = None) -> list:
        from distributed import as_completed as dask_completed

        items = list(items)
        if not items:
            return []
        futs = self.client.map(fn, items, pure=False)
        index = {f.key: i for i, f in enumerate(futs)}
        out: list = [None] * len(items)
        try:
            for n, fut in enumerate(dask_completed(futs), start=1):
                out[index[fut.key]] = fut.result()
                if progress:
                    progress(n / len(items), f"{n}/{len(items)}")
        except BaseException:
            self.client.cancel(futs)
            raise
        return out

    def close(self) -> None:
        self.client.close()


def die_with_parent(parent_pid: int, interval_s: float = 0.5) -> None:
    """Make this (worker) process exit when ``parent_pid`` or its own parent is gone.

    Linux: ``PR_SET_PDEATHSIG`` = SIGKILL (the kernel kills us when the parent thread exits);
    everywhere: a daemon thread that checks every ``interval_s`` that ``parent_pid`` is alive
    and our parent has not changed (a forkserver between us and the caller exits when the
    caller dies), then ``os._exit(70)``. Use as a pool ``initializer``.
    """
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
    ppid = os.getppid()

    def watch() -> None:
        while True:
            if os.getppid() != ppid or not pid_alive(parent_pid):
                os._exit(70)
            time.sleep(interval_s)

    if os.getppid() != ppid or not pid_alive(parent_pid):
        os._exit(70)
    threading.Thread(target=watch, name="occufly-parent-watchdog", daemon=True).start()


def get_executor(dask_address: str | None = None, workers: int | None = None, *,
                 die_with_caller: bool = False) -> SerialExecutor:
    """The executor for fan-out work: Dask when ``dask_address`` is given (or the
    ``OCCUFLY_DASK`` environment variable is set), else a local process pool with ``workers``
    processes (default: CPU count); ``workers`` 0 or 1 runs in-process.
    ``die_with_caller``: local workers exit when the calling process dies
    (:func:`die_with_parent`)."""
    address = dask_address or os.environ.get("OCCUFLY_DASK") or None
    if address:
        return DaskExecutor(address)
    if workers is not None and workers <= 1:
        return SerialExecutor()
    if die_with_caller:
        return LocalExecutor(workers, initializer=die_with_parent, initargs=(os.getpid(),))
    return LocalExecutor(workers)


# ---- BLAS threads ----------------------------------------------------------------------------
_blas_lock = None


def _openblas_libs() -> list:
    """(get, set) ctypes functions of every OpenBLAS loaded in this process (numpy's, scipy's)."""
    out = []
    try:
        paths = sorted({ln.split()[-1] for ln in open("/proc/self/maps") if "openblas" in ln.lower()
                        and ln.split()[-1].startswith("/")})
    except OSError:
        return out
    for p in paths:
        try:
            lib = ctypes.CDLL(p)
        except OSError:
            continue
        for get, set_ in (("scipy_openblas_get_num_threads64_", "scipy_openblas_set_num_threads64_"),
                          ("scipy_openblas_get_num_threads", "scipy_openblas_set_num_threads"),
                          ("openblas_get_num_threads64_", "openblas_set_num_threads64_"),
                          ("openblas_get_num_threads", "openblas_set_num_threads")):
            if hasattr(lib, get) and hasattr(lib, set_):
                out.append((getattr(lib, get), getattr(lib, set_)))
                break
    return out


class single_threaded_blas:  # noqa: N801 - used as a context manager
    """Context manager: OpenBLAS runs on one thread inside (restored on exit).

    Many tiny matrix products (e.g. 100 x 3 by 3 x 2,700 in the kNN boundary pass) are ~40x
    slower with OpenBLAS's thread pool than on one thread (measured 2.1 ms vs 0.05 ms CPU per
    product on the shared 2-core machine) and the result is the same: OpenBLAS splits a
    product over output blocks, each computed by the same kernel. No-op where OpenBLAS cannot
    be found (other BLAS, non-Linux)."""

    def __enter__(self):
        global _blas_lock
        if _blas_lock is None:
            _blas_lock = threading.RLock()
        _blas_lock.acquire()
        self._saved = []
        try:
            for get, set_ in _openblas_libs():
                n = int(get())
                self._saved.append((set_, n))
                if n != 1:
                    set_(1)
        except Exception:  # noqa: BLE001 - never fail a computation over a thread setting
            pass
        return self

    def __exit__(self, *exc) -> None:
        try:
            for set_, n in self._saved:
                if n != 1:
                    set_(n)
        finally:
            _blas_lock.release()
