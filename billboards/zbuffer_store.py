"""A view's z-buffers kept on disk for every worker of a build (:class:`ZbufferStore`).

The texture sampling z-buffers each view it uses: the cloud's (filled and nearest) and the facade
layer's. A worker keeps the last views it used in memory (``SamplingConfig.cache_views``), but the
tasks of both workers run all along the street, so without a shared store each view is z-buffered
about twice over. A store is one directory per build whose name hashes what the z-buffers are made
of (the points' counts and origin, the layer blocks, the z-buffer settings), so a worker whose
inputs differ never reads another's; an entry is written whole or not at all (a temporary file
renamed), and one that cannot be read or written only costs its z-buffers being made again.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

#: The z-buffers of one view: the cloud's filled and nearest and the layer's, each (h, w) float32 or None.
SLOTS = ("filled", "nearest", "layer")


def store_key(*parts) -> str:
    """A hex digest of ``parts`` (arrays, numbers, strings, None): what a store's z-buffers depend on."""
    h = hashlib.sha1()
    for part in parts:
        if isinstance(part, np.ndarray):
            a = np.ascontiguousarray(part)
            h.update(f"{a.dtype.str}{a.shape}".encode())
            h.update(a.tobytes())
        else:
            h.update(repr(part).encode())
        h.update(b"\0")
    return h.hexdigest()[:16]


class ZbufferStore:
    """The z-buffers of views by index, under ``directory``."""

    def __init__(self, directory: os.PathLike | str):
        self.directory = Path(directory)

    def load(self, i: int) -> tuple | None:
        """View ``i``'s z-buffers (one per :data:`SLOTS`, None where absent), or None when not kept."""
        try:
            with np.load(self.directory / f"{i:06d}.npz", allow_pickle=False) as z:
                return tuple(z[s] if s in z.files else None for s in SLOTS)
        except (OSError, ValueError, EOFError, KeyError):  # not kept yet, or damaged: made again
            return None

    def save(self, i: int, buffers: tuple) -> None:
        """Keep view ``i``'s z-buffers (one per :data:`SLOTS`, None for none)."""
        path = self.directory / f"{i:06d}.npz"
        tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}.npz")
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            np.savez(tmp, **{s: b for s, b in zip(SLOTS, buffers) if b is not None})
            os.replace(tmp, path)
        except OSError:  # a full disk: the next reader makes them again
            tmp.unlink(missing_ok=True)
