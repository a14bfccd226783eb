"""The life of a ``bbcity`` process: logging (the only place that configures it), Ctrl-C and
SIGTERM, the lock on a command's output, and the exit code of what ends the command.

Exit codes: 0 done; 2 bad input (:class:`core.errors.InputError`, which DataFormatError and
UsageError are, and OSError: a file-system error), one line naming it; 1 an internal error
(anything else: a bug in bbcity or a library, one line asking for a report, the traceback
under -v) or a worker process that died; 130 interrupted (Ctrl-C).
"""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import re
import signal
import sys
import threading
import time
from pathlib import Path
from typing import Callable

from core.errors import InputError
from core.workdir import owned_output

from .commands.common import absolute_paths, check_own_output, executor_options, logger
from .profiling import ProcessCost, profiled
from .worker import tune_allocator


def run(build_parser: Callable, argv: list[str] | None = None) -> int:
    """Run the command line ``argv`` (default: the process's arguments) of the parser
    ``build_parser()`` makes; return the exit code."""
    # Ctrl-C may land while a library is being imported (parsing already imports the viewer's),
    # where it can surface as another error (an ImportError): one line and 130 all the same
    interrupted = threading.Event()
    start = time.perf_counter()

    def on_interrupt(signum, frame):
        interrupted.set()
        raise KeyboardInterrupt

    # signals reach the main thread only; an ignored SIGINT (a background job of a shell script) stays ignored
    ours = threading.current_thread() is threading.main_thread() and \
        signal.getsignal(signal.SIGINT) is signal.default_int_handler
    previous = signal.signal(signal.SIGINT, on_interrupt) if ours else None
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        datefmt="%H:%M:%S")  # before parsing, so that even an early error is a log line
    try:
        return _main(build_parser, argv, start)
    except BaseException:
        if not interrupted.is_set():
            raise
        logger.error("interrupted")
        return 130
    finally:
        if ours and previous is not None:
            signal.signal(signal.SIGINT, previous)


def _main(build_parser: Callable, argv: list[str] | None, start: float) -> int:
    args = build_parser().parse_args(argv)
    logging.getLogger().setLevel(logging.DEBUG if args.verbose else logging.WARNING if args.quiet else logging.INFO)
    tune_allocator()
    # SIGTERM unwinds like Ctrl-C: atomic writers clean up and pool workers are killed
    signal.signal(signal.SIGTERM, lambda signum, frame: sys.exit(128 + signum))
    try:
        if hasattr(args, "executor") and executor_options(args)["kind"] == "dask":  # a contradiction: one line
            absolute_paths(args)
        # every writing command names its output --out: one live run at a time writes it
        out = getattr(args, "out", None)
        if out is not None and not _writes_file(args):
            _check_directory(out)
            own = getattr(args, "own_output", None)
            if own is not None:
                check_own_output(out, own)
        with owned_output(out) if out is not None else contextlib.nullcontext():
            with profiled(args.profile) if args.profile is not None else contextlib.nullcontext():
                code = args.func(args)
        if not code:
            logger.info("%s: %s", args.command, ProcessCost.since(start).line())
        return code
    # one line for the user; -v adds the traceback
    except InputError as e:  # DataFormatError and UsageError included
        logger.error("%s", e, exc_info=args.verbose)
        return 2
    except OSError as e:  # a file-system error: read-only, full, a name too long, a file where a directory goes
        logger.error("%s", os_error_line(e, getattr(args, "out", None)), exc_info=args.verbose)
        return 2
    except KeyboardInterrupt:
        logger.error("interrupted")
        return 130
    except Exception as e:
        if not worker_died(e):
            # not bad input: a bug in bbcity or a library; -v shows where
            logger.error("internal error, please report: %s: %s", type(e).__name__, e, exc_info=args.verbose)
            return 1
        logger.error("a worker process died (killed, or out of memory: try fewer --workers); what finished is kept, "
                     "and running the command again resumes (%s)", type(e).__name__, exc_info=args.verbose)
        return 1


def _writes_file(args) -> bool:
    """Whether the command writes one file at ``--out`` (its ``writes_file`` default: True, or a
    function of ``--out``), not a directory of its own."""
    writes = getattr(args, "writes_file", False)
    return writes(args.out) if callable(writes) else writes


def _check_directory(out: Path) -> None:
    """Refuse a file where a command writes a directory before any work."""
    if (out.exists() or out.is_symlink()) and not out.is_dir():
        raise NotADirectoryError(errno.ENOTDIR, "exists and is not a directory; not writing over it", str(out))


def worker_died(error: BaseException) -> bool:
    """Whether ``error`` says a worker process died under a task: the local pool's
    BrokenProcessPool, Dask's KilledWorker (named, not imported: Dask loads only with --executor dask)."""
    from concurrent.futures.process import BrokenProcessPool

    return isinstance(error, BrokenProcessPool) or type(error).__name__ == "KilledWorker"


#: numpy's message for a write to a file that stopped short (``ndarray.tofile``), without an errno.
SHORT_WRITE = re.compile(r"(\d+) requested and (\d+) written")


def os_error_line(error: OSError, out: Path | None = None) -> str:
    """One line naming the path(s) and the problem of a file-system error; one that names no
    file (a write through a file object) names the command's output ``out``."""
    if error.strerror is None:
        short = SHORT_WRITE.fullmatch(str(error))
        if short and out is not None:  # numpy's tofile: no errno, the device is full (or over a quota)
            return (f"{out}: No space left on device (or over a quota): a write of {short[1]} items "
                    f"stopped at {short[2]}")
        return str(error)
    paths = [str(p) for p in (error.filename, error.filename2) if p is not None]
    if paths:
        return f"{' → '.join(paths)}: {error.strerror}"
    return f"{out}: {error.strerror} (while writing it)" if out is not None else error.strerror


def exit_process(code: int) -> None:
    """End the process with ``code``. After Ctrl-C (130) the exit skips the libraries' exit
    handlers: one interrupted while it was being imported (Open3D) can fail in them."""
    if code == 130:
        logging.shutdown()
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    sys.exit(code)
