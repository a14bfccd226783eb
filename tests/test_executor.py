"""The executor interface: serial and process pools behave alike; failures leave no workers."""

from __future__ import annotations

import multiprocessing
import time

import pytest

from core.tasks import executor_workers, run_tasks
from bbcity.executor import SerialExecutor, executor_scope, make_executor


def _square(x: int) -> int:
    return x * x


def _nap(x: float) -> float:
    time.sleep(x)
    return x


@pytest.mark.parametrize("workers", [1, 2])
def test_run_tasks_gives_every_result(workers):
    with executor_scope(workers) as ex:
        assert sorted(run_tasks(_square, list(range(20)), ex, progress=False)) == [i * i for i in range(20)]


def test_serial_executor_delivers_exceptions_through_the_future():
    future = SerialExecutor().submit(int, "not a number")
    with pytest.raises(ValueError):
        future.result()


def test_a_failure_cancels_queued_tasks_and_joins_the_workers():
    futures = []
    with pytest.raises(KeyboardInterrupt):
        with executor_scope(2) as ex:
            futures = [ex.submit(_nap, 0.2) for _ in range(40)]
            raise KeyboardInterrupt
    assert sum(f.cancelled() for f in futures) > 30  # at most the running and prefetched ones ran
    assert multiprocessing.active_children() == []  # the pool's workers were joined


def test_workers_must_be_positive():
    with pytest.raises(ValueError, match="at least 1"):
        make_executor(0)


def test_executor_workers_counts_what_runs_at_once():
    from concurrent.futures import ThreadPoolExecutor

    assert executor_workers(None) == 1
    assert executor_workers(SerialExecutor()) == 1
    with make_executor(3) as pool, ThreadPoolExecutor(2) as threads:
        assert (executor_workers(pool), executor_workers(threads)) == (3, 2)


def test_dask_executor_without_dask_is_one_line_naming_the_extra(monkeypatch):
    """Dask is an optional extra: without it, --executor dask is bad input naming how to install it."""
    import sys

    from core.errors import InputError

    monkeypatch.delitem(sys.modules, "bbcity.dask_executor", raising=False)
    monkeypatch.setitem(sys.modules, "distributed", None)  # an import of it fails
    with pytest.raises(InputError, match=r"distributed is not installed.*bbcity\[cluster\]"):
        make_executor(2, kind="dask")
