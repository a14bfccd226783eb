"""The base layer every stage may import, and which imports none of them.

- :mod:`core.errors` — :class:`InputError`, the bad input every stage raises (exit 2);
- :mod:`core.fileio` — atomic writers, validated readers, :class:`DataFormatError`;
- :mod:`core.workdir` — one live run per output (a lock), the hidden names beside an output and the
  sweep of dead runs' temporaries;
- :mod:`core.tasks` — independent tasks through any ``concurrent.futures.Executor``;
- :mod:`core.rigid` — rigid transforms (inverse, nearest rotation);
- :mod:`core.metrics` — image quality numbers (PSNR);
- :mod:`core.memory` — resident and peak memory of this process and its workers, and giving
  memory back (heap trim, mapped pages);
- :mod:`core.signals` — Python's signal handlers kept across native libraries' imports.
"""

from .fileio import DataFormatError

__all__ = ["DataFormatError"]
