"""Running independent tasks through an executor, with a progress bar.

Shared by every stage whose items (frames, tiles) are independent: they take
any ``concurrent.futures.Executor`` (None runs in this process).
"""

from __future__ import annotations

from concurrent.futures import Executor, as_completed
from typing import Callable, Sequence, TypeVar

from tqdm import tqdm

T = TypeVar("T")
R = TypeVar("R")


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
            for future in as_completed([executor.submit(fn, task) for task in tasks]):
                results.append(future.result())
                bar.update()
    return results
