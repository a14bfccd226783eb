"""What the texture sampling keeps of each view: its image pyramid and z-buffers, per process
(:class:`ViewCache`), and its z-buffers on disk for every worker of a build (:class:`ZbufferStore`).

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
from collections import OrderedDict
from pathlib import Path

import cv2
import numpy as np

from .views import Views
from .voxels import VoxelPoints, zbuffer

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


class ViewCache:
    """Per-process LRU of decoded image pyramids and z-buffers: the cloud's (filled and nearest)
    and, with ``layer`` (the facade layer's blocks as points), the layer's (filled; None without);
    with ``store``, the z-buffers are read from and kept in it. config: a
    :class:`~billboards.sampling.SamplingConfig` (its cache_views, max_distance, zbuffer_scale)."""

    def __init__(self, views: Views, voxels: VoxelPoints | None, config,
                 layer: VoxelPoints | None = None, store: ZbufferStore | None = None):
        self.views, self.voxels, self.config, self.layer, self.store = views, voxels, config, layer, store
        self._entries: OrderedDict[int, tuple] = OrderedDict()
        self.loads = 0  # views decoded and z-buffered so far (misses)

    def get(self, i: int) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray | None]:
        if i in self._entries:
            self._entries.move_to_end(i)
            return self._entries[i]
        self.loads += 1
        image = self.views.image(i)
        pyramid = [image]
        while min(pyramid[-1].shape[:2]) >= 16 and len(pyramid) < 6:
            pyramid.append(cv2.pyrDown(pyramid[-1]))
        kept = None if self.store is None else self.store.load(i)
        filled, nearest, layer = kept if kept is not None else self._zbuffers(i)
        entry = (pyramid, filled, nearest, layer)
        self._entries[i] = entry
        if len(self._entries) > self.config.cache_views:
            self._entries.popitem(last=False)
        return entry

    def _zbuffers(self, i: int) -> tuple:
        """View ``i``'s z-buffers (filled, nearest, the layer's), made, and kept in the store."""
        K, pose, size = self.views.K[i], self.views.world_from_cam[i], self.views.sizes[i]
        filled = nearest = layer = None
        if self.voxels is not None:
            pts = self.voxels.in_view(K, pose, size, self.config.max_distance)
            filled, nearest = zbuffer(pts, self.voxels.origin, K, pose, size, self.config.zbuffer_scale)
        if self.layer is not None:
            pts = self.layer.in_view(K, pose, size, self.config.max_distance)
            layer = zbuffer(pts, self.layer.origin, K, pose, size, self.config.zbuffer_scale)[0]
        if self.store is not None:
            self.store.save(i, (filled, nearest, layer))
        return filled, nearest, layer
