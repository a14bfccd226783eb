"""Output directories that one run at a time writes: a lock, and the sweep of what dead runs left.

Two runs into one work directory would mix their outputs (recon's spill tiles are
shared), so a run holds an advisory lock on ``.NAME.lock`` beside its output for as
long as it lives; the kernel releases it when the process dies, however it dies.
The holder then owns the output's temporaries: every one that is not its own was
left by a killed run and is removed.

The writers' temporaries, all hidden: ``.NAME.tmp-PID.SUFFIX`` (atomic_path),
``.NAME.body-PID`` (the PLY writer), ``.NAME.tmp-RANDOM``, ``.NAME.build-RANDOM`` and
``.NAME.old-RANDOM`` (directories of the model writer, the build and
:func:`core.fileio.replace_dir`).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import logging
import os
import re
import shutil
from pathlib import Path
from typing import Iterator

logger = logging.getLogger(__name__)

#: hidden names of temporaries: .NAME.KIND-TAG[.SUFFIX]; the tag is a pid, tempfile's 8 random
#: characters or a uuid's hex (8 or 32 digits)
TEMPORARY = re.compile(r"\.(?P<name>.+)\.(?P<kind>tmp|body|build|old)-(?P<tag>[0-9]+|[0-9a-z_]{8}|[0-9a-f]{32})"
                       r"(\.\w+)?")


def lock_path(output: os.PathLike | str) -> Path:
    """The lock file of an output directory or file: ``.NAME.lock`` beside it."""
    output = Path(output).absolute()
    return output.with_name(f".{output.name}.lock")


@contextlib.contextmanager
def exclusive_output(output: os.PathLike | str) -> Iterator[Path]:
    """Hold the lock of ``output`` for the ``with`` block; yields ``output``.

    Raises BlockingIOError naming ``output`` (and the holder's pid) when another live
    run holds it. The lock file stays (it is empty of meaning once unlocked).
    """
    output = Path(output)
    path = lock_path(output)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            raise BlockingIOError(errno.EWOULDBLOCK, f"another bbcity run (pid {holder}) is writing it; wait for "
                                                     "that run to end or stop it", str(output)) from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield output
    finally:
        os.close(fd)  # releases the lock


def pid_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (one of another user counts)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _left_by_dead_run(match: re.Match, locked: bool) -> bool:
    tag = match["tag"]
    if match["kind"] in ("tmp", "body") and tag.isdigit():  # named by the writer's pid
        return int(tag) != os.getpid() and not pid_alive(int(tag))
    return locked  # a random tag: only the lock holder knows nobody else is writing


def sweep_temporaries(root: os.PathLike | str, locked: bool = False) -> list[Path]:
    """Remove the temporaries that dead runs left under ``root``; returns what was removed.

    Temporaries tagged with a pid are removed once that process is gone; those with a
    random tag only when ``locked`` (the caller holds :func:`exclusive_output` of
    ``root``). An output set aside by an interrupted replacement (``.NAME.old-*`` while
    NAME is missing) is put back, never removed.
    """
    root = Path(root)
    if not root.is_dir() or root.is_symlink():
        return []
    removed: list[Path] = []
    for path in sorted(root.rglob(".*"), key=lambda p: len(p.parts)):  # a directory before its contents
        match = TEMPORARY.fullmatch(path.name)
        if match is not None and (path.exists() or path.is_symlink()):
            removed += _remove_if_dead(path, match, locked)
    return removed


def sweep_output(output: os.PathLike | str) -> list[Path]:
    """For the holder of ``output``'s lock: remove the temporaries of dead runs beside it
    (``.NAME.*``) and, when it is a directory, inside it; returns what was removed."""
    output = Path(output).absolute()
    removed: list[Path] = []
    if output.parent.is_dir():
        for path in sorted(output.parent.iterdir()):
            match = TEMPORARY.fullmatch(path.name)
            if match is not None and match["name"] == output.name:
                removed += _remove_if_dead(path, match, locked=True)
    return removed + sweep_temporaries(output, locked=True)


def _remove_if_dead(path: Path, match: re.Match, locked: bool) -> list[Path]:
    if not _left_by_dead_run(match, locked):
        return []
    if match["kind"] == "old" and _restore_set_aside(path, path.with_name(match["name"])):
        return []
    logger.info("removing %s, left by an interrupted run", path)
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)
    return [path]


def _restore_set_aside(old: Path, output: Path) -> bool:
    """A replacement killed between its two renames (:func:`core.fileio.replace_dir`) left the
    previous output set aside as ``old`` and none at ``output``: put it back. Returns whether it did."""
    if old.is_dir() and not old.is_symlink() and not output.exists() and not output.is_symlink():
        logger.warning("restoring %s from %s (a replacement of it was interrupted)", output, old)
        os.rename(old, output)
        return True
    return False


@contextlib.contextmanager
def owned_output(output: os.PathLike | str) -> Iterator[Path]:
    """:func:`exclusive_output` of ``output``, swept of dead runs' temporaries on entry and exit
    (on exit: those of this run's own workers killed by an interruption)."""
    with exclusive_output(output):
        sweep_output(output)
        try:
            yield Path(output)
        finally:
            with contextlib.suppress(OSError):  # never mask the run's own error
                sweep_output(output)
