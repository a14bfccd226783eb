"""The methods a novel-view evaluation scores: callables ``(K (3, 3), world_from_cam (4, 4),
size (w, h)) → (h, w, 3) uint8``; a callable's ``nbytes`` attribute (when it has one) is its
size. A billboard model (:class:`ModelMethod`) and a Poisson mesh built on first use or
elsewhere (:class:`LazyPoisson`); the point projection is :class:`render.baselines.PointProjector`.
"""

from __future__ import annotations

from concurrent.futures import Future
from typing import Callable

import numpy as np

from billboards.decode import decode_directions
from billboards.fit import quads_of
from billboards.fit_cast import cast_view
from billboards.geometry import KINDS
from billboards.model_set import ModelSet

from .baselines import PoissonMesh
from .poisson_cache import PoissonCache, cached_poisson

BACKGROUND = (0.0, 0.0, 0.0)

#: A method: (K (3, 3), world_from_cam (4, 4), size (w, h)) → (h, w, 3) uint8.
Method = Callable[[np.ndarray, np.ndarray, tuple], np.ndarray]

#: Not a kind of quad (one past them): ground blocks whose texture was synthesised (no camera
#: saw them); :meth:`ModelMethod.kinds` marks their pixels so.
SYNTHESISED = max(KINDS) + 1
_UNUSED_COLOUR = (1.0, 0.0, 1.0)  # background for finding the pixels a model draws (magenta, absent from streets)


class ModelMethod:
    """A billboard model (or a tiled one, a :class:`~billboards.model_set.ModelSet`, every tile a
    view sees drawn) as a method (GPU decode, offscreen), over ``sky`` when given.

    visible: None (every quad) or the indices drawn; nbytes: the model's bytes (a set: its
    tiles' bytes on disk; + the sky's);
    gains: frame → (3,) float64 exposure gain that :func:`~render.eval_scores.evaluate_methods` applies to the
    view of that frame (see :func:`neighbour_gains`); renders: a dict shared by methods of the
    same model and settings, so that each view is drawn once (None: no caching)."""

    def __init__(self, model, sky=None, visible=None, nbytes: int | None = None, decode: str = "gpu",
                 gains: dict[int, np.ndarray] | None = None, renders: dict | None = None):
        self.model, self.sky, self.visible, self.decode = model, sky, visible, decode
        self.gains = gains or {}
        self.renders = renders
        model_bytes = model.bytes if isinstance(model, ModelSet) else model.nbytes()["total"]
        self.nbytes = int(model_bytes + (sky.colours.nbytes if sky is not None else 0) if nbytes is None else nbytes)

    def _draw(self, K, world_from_cam, size, sky, background) -> np.ndarray:
        from .offscreen import render_view

        key = (np.asarray(K).tobytes(), np.asarray(world_from_cam).tobytes(), tuple(size), background)
        if self.renders is not None and key in self.renders:
            return self.renders[key]
        image = render_view(self.model, K, world_from_cam, size, decode=self.decode, visible=self.visible,
                            sky=sky, background=background)
        if self.renders is not None:
            self.renders[key] = image
        return image

    def __call__(self, K, world_from_cam, size) -> np.ndarray:
        return self._draw(K, world_from_cam, size, self.sky, BACKGROUND)

    def kinds(self, K, world_from_cam, size) -> np.ndarray | None:
        """(h, w) int8: the kind of quad the model draws at each pixel (−1: none; :data:`SYNTHESISED`
        for a synthesised ground block), found by ray casting its quads as the renderer places them
        (:func:`billboards.fit_cast.cast_view`); None for a tiled set."""
        if isinstance(self.model, ModelSet):
            return None
        if not hasattr(self, "_quads"):
            m = self.model
            self._quads = quads_of(m.origin, m.centres, m.base_yaw, m.kind, m.voxel_size, m.block_size, m.tile,
                                   m.yaw_offsets, m.pitches, m.pitched_quads, split=m.split, corner_dz=m.corner_dz)
            n, chunk = m.num_billboards, 1024
            self._alpha = np.concatenate([np.rint(decode_directions(m, np.arange(b, min(n, b + chunk)))[..., 3] * 255)
                                          .astype(np.uint8).reshape(-1, m.num_directions, m.tile * m.tile)
                                          for b in range(0, n, chunk)]) if n else np.zeros((0, 1, 1), np.uint8)
        hits = cast_view(self._quads, self._alpha, np.asarray(K, np.float64), np.asarray(world_from_cam, np.float64),
                         size, max_distance=np.inf)
        out = np.full((int(size[1]), int(size[0])), -1, np.int8)
        kind = np.where(self.model.synthesised > 0, SYNTHESISED, self.model.kind)
        out[hits.pixel[:, 1], hits.pixel[:, 0]] = kind[hits.quad]
        return out

    def covered(self, K, world_from_cam, size) -> np.ndarray:
        """(h, w) bool: the pixels the model draws (rendered once more over a colour no texel has)."""
        image = self._draw(K, world_from_cam, size, None, _UNUSED_COLOUR)
        return np.any(image != np.round(np.asarray(_UNUSED_COLOUR) * 255).astype(np.uint8), axis=-1)


def neighbour_gains(exposure: dict | None, frames, camera: int = 0) -> dict[int, np.ndarray]:
    """Frame → (3,) float64 gain of ``camera`` at each of ``frames``, from the gains that
    photometry found for the frames the textures came from (``exposure``: a model's
    ``info["exposure"]``, {"views": [[frame, camera], ...], "gains": [[r, g, b], ...]}):
    geometric interpolation between the nearest frames before and after (the nearest one
    at the ends). A camera's exposure drifts slowly along a drive; the held-out frame's
    own pixels are not used. Empty without ``exposure``."""
    if not exposure:
        return {}
    views = np.asarray(exposure.get("views", []), dtype=np.int64).reshape(-1, 2)
    gains = np.asarray(exposure.get("gains", []), dtype=np.float64).reshape(-1, 3)
    mine = (views[:, 1] == camera) & np.all(gains > 0, axis=1) if len(views) == len(gains) else np.zeros(0, bool)
    if not mine.any():
        return {}
    known = views[mine, 0]
    order = np.argsort(known)
    known, logs = known[order], np.log(gains[mine][order])
    out = {}
    for f in frames:
        out[int(f)] = np.exp([np.interp(f, known, logs[:, k]) for k in range(3)])
    return out


class LazyPoisson:
    """A :class:`PoissonMesh` method built on first use (meshing takes seconds to minutes), or
    taken from ``pending``, a future of :func:`~render.baselines.poisson_arrays`' result meshed
    elsewhere (a worker process: Open3D's Poisson holds the GIL, so a thread of this process
    would stop it drawing; the first call waits for it and raises what the meshing raised);
    built on first use, it is taken from ``cache`` (a :class:`~render.poisson_cache.PoissonCache`
    of the cloud) when that holds it, and kept there when made; freed by :meth:`release` once
    its views are scored."""

    def __init__(self, cloud: dict, depth: int, trim_quantile: float, pending: Future | None = None,
                 cache: PoissonCache | None = None):
        self.cloud, self.depth, self.trim_quantile = cloud, int(depth), float(trim_quantile)
        self.cache = cache
        self.mesh: PoissonMesh | None = None
        self.nbytes: int | None = None
        self.seconds: float | None = None
        self._pending = pending

    def _adopt(self, mesh: PoissonMesh) -> None:
        self.mesh, self.nbytes, self.seconds = mesh, mesh.nbytes, mesh.seconds

    def __call__(self, K, world_from_cam, size) -> np.ndarray:
        if self._pending is not None:
            pending, self._pending = self._pending, None
            self._adopt(PoissonMesh.from_arrays(pending.result()))
        if self.mesh is None:
            self._adopt(PoissonMesh.from_arrays(cached_poisson(self.cache, lambda: self.cloud, self.depth,
                                                               self.trim_quantile, self.cloud["viewpoints"])))
        return self.mesh.render(K, world_from_cam, size)

    def release(self) -> None:
        self.mesh = None

