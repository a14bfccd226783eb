"""The executor interface on a Dask distributed cluster.

:class:`DaskExecutor` is a ``concurrent.futures.Executor`` whose ``submit`` sends the
task to a Dask cluster: an embedded ``LocalCluster`` of worker processes started here
(one thread each), or any running scheduler. The stages run unchanged: their tasks carry
file paths and small settings, and the workers read their inputs and write their outputs
(atomically) on a file system every worker sees at the same path.

Its futures behave like a process pool's:

- a task that raises fails its future with the task's exception (a ``DataFormatError``
  arrives as itself); an exception that cannot be pickled arrives as a ``WorkerError``;
- a task that fails is run again up to ``retries`` times (Dask's ``retries=``: a worker
  that died, a network file system that hiccuped), except when it fails on bad input
  (``ValueError``, ``DataFormatError`` among them): that fails the same way every time,
  so it comes back at once as the task's result and is raised here, unretried;
- ``cancel()`` never stops a task a worker already runs (no pool can): it returns False
  and the future ends, cancelled, once no worker runs the task any more, so that
  ``core.tasks.settled`` waits for the running tasks as it does with a pool.

This module imports ``distributed``; ``bbcity.executor`` imports it only for
``--executor dask``.
"""

from __future__ import annotations

import asyncio
import logging
import os
import shutil
import signal
import tempfile
import threading
import time
import traceback
from concurrent.futures import Executor, Future
from concurrent.futures import wait as futures_wait
from concurrent.futures._base import CANCELLED, CANCELLED_AND_NOTIFIED, FINISHED

import distributed
from distributed.diagnostics.plugin import WorkerPlugin

from core.errors import InputError

from .executor_config import DEFAULT_RETRIES
from .worker import call_in_worker, tune_allocator

logger = logging.getLogger(__name__)

#: Exceptions that mean bad input (a malformed file, an impossible value): the same task
#: fails the same way again, so it is not retried.
NOT_RETRIED = (ValueError,)

#: Seconds between the polls that watch cancelled tasks until no worker runs them; a task
#: counts as stopped after two polls in a row find it nowhere (a task handed to a worker
#: just before it was cancelled may not have reached the worker at the first).
_POLL_S = 0.05

#: Seconds to wait for a scheduler to answer, and for an embedded cluster to close.
CONNECT_TIMEOUT_S = 20.0
CLOSE_TIMEOUT_S = 10.0


class RemoteTraceback(Exception):
    """The traceback text of an exception raised in a Dask worker (its ``__cause__``)."""

    def __str__(self) -> str:
        return self.args[0] if self.args else ""


class _Raised:
    """A task's bad-input exception carried back as its result, so that Dask does not retry it."""

    def __init__(self, error: BaseException, trace: str):
        self.error = error
        self.trace = trace


def _run_task(fn, args, kwargs):
    """A task on a worker: ``fn(*args, **kwargs)``, with bad input returned as a :class:`_Raised`."""
    try:
        return call_in_worker(fn, args, kwargs)
    except NOT_RETRIED as e:
        return _Raised(e, traceback.format_exc())


def _busy_keys(keys: list, dask_worker=None) -> list:
    """The ``keys`` a worker still holds to run or runs (also cancelled ones whose thread goes on).
    Runs on every worker through ``Client.run``."""
    tasks = dask_worker.state.tasks
    return [k for k in keys if k in tasks and tasks[k].state not in ("memory", "error", "released", "forgotten")]


class _QuietFailures(logging.Filter):
    """Drops a worker's "Compute Failed" record: the task's exception reaches the command,
    which reports it in one line, and a retried task would print its traceback each time."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Compute Failed")


def probe_scheduler(address: str, timeout: float) -> None:
    """Ask ``address`` who it is, all within ``timeout`` seconds: ConnectionError unless a Dask
    scheduler answers. A client alone waits without end on a port that accepts and never
    answers (its timeout covers the connection, not the handshake after it)."""

    async def identity():
        comm = await distributed.comm.connect(address, timeout=timeout)
        try:
            await comm.write({"op": "identity", "reply": True})
            return await comm.read()
        finally:
            await comm.close()

    try:
        reply = asyncio.run(asyncio.wait_for(identity(), timeout))
    except (OSError, asyncio.TimeoutError) as e:
        raise ConnectionError(f"{address}: no Dask scheduler answers within {timeout:g} s "
                              f"({type(e).__name__}{': ' if str(e) else ''}{e})") from None
    if not isinstance(reply, dict) or reply.get("type") != "Scheduler":
        raise ConnectionError(f"{address}: answers, but not as a Dask scheduler")


class WorkerSetup(WorkerPlugin):
    """What every worker does when it joins: the pool workers' allocator tuning (the stages
    allocate and free large arrays in loops); in an embedded cluster also Ctrl-C ignored (the
    command stops the workers) and task failures left to the command to report.
    (BLAS/OpenMP threads are 1 already: a nanny starts its worker with OMP_NUM_THREADS=1.)"""

    name = "bbcity-worker-setup"

    def __init__(self, embedded: bool):
        self.embedded = embedded

    def setup(self, worker) -> None:
        tune_allocator()
        if self.embedded:
            if threading.current_thread() is threading.main_thread():
                signal.signal(signal.SIGINT, signal.SIG_IGN)
            logging.getLogger("distributed.worker").addFilter(_QuietFailures())


class _TaskFuture(Future):
    """A ``concurrent.futures.Future`` following one Dask future (see the module's notes on cancel)."""

    def __init__(self, executor: "DaskExecutor", task: distributed.Future):
        super().__init__()
        self._executor = executor
        self.task: distributed.Future | None = task  # dropped once settled: the worker then frees the result
        self.key = task.key

    def cancel(self) -> bool:
        with self._condition:
            if self._state in (CANCELLED, CANCELLED_AND_NOTIFIED):
                return True
            if self._state == FINISHED:
                return False
        self._executor._cancel(self)
        return False

    def _finish_cancelled(self) -> None:
        """End as cancelled (no worker runs the task), waking ``wait`` and ``as_completed``."""
        if Future.cancel(self):
            self.set_running_or_notify_cancel()

    def _settle(self, task: distributed.Future) -> None:
        """Dask's done callback (in its callback thread): hand the outcome to this future."""
        try:
            status = task.status
            if status == "finished":
                value = task.result()
                if isinstance(value, _Raised):
                    error = value.error
                    error.__cause__ = RemoteTraceback(value.trace)
                    self._set(exception=error)
                else:
                    self._set(result=value)
            elif status == "error":
                error = task.exception()
                self._set(exception=error.with_traceback(task.traceback()))
            elif status == "cancelled" and not self._executor._draining_has(self):
                # cancelled by Dask itself (the client or cluster closing): nothing runs it for us
                self._finish_cancelled()
            # cancelled here: the executor's drain ends it once no worker runs it
        except BaseException as e:  # a lost connection while fetching the result
            self._set(exception=e)
        if self.done():
            self.task = None

    def _set(self, result=None, exception: BaseException | None = None) -> None:
        with self._condition:
            if self._state in (CANCELLED, CANCELLED_AND_NOTIFIED, FINISHED):
                return
        try:
            if exception is not None:
                self.set_exception(exception)
            else:
                self.set_result(result)
        except Exception:  # ended meanwhile (cancelled by the drain)
            pass


class DaskExecutor(Executor):
    """Runs tasks on a Dask cluster through ``client``; owns ``cluster`` when it started one here.

    ``max_workers`` is the number of tasks the cluster runs at once (its workers' threads),
    read by ``core.tasks.executor_workers`` to keep that many tasks in flight.
    """

    def __init__(self, client: distributed.Client, cluster=None, retries: int = DEFAULT_RETRIES):
        if retries < 0:
            raise InputError(f"retries must be at least 0, got {retries}")
        self.client = client
        self.cluster = cluster
        self.retries = retries
        self._lock = threading.Lock()
        self._live: set[_TaskFuture] = set()
        self._draining: dict[_TaskFuture, int] = {}  # cancelled futures → polls in a row that found them stopped
        self._drainer: threading.Thread | None = None
        self._shutdown = False
        self._closed = False
        self._scratch: str | None = None  # an embedded cluster's worker directories

    # --- construction ---------------------------------------------------------------------

    @classmethod
    def embedded(cls, workers: int, retries: int = DEFAULT_RETRIES) -> "DaskExecutor":
        """A ``LocalCluster`` of ``workers`` processes with one thread each on this machine,
        no dashboard, logging warnings only. The workers start with Ctrl-C blocked (a signal
        mask survives exec; the command stops them) and exit when this process dies."""
        quiet_logs()
        scratch = tempfile.mkdtemp(prefix="bbcity-dask-")
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:  # the cluster's threads, and so the worker processes they start, inherit the mask
            # no dashboard; the scheduler's HTTP routes (health, metrics) on a free port, not on 8787,
            # which another cluster may hold; no memory limit (a pool has none: build checks memory)
            cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                               host="127.0.0.1", dashboard_address=None,
                                               scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                                               memory_limit=0, silence_logs=logging.WARNING,
                                               local_directory=scratch)
            try:
                client = distributed.Client(cluster, set_as_default=False)
            except BaseException:
                cluster.close()
                raise
        except BaseException:
            shutil.rmtree(scratch, ignore_errors=True)
            raise
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
        executor = cls(client, cluster, retries)
        executor._scratch = scratch
        try:
            client.register_plugin(WorkerSetup(embedded=True))
        except BaseException:
            executor.stop()
            raise
        return executor

    @classmethod
    def connect(cls, address: str, retries: int = DEFAULT_RETRIES) -> "DaskExecutor":
        """A client of the running scheduler at ``address`` (``tcp://host:8786``). ConnectionError
        when none answers; a warning when it has no workers yet (tasks wait for them)."""
        quiet_logs()
        probe_scheduler(address, CONNECT_TIMEOUT_S)
        try:
            client = distributed.Client(address, timeout=CONNECT_TIMEOUT_S, set_as_default=False)
        except OSError as e:
            raise ConnectionError(f"{address}: no Dask scheduler answers ({e})") from None
        executor = cls(client, None, retries)
        try:
            client.register_plugin(WorkerSetup(embedded=False))
        except BaseException:
            executor._close()
            raise
        if not client.nthreads():
            logger.warning("the Dask scheduler at %s has no workers yet; tasks wait for them", address)
        return executor

    # --- the Executor interface --------------------------------------------------------------

    @property
    def max_workers(self) -> int:
        """Tasks the cluster runs at once: its workers' threads (at least 1)."""
        try:
            return max(1, sum(self.client.nthreads().values()))
        except Exception:
            return 1

    def submit(self, fn, /, *args, **kwargs) -> Future:
        if self._shutdown:
            raise RuntimeError("cannot schedule new futures after shutdown")
        task = self.client.submit(_run_task, fn, args, kwargs, pure=False, retries=self.retries)
        future = _TaskFuture(self, task)
        with self._lock:
            self._live.add(future)
        future.add_done_callback(self._forget)
        task.add_done_callback(future._settle)
        return future

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Stop taking tasks; with ``cancel_futures`` cancel those not run yet; with ``wait``
        wait for the running ones; then close the client (and the embedded cluster)."""
        if self._closed:
            return
        self._shutdown = True
        with self._lock:
            live = list(self._live)
        if cancel_futures:
            for future in live:
                future.cancel()
        if wait:
            futures_wait(live)
        self._close()

    def stop(self) -> None:
        """Ctrl-C or SIGTERM: kill an embedded cluster's workers at once (a running scheduler's
        workers finish the tasks they run) and close."""
        self._shutdown = True
        if self.cluster is None:
            with self._lock:
                tasks = [f.task for f in self._live if f.task is not None]
            try:
                self.client.cancel(tasks)
            except Exception:
                pass
        self._close()

    # --- internals ---------------------------------------------------------------------------

    def _forget(self, future: _TaskFuture) -> None:
        with self._lock:
            self._live.discard(future)
            self._draining.pop(future, None)

    def _draining_has(self, future: _TaskFuture) -> bool:
        with self._lock:
            return future in self._draining

    def _cancel(self, future: _TaskFuture) -> None:
        """Cancel ``future``'s task and have the drain end the future once no worker runs it."""
        with self._lock:
            if future in self._draining or future.done():
                return
            self._draining[future] = -1  # -1: Dask not told yet (told in a batch by the drain)
            if self._drainer is None:
                self._drainer = threading.Thread(target=self._drain, name="bbcity-dask-drain", daemon=True)
                self._drainer.start()

    def _drain(self) -> None:
        """Tell Dask of the cancelled tasks and end each cancelled future once two polls in a
        row find no worker holding its task."""
        while True:
            with self._lock:
                untold = [f for f, n in self._draining.items() if n < 0]
                for f in untold:
                    self._draining[f] = 0
                watched = list(self._draining)
                if not watched:
                    self._drainer = None
                    return
            try:
                if untold:
                    self.client.cancel([f.task for f in untold if f.task is not None])
                time.sleep(_POLL_S)
                keys = [f.key for f in watched]
                busy: set | None = set()
                for found in self.client.run(_busy_keys, keys, on_error="ignore").values():
                    busy.update(found)
            except Exception:  # the client or cluster is closing: nothing runs them for us any more
                busy = None
            stopped = []
            with self._lock:
                for f in watched:
                    if f not in self._draining:
                        continue
                    n = 2 if busy is None else 0 if f.key in busy else self._draining[f] + 1
                    self._draining[f] = n
                    if n >= 2:
                        stopped.append(f)
                        del self._draining[f]
            for f in stopped:
                f._finish_cancelled()

    def _retire_workers(self) -> list[int]:
        """Tell the embedded cluster's nannies not to restart their workers; the workers' process ids."""
        pids = []
        for nanny in list(getattr(self.cluster, "workers", {}).values()):
            try:
                nanny.close_gracefully(reason="bbcity-close")
            except Exception:
                pass
            pid = getattr(nanny, "pid", None)
            if isinstance(pid, int):
                pids.append(pid)
        return pids

    def _close(self) -> None:
        """Close the client; an embedded cluster's workers are killed first (they hold no
        result: every output is on disk, written atomically), which ends them at once where a
        graceful close waits on each, and its scheduler and worker directories go."""
        if self._closed:
            return
        self._closed = True
        self._shutdown = True
        if self.cluster is not None:
            for pid in self._retire_workers():
                try:
                    os.kill(pid, signal.SIGKILL)
                except OSError:
                    pass
        try:
            self.client.close(timeout=CLOSE_TIMEOUT_S)
        except Exception:
            pass
        if self.cluster is not None:
            try:
                self.cluster.close(timeout=CLOSE_TIMEOUT_S)
            except Exception:
                pass
        if self._scratch is not None:
            shutil.rmtree(self._scratch, ignore_errors=True)
        with self._lock:
            left = list(self._live) + list(self._draining)
            self._draining.clear()
        for future in left:  # nothing will finish them now
            if not future.done():
                future._finish_cancelled()


def quiet_logs() -> None:
    """Dask logs its start, connections and shutdown at INFO: warnings only (its import set INFO)."""
    for name in ("distributed", "distributed.client"):
        if logging.getLogger(name).getEffectiveLevel() < logging.WARNING:
            logging.getLogger(name).setLevel(logging.WARNING)
