"""COLMAP's (glog) messages routed through Python logging: :func:`colmap_log_to_logging`."""

from __future__ import annotations

import contextlib
import logging
import shutil
import tempfile
import threading
from pathlib import Path
from typing import Iterator

from capture.native import pycolmap

logger = logging.getLogger(__name__)

__all__ = ["colmap_log_to_logging"]


_LOG_LOCK = threading.Lock()
_log_depth = 0  # nesting depth of colmap_log_to_logging (only the outermost block redirects)


@contextlib.contextmanager
def colmap_log_to_logging(log: logging.Logger = logger) -> Iterator[None]:
    """Route COLMAP's (glog) messages through Python logging while the block runs.

    COLMAP writes to stderr from C++; inside this block its messages go to a
    temporary log file that a thread forwards line by line: I → ``log.debug``,
    W → ``log.warning``, E/F → ``log.error``. glog is process-global: after
    the block COLMAP logs to stderr again as before (and no longer writes its
    default log files to /tmp). Nested blocks forward through the outermost.
    """
    global _log_depth
    with _LOG_LOCK:
        _log_depth += 1
        outermost = _log_depth == 1
    if not outermost:
        try:
            yield
        finally:
            with _LOG_LOCK:
                _log_depth -= 1
        return

    L = pycolmap.logging
    folder = Path(tempfile.mkdtemp(prefix="bbcity-colmap-log-"))
    prefix = folder / "colmap."
    saved = (L.logtostderr, L.alsologtostderr, L.stderrthreshold)
    levels = {"I": logging.DEBUG, "W": logging.WARNING, "E": logging.ERROR, "F": logging.ERROR}
    stop = threading.Event()
    state = {"offset": 0, "rest": b""}

    def pump(final: bool = False) -> None:
        files = sorted(folder.glob(prefix.name + "*"))
        chunk = b""
        if files:
            with open(files[-1], "rb") as fh:
                fh.seek(state["offset"])
                chunk = fh.read()
                state["offset"] = fh.tell()
        lines = (state["rest"] + chunk).split(b"\n")
        state["rest"] = b"" if final else lines.pop()
        for raw in lines:
            line = raw.decode("utf-8", errors="replace")
            if not line or line[0] not in levels or "] " not in line:
                continue  # the file's header
            log.log(levels[line[0]], "colmap: %s", line.split("] ", 1)[1])

    def run() -> None:
        while not stop.wait(0.2):
            pump()

    L.logtostderr = False
    L.alsologtostderr = False
    L.stderrthreshold = 3  # FATAL only; errors reach the caller through `log`
    L.set_log_destination(L.INFO, str(prefix))
    for level in (L.WARNING, L.ERROR, L.FATAL):
        L.set_log_destination(level, "")  # the INFO file holds every severity
    thread = threading.Thread(target=run, name="colmap-log", daemon=True)
    thread.start()
    try:
        yield
    finally:
        L.set_log_destination(L.INFO, "")  # closes (flushes) the file
        L.logtostderr, L.alsologtostderr, L.stderrthreshold = saved
        stop.set()
        thread.join()
        pump(final=True)
        shutil.rmtree(folder, ignore_errors=True)
        with _LOG_LOCK:
            _log_depth -= 1
