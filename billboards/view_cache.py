"""The images and z-buffers a sampling process reads: each view's decoded image pyramid and
z-buffers, kept while they fit (:class:`ViewCache`), since neighbouring billboards and the fit
read the same views again."""

from __future__ import annotations

from collections import OrderedDict

import cv2
import numpy as np

from core.memory import available_bytes

from .views import Views
from .voxels import VoxelPoints, zbuffer


class ViewCache:
    """Per-process LRU of decoded image pyramids and z-buffers: the cloud's (filled and nearest)
    and, with ``layer`` (the facade layer's blocks as points), the layer's (filled; None without).
    config: the :class:`~billboards.sampling.SamplingConfig` (z-buffers' scale and reach; at most
    ``cache_views`` views kept, within ``cache_share`` of the memory free when it is made)."""

    def __init__(self, views: Views, voxels: VoxelPoints | None, config,
                 layer: VoxelPoints | None = None):
        self.views, self.voxels, self.config, self.layer = views, voxels, config, layer
        self._entries: OrderedDict[int, tuple] = OrderedDict()
        self.loads = 0  # views decoded and z-buffered so far (misses)
        self.budget, self.nbytes = available_bytes() * config.cache_share, 0

    def get(self, i: int) -> tuple[list[np.ndarray], np.ndarray, np.ndarray, np.ndarray | None]:
        if i in self._entries:
            self._entries.move_to_end(i)
            return self._entries[i]
        self.loads += 1
        image = self.views.image(i)
        pyramid = [image]
        while min(pyramid[-1].shape[:2]) >= 16 and len(pyramid) < 6:
            pyramid.append(cv2.pyrDown(pyramid[-1]))
        K, pose, size = self.views.K[i], self.views.world_from_cam[i], self.views.sizes[i]
        if self.voxels is not None:
            pts = self.voxels.in_view(K, pose, size, self.config.max_distance)
            filled, nearest = zbuffer(pts, self.voxels.origin, K, pose, size, self.config.zbuffer_scale)
        else:
            filled = nearest = None
        layer = None
        if self.layer is not None:
            pts = self.layer.in_view(K, pose, size, self.config.max_distance)
            layer = zbuffer(pts, self.layer.origin, K, pose, size, self.config.zbuffer_scale)[0]
        entry = (pyramid, filled, nearest, layer)
        self._entries[i] = entry
        self.nbytes += _entry_bytes(entry)
        while len(self._entries) > 1 and (len(self._entries) > self.config.cache_views or self.nbytes > self.budget):
            self.nbytes -= _entry_bytes(self._entries.popitem(last=False)[1])
        return entry


def _entry_bytes(entry: tuple) -> int:
    pyramid, *zbuffers = entry
    return sum(a.nbytes for a in pyramid) + sum(z.nbytes for z in zbuffers if z is not None)
