"""The one executor interface every parallel stage runs through.

Stages take a ``concurrent.futures.Executor`` and use only ``submit``: a process
pool on this machine (``local``) or a Dask distributed cluster (``dask``,
:mod:`bbcity.dask_executor`) runs the same code.
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
from dataclasses import dataclass
from typing import Iterator

from core.errors import InputError


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


#: What runs the tasks: ``local``, a process pool here; ``dask``, a Dask distributed cluster.
EXECUTORS = ("local", "dask")

#: Times the Dask executor runs a failed task again (a task failing on bad input is not retried).
DEFAULT_RETRIES = 2


@dataclass(frozen=True)
class ExecutorConfig:
    """Where a stage's tasks run."""

    kind: str = "local"                 # local: a process pool here; dask: a Dask distributed cluster
    workers: int | None = None          # processes of the pool or the embedded Dask cluster (None: one per core)
    scheduler: str | None = None        # dask: a running scheduler's address (tcp://host:8786); None: embedded cluster
    retries: int = DEFAULT_RETRIES      # dask: runs again a task that failed other than on bad input

    def __post_init__(self):
        if self.kind not in EXECUTORS:
            raise InputError(f"executor must be one of {', '.join(EXECUTORS)}, got {self.kind!r}")
        if self.workers is not None and (isinstance(self.workers, bool) or not isinstance(self.workers, int)
                                         or self.workers < 1):
            raise InputError(f"workers must be at least 1, got {self.workers}")
        if self.scheduler is not None:
            if self.kind != "dask":
                raise InputError("a scheduler address needs the dask executor")
            if not self.scheduler.strip():
                raise InputError("the scheduler address is empty")
            if self.workers is not None:
                raise InputError("workers sizes a cluster started here; a running scheduler's cluster has the "
                                 "workers started on its machines")
        if isinstance(self.retries, bool) or not isinstance(self.retries, int) or self.retries < 0:
            raise InputError(f"retries must be at least 0, got {self.retries}")


def make_executor(workers: int | None = None, *, kind: str = "local", scheduler: str | None = None,
                  retries: int = DEFAULT_RETRIES) -> Executor:
    """The executor :class:`ExecutorConfig` describes (``kind``, ``workers``, ``scheduler``, ``retries``).

    local: a process pool of ``workers`` (default: one per core), or serial for 1. Workers
    are spawned, not forked: Open3D and OpenCV keep thread pools that do not survive a fork.
    dask: a :class:`bbcity.dask_executor.DaskExecutor` on an embedded cluster of ``workers``
    processes, or on the cluster of the running ``scheduler``.
    """
    config = ExecutorConfig(kind, workers, scheduler, retries)
    workers = default_workers() if workers is None else workers
    if config.kind == "dask":  # its nannies start each worker with one BLAS/OpenMP thread
        from .dask_executor import DaskExecutor

        if config.scheduler is not None:
            return DaskExecutor.connect(config.scheduler, config.retries)
        return DaskExecutor.embedded(workers, config.retries)
    if workers == 1:
        return SerialExecutor()
    # One BLAS/OpenMP thread per worker: the pool already fills the cores, and
    # nested thread pools oversubscribe them. Spawned workers inherit this.
    for name in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(name, "1")
    return WorkerPool(workers)


@contextmanager
def executor_scope(workers: int | None = None, *, kind: str = "local", scheduler: str | None = None,
                   retries: int = DEFAULT_RETRIES) -> Iterator[Executor]:
    """:func:`make_executor` for a ``with`` block that cleans up after failures too.

    On an error queued tasks are cancelled and the running ones finish; on Ctrl-C
    or SIGTERM (turned into SystemExit by the CLI) the workers are killed at once
    (a running Dask scheduler's workers finish the tasks they run). Either way no
    pool or embedded cluster process outlives the command.
    """
    executor = make_executor(workers, kind=kind, scheduler=scheduler, retries=retries)
    try:
        yield executor
    except (KeyboardInterrupt, SystemExit):
        stop = getattr(executor, "stop", None)
        if stop is not None:
            stop()
        raise
    except BaseException:
        executor.shutdown(wait=True, cancel_futures=True)
        raise
    executor.shutdown(wait=True)
