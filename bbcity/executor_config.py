"""Where a stage's tasks run: the executor kinds and their settings (:class:`ExecutorConfig`)."""

from __future__ import annotations

from dataclasses import dataclass

from core.errors import InputError

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
