"""Output directories that one run at a time writes: a lock, and the sweep of what dead runs left.

Two runs into one work directory would mix their outputs (recon's spill tiles are
shared), so a run holds an advisory lock on ``.NAME.lock`` beside its output for as
long as it lives; the kernel releases it when the process dies, however it dies.
The holder then owns the output's temporaries: every one that is not its own was
left by a killed run and is removed.

The writers' temporaries, all hidden, are named by :func:`temporary`: a pid-tagged one
is removed once its process is gone; a randomly tagged one (made only beside an output
or directly in it) by the lock holder.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import logging
import os
import re
import shutil
import stat
from pathlib import Path
from typing import Iterator

logger = logging.getLogger(__name__)

#: The longest output name (UTF-8 bytes) kept whole in the hidden files beside it
#: (``.NAME.lock``, ``.NAME.tmp-…``): with the longest tag and suffix they stay within the
#: 255 bytes a file name may have.
MAX_HIDDEN_NAME = 200

_SHORTENED = re.compile(r".*~[0-9a-f]{16}")


def hidden_name(name: str) -> str:
    """The NAME of the hidden files beside an output called ``name`` (its lock, its
    temporaries): ``name`` itself, or, when it is over :data:`MAX_HIDDEN_NAME` bytes, its first
    bytes, ``~`` and 16 hex digits of its SHA-256 (the same in every run: one lock per output)."""
    raw = name.encode("utf-8", "surrogateescape")
    if len(raw) <= MAX_HIDDEN_NAME:
        return name
    head = raw[: MAX_HIDDEN_NAME - 17].decode("utf-8", "ignore")
    return f"{head}~{hashlib.sha256(raw).hexdigest()[:16]}"


_TEMPORARY = re.compile(r"\.(?P<name>.+)\.(?P<kind>tmp|body|build|old)-(?P<tag>[0-9a-z_]+)(?P<suffix>\.\w+)?")
_MKDTEMP_TAG = re.compile(r"[0-9a-z_]{8}")  # tempfile.mkdtemp's random part
_UUID_TAG = re.compile(r"[0-9a-f]{32}")


def temporary(name: str) -> tuple[str, str, int | None] | None:
    """(the output's name, kind, the writer's pid or None) when ``name`` is a temporary one of
    the writers makes, else None: ``.NAME.tmp-PID[.SUFFIX]`` and ``.NAME.body-PID`` (pid),
    ``.NAME.tmp-XXXXXXXX`` and ``.NAME.build-XXXXXXXX`` (tempfile.mkdtemp), ``.NAME.tmp-HEX`` and
    ``.NAME.old-HEX`` (a uuid's 32 hex digits: atomic_dir, replace_dir)."""
    m = _TEMPORARY.fullmatch(name)
    if m is None:
        return None
    kind, tag = m["kind"], m["tag"]
    if kind in ("tmp", "body") and tag.isdigit():
        return m["name"], kind, int(tag)
    if m["suffix"] is not None:
        return None
    random = (kind in ("tmp", "build") and _MKDTEMP_TAG.fullmatch(tag)) or \
        (kind in ("tmp", "old") and _UUID_TAG.fullmatch(tag))
    return (m["name"], kind, None) if random else None


def lock_path(output: os.PathLike | str) -> Path:
    """The lock file of an output directory or file: ``.NAME.lock`` beside it, the output's path
    resolved first (links followed), so that two runs reaching one output through a link and
    through its real path take the same lock."""
    output = Path(output).resolve()
    return output.with_name(f".{hidden_name(output.name)}.lock")


@contextlib.contextmanager
def exclusive_output(output: os.PathLike | str) -> Iterator[Path]:
    """Hold the lock of ``output`` for the ``with`` block; yields ``output``.

    Raises BlockingIOError naming ``output`` (and the holder's pid) when another live
    run holds it. The lock file stays (it is empty of meaning once unlocked).
    """
    output = Path(output)
    path = lock_path(output)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:  # never through a link: a lock planted as a link to another file would truncate that file
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o666)
    except OSError as e:
        if e.errno == errno.ELOOP:
            raise OSError(errno.ELOOP, "the lock file is a symbolic link; remove it (a lock is a plain file)",
                          str(path)) from None
        raise
    try:
        if not stat.S_ISREG(os.fstat(fd).st_mode):
            raise OSError(errno.EINVAL, "the lock file is not a plain file (a FIFO, a device?); remove it", str(path))
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


def _left_by_dead_run(pid: int | None, locked: bool) -> bool:
    if pid is not None:  # named by the writer's pid
        return pid != os.getpid() and not pid_alive(pid)
    return locked  # a random tag: only the lock holder knows nobody else is writing


def sweep_temporaries(root: os.PathLike | str, locked: bool = False) -> list[Path]:
    """Remove the temporaries that dead runs left in ``root``; returns what was removed.

    Temporaries tagged with a pid are removed, at any depth, once that process is gone;
    those with a random tag only directly in ``root`` (where the writers make them) and only
    when ``locked`` (the caller holds :func:`exclusive_output` of ``root``). An output set
    aside by an interrupted replacement (``.NAME.old-HEX`` while NAME is missing) is put
    back, never removed.
    """
    root = Path(root)
    if not root.is_dir() or root.is_symlink():
        return []
    removed: list[Path] = []
    for path in sorted(root.rglob(".*"), key=lambda p: len(p.parts)):  # a directory before its contents
        found = temporary(path.name)
        if found is None or not (path.exists() or path.is_symlink()):
            continue
        if found[2] is None and path.parent != root:
            continue
        removed += _remove_if_dead(path, *found, locked=locked)
    return removed


def sweep_output(output: os.PathLike | str) -> list[Path]:
    """For the holder of ``output``'s lock: remove the temporaries of dead runs beside it
    (``.NAME.*``) and, when it is a directory, in it; returns what was removed."""
    output = Path(output).absolute()
    removed: list[Path] = []
    if output.parent.is_dir():
        for path in sorted(output.parent.iterdir()):
            found = temporary(path.name)
            if found is not None and found[0] == hidden_name(output.name):
                removed += _remove_if_dead(path, *found, locked=True, output=output)
    return removed + sweep_temporaries(output, locked=True)


def _remove_if_dead(path: Path, name: str, kind: str, pid: int | None, locked: bool,
                    output: Path | None = None) -> list[Path]:
    """Remove ``path``, the temporary ``kind`` of the output ``name`` (its :func:`hidden_name`),
    when a dead run left it; a set-aside output goes back to ``output`` (default: ``name``
    beside it) instead, and one whose name was shortened is left alone when ``output`` is
    not given (where it goes back is not known)."""
    if not _left_by_dead_run(pid, locked):
        return []
    if kind == "old":
        if output is None and _SHORTENED.fullmatch(name):
            return []
        if _restore_set_aside(path, output if output is not None else path.with_name(name)):
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
