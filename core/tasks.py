"""Running independent tasks through an executor, with a progress bar.

Shared by every stage whose items (frames, tiles) are independent: they take
any ``concurrent.futures.Executor`` (None runs in this process).
"""

from __future__ import annotations

import contextlib
from collections import deque
from concurrent.futures import Executor, Future, as_completed, wait
from itertools import islice
from typing import Callable, Iterable, Iterator, Sequence, TypeVar

from tqdm import tqdm

T = TypeVar("T")
R = TypeVar("R")


def executor_workers(executor: Executor | None) -> int:
    """Tasks ``executor`` runs at once, for sizing how many to keep in flight. The
    ``concurrent.futures`` interface has no public way to ask, so an executor says it with a
    ``max_workers`` attribute or property (an int ≥ 1: the Dask executor's count of worker
    threads); else a process or thread pool's ``_max_workers``; else 1 (None: this process,
    a serial executor, or one that does not say)."""
    for name in ("max_workers", "_max_workers"):
        n = getattr(executor, name, None)
        if isinstance(n, int) and not isinstance(n, bool) and n >= 1:
            return n
    return 1


#: Tasks kept in flight per worker by :func:`in_flight`.
IN_FLIGHT_PER_WORKER = 8


def in_flight(executor: Executor | None) -> int:
    """The ``window`` of :func:`ordered_results` for tasks of uneven sizes whose results are small
    (statistics, a file's name): results are taken in task order, so with a window of a few
    tasks per worker a long task leaves the other workers idle once they have run the tasks
    behind it; :data:`IN_FLIGHT_PER_WORKER` per worker keeps them busy."""
    return IN_FLIGHT_PER_WORKER * executor_workers(executor)


def run_tasks(fn: Callable[[T], R], tasks: Sequence[T], executor: Executor | None = None,
              desc: str = "", progress: bool | None = None) -> list[R]:
    """Apply ``fn`` to every task; results in completion order.

    progress: None shows a bar on a terminal only (quiet in CI), True/False force it.
    The first task to raise stops the loop and its exception propagates.
    """
    results: list[R] = []
    with tqdm(total=len(tasks), desc=desc, unit="item", disable=None if progress is None else not progress) as bar:
        if executor is None:
            for task in tasks:
                results.append(fn(task))
                bar.update()
        else:
            futures = [executor.submit(fn, task) for task in tasks]
            with settled(futures):
                for future in as_completed(futures):
                    results.append(future.result())
                    bar.update()
    return results


def ordered_results(fn: Callable[[T], R], tasks: Sequence[T], executor: Executor | None = None,
                    window: int = 4, desc: str = "", progress: bool | None = None) -> Iterator[R]:
    """Yield ``fn(task)`` for every task in task order, with at most ``window`` tasks
    submitted ahead, so a consumer that writes results as they come holds only a
    window of them in memory. Exceptions propagate at the task that raised."""
    with tqdm(total=len(tasks), desc=desc, unit="item", disable=None if progress is None else not progress) as bar:
        if executor is None:
            for task in tasks:
                result = fn(task)
                bar.update()
                yield result
            return
        pending: deque = deque()
        queue = iter(tasks)
        with settled(pending):
            for task in islice(queue, max(1, window)):
                pending.append(executor.submit(fn, task))
            while pending:
                result = pending.popleft().result()
                bar.update()
                for task in islice(queue, 1):
                    pending.append(executor.submit(fn, task))
                yield result


@contextlib.contextmanager
def settled(futures: Iterable[Future]) -> Iterator[None]:
    """On an error (a task's, or run_tasks' consumer's), cancel the queued ``futures`` and wait for
    the running ones before it propagates: no task of this call still writes when the caller
    cleans up after the failure. On Ctrl-C or SIGTERM, or when the consumer of ordered_results
    stops it (GeneratorExit), only cancel: the executor's owner stops the workers."""
    try:
        yield
    except BaseException as e:
        futures = list(futures)
        for future in futures:
            future.cancel()
        if isinstance(e, Exception):
            wait(futures)
        raise
