"""Timing a block of the benchmark: wall and CPU seconds and peak resident memory, and the
median of several runs (shared machines are noisy)."""

from __future__ import annotations

import statistics
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Callable, Iterator

from core.memory import rss_bytes


@dataclass
class Measurement:
    """wall and cpu seconds, and the peak resident memory above the start, bytes."""

    wall: float = 0.0
    cpu: float = 0.0
    peak_rss: int = 0


@contextmanager
def measure() -> Iterator[Measurement]:
    """Time a block (wall, CPU) and sample its peak RSS every 5 ms."""
    m = Measurement()
    base = rss_bytes()
    peak = [base]
    stop = threading.Event()

    def sample() -> None:
        while not stop.wait(0.005):
            peak[0] = max(peak[0], rss_bytes())

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    w0, c0 = time.perf_counter(), time.process_time()
    try:
        yield m
    finally:
        m.wall = time.perf_counter() - w0
        m.cpu = time.process_time() - c0
        stop.set()
        sampler.join()
        m.peak_rss = max(peak[0], rss_bytes()) - base


def median_of(fn: Callable[[], object], repeats: int) -> Measurement:
    """Run ``fn`` ``repeats`` times; the median wall/cpu and the largest peak."""
    runs = []
    for _ in range(repeats):
        with measure() as m:
            fn()
        runs.append(m)
    return Measurement(statistics.median(r.wall for r in runs), statistics.median(r.cpu for r in runs),
                       max(r.peak_rss for r in runs))
