"""The one executor interface every parallel stage runs through.

Stages take a ``concurrent.futures.Executor`` and use only ``submit``; a
process pool today, and tomorrow any other implementation of the same
interface (a Dask ``Client.get_executor()``), runs the same code.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import multiprocessing
import os
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Iterator


_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def tune_allocator(threshold: int = 256 << 20) -> bool:
    """Keep glibc from returning freed memory to the kernel after every large numpy temporary.

    The stages allocate and free megabyte arrays in tight loops; with glibc's
    defaults each one is a fresh mmap whose pages fault in again (a fifth of
    the renderer's time went to the kernel). Process-wide, so only the
    composition root calls it, for the CLI process and every pool worker.
    Returns False where the C library has no mallopt (not glibc).
    """
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        mallopt = libc.mallopt if libc is not None else None
    except (OSError, AttributeError):
        return False
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, threshold)) and bool(mallopt(_M_TRIM_THRESHOLD, 2 * threshold))


class SerialExecutor(Executor):
    """Runs each task immediately in this process (workers = 1, debugging, profiling)."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as e:  # delivered through the future, like a pool would
            future.set_exception(e)
        return future


def default_workers() -> int:
    """One worker per usable core."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:
        return max(1, os.cpu_count() or 1)


def make_executor(workers: int | None = None) -> Executor:
    """A process pool of ``workers`` (default: one per core), or serial for 1.

    Workers are spawned, not forked: Open3D and OpenCV keep thread pools that
    do not survive a fork.
    """
    workers = default_workers() if workers is None else workers
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    if workers == 1:
        return SerialExecutor()
    # One BLAS/OpenMP thread per worker: the pool already fills the cores, and
    # nested thread pools oversubscribe them. Spawned workers inherit this.
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")
    return ProcessPoolExecutor(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                               initializer=tune_allocator)


@contextmanager
def executor_scope(workers: int | None = None) -> Iterator[Executor]:
    """:func:`make_executor` for a ``with`` block that cleans up after failures too.

    On an exception (an error, Ctrl-C, or SIGTERM turned into SystemExit by the
    CLI) queued tasks are cancelled and the workers are joined, so no pool
    process outlives the command.
    """
    executor = make_executor(workers)
    try:
        yield executor
    except BaseException:
        executor.shutdown(wait=True, cancel_futures=True)
        raise
    executor.shutdown(wait=True)
