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
import pickle
import signal
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Iterator


_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_PR_SET_PDEATHSIG = 1


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


def die_with_parent(parent_pid: int) -> bool:
    """Have the kernel kill this process when its parent dies (Linux; False elsewhere).

    A pool worker must not outlive a run killed by SIGKILL or the OOM killer: it
    would hold its memory and keep writing. If the parent is already gone, exit now.
    (The kernel watches the thread that started the worker: pools are used from the
    main thread, whose end is the process's.)
    """
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        armed = libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) == 0
    except (OSError, AttributeError, TypeError):
        armed = False
    if os.getppid() != parent_pid:  # the parent died before the signal was armed
        os._exit(1)
    return armed


def _init_worker(parent_pid: int) -> None:
    die_with_parent(parent_pid)
    # Ctrl-C reaches the whole process group; the parent alone handles it (and stops the workers)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    tune_allocator()


class WorkerError(RuntimeError):
    """An exception raised in a pool worker that cannot cross back to the parent as itself."""


def _call_in_worker(fn, args, kwargs):
    """Run one task; an exception that would not survive pickling comes back as a WorkerError
    with its type and message (an unpicklable one would break the whole pool)."""
    try:
        return fn(*args, **kwargs)
    except Exception as e:
        try:
            pickle.loads(pickle.dumps(e))
        except Exception:
            raise WorkerError(f"{type(e).__name__}: {e}") from None
        raise


class WorkerPool(ProcessPoolExecutor):
    """A process pool whose workers die with the parent, ignore Ctrl-C and return every
    exception intact; :meth:`stop` ends them at once."""

    def __init__(self, workers: int):
        super().__init__(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                         initializer=_init_worker, initargs=(os.getpid(),))

    def submit(self, fn, /, *args, **kwargs) -> Future:
        # Workers are started here, and start with Ctrl-C blocked (a signal mask survives exec):
        # one pressed while a worker still imports would print its traceback. The parent gets it
        # once unblocked.
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            return super().submit(_call_in_worker, fn, args, kwargs)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)

    def stop(self) -> None:
        """Cancel queued tasks and kill the workers without waiting for running ones."""
        # killed first: the pool then sees itself broken and shuts down without handing the
        # workers a last message (a worker that answers one can be replaced by a fresh one)
        for process in list((self._processes or {}).values()):
            process.kill()
        self.shutdown(wait=True, cancel_futures=True)


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
    return WorkerPool(workers)


@contextmanager
def executor_scope(workers: int | None = None) -> Iterator[Executor]:
    """:func:`make_executor` for a ``with`` block that cleans up after failures too.

    On an error queued tasks are cancelled and the running ones finish; on Ctrl-C
    or SIGTERM (turned into SystemExit by the CLI) the workers are killed at once.
    Either way no pool process outlives the command.
    """
    executor = make_executor(workers)
    try:
        yield executor
    except (KeyboardInterrupt, SystemExit):
        if isinstance(executor, WorkerPool):
            executor.stop()
        raise
    except BaseException:
        executor.shutdown(wait=True, cancel_futures=True)
        raise
    executor.shutdown(wait=True)
