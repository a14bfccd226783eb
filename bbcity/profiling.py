"""Where a command's seconds go: cProfile of the process and of every pool worker, merged.

``bbcity --profile DIR COMMAND …`` profiles the command's process and sets
:data:`PROFILE_ENV` so that each worker it starts (:mod:`bbcity.worker`) profiles the
tasks it runs; each process writes its statistics to ``DIR/<role>-<pid>.prof``
(pstats' format: ``python -m pstats`` and snakeviz read them). :func:`summarise` merges
them into one table of the functions with the most time of their own, all processes
together (on this 2-core machine, the CPU seconds of both cores), written to
``DIR/profile.md``. A Dask worker on another machine does not see the variable and is
not profiled.
"""

from __future__ import annotations

import cProfile
import os
import pstats
import resource
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from core.fileio import write_bytes

#: The environment variable that asks a worker to profile its tasks into the directory it names.
PROFILE_ENV = "BBCITY_PROFILE"

_worker_profile: cProfile.Profile | None = None


@dataclass(frozen=True)
class ProcessCost:
    """What a process has cost since ``start`` (a ``time.perf_counter()``): wall seconds, CPU
    seconds (user and system, of the process and of its ended workers: on two busy cores
    about twice the wall time) and the peak resident memory of the process and of its
    largest ended child process (a worker, ffmpeg), bytes (``ru_maxrss``)."""

    wall_s: float
    cpu_s: float
    peak_bytes: int
    worker_peak_bytes: int

    @classmethod
    def since(cls, start: float) -> "ProcessCost":
        own = resource.getrusage(resource.RUSAGE_SELF)
        kids = resource.getrusage(resource.RUSAGE_CHILDREN)
        return cls(time.perf_counter() - start, own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime,
                   own.ru_maxrss * 1024, kids.ru_maxrss * 1024)

    def line(self) -> str:
        """``"12.3 s wall, 20.1 s CPU, peak memory 1.21 GB (largest child process 0.80 GB)"``."""
        workers = f" (largest child process {self.worker_peak_bytes / 1e9:.2f} GB)" if self.worker_peak_bytes else ""
        return (f"{self.wall_s:.1f} s wall, {self.cpu_s:.1f} s CPU, peak memory {self.peak_bytes / 1e9:.2f} GB"
                f"{workers}")


@contextmanager
def profiled(directory: Path) -> Iterator[None]:
    """Profile this process (and, through :data:`PROFILE_ENV`, the workers it starts) into
    ``directory``; the merged table is written to ``directory/profile.md`` at the end."""
    directory = Path(directory).resolve()
    directory.mkdir(parents=True, exist_ok=True)
    for old in directory.glob("*.prof"):  # a table of this run only
        old.unlink()
    previous = os.environ.get(PROFILE_ENV)
    os.environ[PROFILE_ENV] = str(directory)
    profile = cProfile.Profile()
    profile.enable()
    try:
        yield
    finally:
        profile.disable()
        profile.dump_stats(directory / f"main-{os.getpid()}.prof")
        if previous is None:
            os.environ.pop(PROFILE_ENV, None)
        else:
            os.environ[PROFILE_ENV] = previous
        write_bytes(directory / "profile.md", profile_table(summarise(directory)).encode())


def profile_task(fn, args, kwargs):
    """Run one worker task, under this worker's profile when :data:`PROFILE_ENV` names a directory.

    The statistics so far are written after every task: a pool worker ends without running
    exit handlers."""
    global _worker_profile
    directory = os.environ.get(PROFILE_ENV)
    if not directory:
        return fn(*args, **kwargs)
    if _worker_profile is None:
        _worker_profile = cProfile.Profile()
    _worker_profile.enable()
    try:
        return fn(*args, **kwargs)
    finally:
        _worker_profile.disable()
        _worker_profile.dump_stats(Path(directory) / f"worker-{os.getpid()}.prof")


@dataclass(frozen=True)
class FunctionCost:
    """One function's share of a profile, all processes together: seconds spent in the
    function itself (``own_s``), in it and what it called (``cumulative_s``; a function that
    recurses or runs in several processes can exceed the wall time), and its calls."""

    function: str
    own_s: float
    cumulative_s: float
    calls: int


def summarise(directory: Path, top: int = 25) -> list[FunctionCost]:
    """The ``top`` functions by their own time over every ``*.prof`` in ``directory`` (empty: none)."""
    files = sorted(str(p) for p in Path(directory).glob("*.prof"))
    if not files:
        return []
    stats = pstats.Stats(*files)
    rows = []
    for (filename, line, name), (_, calls, own, cumulative, _) in stats.stats.items():
        rows.append(FunctionCost(_where(filename, line, name), float(own), float(cumulative), int(calls)))
    rows.sort(key=lambda r: r.own_s, reverse=True)
    return rows[:top]


def _where(filename: str, line: int, name: str) -> str:
    """``package/module.py:line(name)`` for the project's and the libraries' files, ``{name}`` for built-ins."""
    if filename == "~":
        return name
    parts = Path(filename).parts
    keep = 2 if "site-packages" not in parts else len(parts) - parts.index("site-packages") - 1
    return f"{'/'.join(parts[-min(keep, 3):])}:{line}({name})"


def profile_table(rows: list[FunctionCost]) -> str:
    """The rows as a Markdown table."""
    lines = ["| function | own s | cumulative s | calls |", "|---|---|---|---|"]
    lines += [f"| `{r.function}` | {r.own_s:.2f} | {r.cumulative_s:.2f} | {r.calls} |" for r in rows]
    return "\n".join(lines) + "\n"
