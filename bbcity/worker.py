"""What runs in a worker process, whichever executor started it.

A pool worker (:mod:`bbcity.executor`) and a Dask worker (:mod:`bbcity.dask_executor`)
both run each task through :func:`call_in_worker` and tune the allocator on start; a pool
worker also dies with its parent and ignores Ctrl-C (:func:`init_worker`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import pickle
import signal

from .profiling import profile_task

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


def init_worker(parent_pid: int) -> None:
    """A pool worker's start (its pool's ``initializer``): it dies with ``parent_pid``, ignores
    Ctrl-C and tunes the allocator."""
    die_with_parent(parent_pid)
    # Ctrl-C reaches the whole process group; the parent alone handles it (and stops the workers)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    tune_allocator()


class WorkerError(RuntimeError):
    """An exception raised in a pool worker that cannot cross back to the parent as itself."""


def call_in_worker(fn, args, kwargs):
    """Run one task (profiled under ``bbcity --profile``: :mod:`bbcity.profiling`); an exception
    that would not survive pickling comes back as a WorkerError with its type and message (an
    unpicklable one would break the whole pool)."""
    try:
        return profile_task(fn, args, kwargs)
    except Exception as e:
        try:
            pickle.loads(pickle.dumps(e))
        except Exception:
            raise WorkerError(f"{type(e).__name__}: {e}") from None
        raise
