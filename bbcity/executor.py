"""The one executor interface every parallel stage runs through.

Stages take a ``concurrent.futures.Executor`` and use only ``submit``: a process
pool on this machine (``local``) or a Dask distributed cluster (``dask``,
:mod:`bbcity.dask_executor`) runs the same code. What each worker runs a task through:
:mod:`bbcity.worker`; the settings: :class:`bbcity.executor_config.ExecutorConfig`.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
from concurrent.futures import Executor, Future, ProcessPoolExecutor
from contextlib import contextmanager
from typing import Iterator

from core.errors import InputError

from .executor_config import DEFAULT_RETRIES, ExecutorConfig
from .worker import call_in_worker, init_worker


class WorkerPool(ProcessPoolExecutor):
    """A process pool whose workers die with the parent, ignore Ctrl-C and return every
    exception intact; :meth:`stop` ends them at once."""

    def __init__(self, workers: int):
        super().__init__(max_workers=workers, mp_context=multiprocessing.get_context("spawn"),
                         initializer=init_worker, initargs=(os.getpid(),))

    def submit(self, fn, /, *args, **kwargs) -> Future:
        # Workers are started here, and start with Ctrl-C blocked (a signal mask survives exec):
        # one pressed while a worker still imports would print its traceback. The parent gets it
        # once unblocked.
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            return super().submit(call_in_worker, fn, args, kwargs)
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
        try:
            from .dask_executor import DaskExecutor
        except ImportError as e:  # an optional extra
            raise InputError(f"--executor dask needs Dask ({e.name} is not installed): "
                             "pip install 'bbcity[cluster]'") from e

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


@contextmanager
def process_scope(workers: int = 1) -> Iterator[Executor]:
    """A :class:`WorkerPool` of ``workers`` processes, a real process even for one worker
    (:func:`make_executor` runs a single worker's tasks in this process), for work that must
    leave this process (it holds the GIL), for a ``with`` block; on any error its workers are
    killed, not waited for."""
    executor = WorkerPool(workers)
    try:
        yield executor
    except BaseException:  # what runs there is of no use now: not waited for
        executor.stop()
        raise
    executor.shutdown(wait=True)
