"""Memory of this process and its workers, read from /proc (Linux; 0 or None elsewhere).

``ru_maxrss`` is not used: Linux carries it from the parent into a child through fork
and exec, so a worker would report the parent's peak. A process's ``VmHWM`` (its peak
resident set) starts afresh at exec.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import mmap
import os

import numpy as np
import psutil


def rss_bytes(pid: int | str = "self") -> int:
    """Resident memory of a process (default this one), bytes; 0 when it has ended."""
    try:
        with open(f"/proc/{pid}/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def peak_rss_bytes(pid: int | str = "self") -> int:
    """Peak resident memory of a process (``VmHWM``), bytes; 0 when it has ended."""
    try:
        with open(f"/proc/{pid}/status") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) * 1024  # kB
    except (OSError, ValueError, IndexError):
        pass
    return 0


def available_bytes() -> int:
    """Memory the system can give without swapping (``MemAvailable``, through psutil), bytes."""
    return int(psutil.virtual_memory().available)


def child_pids(pid: int | None = None) -> list[int]:
    """Process ids whose parent is ``pid`` (default this process), scanning /proc."""
    pid = os.getpid() if pid is None else pid
    out = []
    try:
        entries = os.listdir("/proc")
    except OSError:
        return out
    for entry in entries:
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as f:
                    stat = f.read()
            except OSError:
                continue
            if int(stat.rpartition(")")[2].split()[1]) == pid:
                out.append(int(entry))
    return out


def peak_memory() -> dict:
    """The stages' reports' peak memory: ``{"main_mb": this process's peak RSS, "largest_worker_mb":
    the largest peak RSS among its live child processes (its pool workers; None when it has
    none)}``, MB (10⁶ bytes), one decimal. Called while the pool still lives."""
    workers = [peak_rss_bytes(p) for p in child_pids()]
    workers = [b for b in workers if b > 0]
    return {"main_mb": round(peak_rss_bytes() / 1e6, 1),
            "largest_worker_mb": round(max(workers) / 1e6, 1) if workers else None}


@functools.cache
def _malloc_trim():
    """glibc's ``malloc_trim`` (None elsewhere), looked up once (find_library runs ldconfig)."""
    name = ctypes.util.find_library("c")
    try:
        return ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        return None


def trim_heap() -> bool:
    """Return the C heap's free pages to the kernel (glibc ``malloc_trim(0)``: every arena, free
    pages in the middle too). Freed texture-sized blocks otherwise stay resident where the
    allocator put them in its heap; a viewer that uploads and releases tiles would keep the
    largest set it ever held. False where the C library has no malloc_trim (not glibc)."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


def drop_mapped_pages(array: np.ndarray) -> bool:
    """Take the pages of the file that ``array`` (a ``numpy.memmap`` or a view of one) maps out of
    this process's resident set; they stay in the page cache and fault back in on the next read.
    For data read once (uploaded, warmed): a mapping otherwise counts every page it was read
    through as resident while it lives. False when ``array`` maps no file."""
    base = array
    while base is not None and getattr(base, "_mmap", None) is None:
        base = base.base if isinstance(base, np.ndarray) else None
    mm = getattr(base, "_mmap", None)
    if mm is None or mm.closed:
        return False
    mm.madvise(mmap.MADV_DONTNEED)
    return True
