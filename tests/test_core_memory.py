"""Giving memory back: mapped pages out of the resident set, the C heap's free pages to the kernel."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from core.memory import drop_mapped_pages, trim_heap

MIB = 1 << 20


def mapped_resident_bytes(path: Path) -> int:
    """Resident bytes of this process's mappings of ``path`` (/proc/self/smaps)."""
    total, inside = 0, False
    with open("/proc/self/smaps") as f:
        for line in f:
            head = line.split()
            if head and "-" in head[0] and len(head) >= 5:  # a mapping's first line
                inside = len(head) >= 6 and head[5] == str(path)
            elif inside and head and head[0] == "Rss:":
                total += int(head[1]) * 1024
    return total


@pytest.mark.skipif(not os.path.exists("/proc/self/smaps"), reason="needs Linux /proc")
def test_dropped_pages_leave_the_resident_set_and_read_back_the_same(tmp_path):
    path = tmp_path / "page.npy"
    data = np.arange(8 * MIB, dtype=np.uint32).reshape(2048, -1)  # 32 MiB
    np.save(path, data)
    page = np.load(path, mmap_mode="r")
    assert int(page[::64].sum(dtype=np.uint64)) == int(data[::64].sum(dtype=np.uint64))  # touch every page
    assert mapped_resident_bytes(path) >= 30 * MIB
    assert drop_mapped_pages(page[100:200])  # through a view of the mapping: the whole file goes
    assert mapped_resident_bytes(path) < MIB
    np.testing.assert_array_equal(page[1000:1010], data[1000:1010])  # faults back in from the page cache
    assert not drop_mapped_pages(data)  # an array in memory maps nothing
    assert not drop_mapped_pages(np.zeros(0))


def test_heap_trim_gives_back_freed_blocks_between_live_ones():
    """Blocks below the mmap threshold come from the heap; freeing all but every 50th leaves
    holes that free() keeps; a trim returns them (in a fresh process: a heap of its own)."""
    script = textwrap.dedent("""
        import sys
        from core.memory import rss_bytes, trim_heap
        blocks = [bytearray(b"x" * 65536) for _ in range(3000)]  # 190 MiB, every page touched
        keep = blocks[::50]
        del blocks
        before = rss_bytes()
        ok = trim_heap()
        print(ok, before, rss_bytes())
    """)
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True, text=True, check=True)
    ok, before, after = out.stdout.split()
    if ok != "True":
        pytest.skip("the C library has no malloc_trim (not glibc)")
    assert int(before) - int(after) > 100 * MIB, (before, after)

