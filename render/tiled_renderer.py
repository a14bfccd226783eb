"""A tiled model drawn out of core: :class:`TiledRenderer`.

One frame, one clear, one sky pass, one depth buffer: each resident tile whose bounds meet the
view frustum is drawn by its own :class:`~render.renderer.BillboardRenderer` into the bound
framebuffer, with camera matrices relative to that tile's origin (float64 on the CPU, float32
relative positions on the GPU, as for one model), nearest tile first (with level of detail, the
frame's impostor images and refreshes of decoded tiles shared among them, nearest first). Nothing is cleared between
tiles, so a set draws the image its billboards would draw as one model, up to each tile's
float32 origin (and the order of exactly coincident quads of different tiles).

Which tiles are resident follows the eye (:mod:`render.paging`): tiles are loaded in a
background thread (memory-mapped, nearest and visible first, prefetching along the direction of
travel), uploaded on the GL thread a bounded amount per frame in frames with time left
(:class:`~render.paging.FrameBudget`), and released, farthest first,
when the GPU budget would be exceeded or they fall behind ``drop_radius``; a tile uploaded far
from the eye is decoded for the view over a few frames before it is first drawn (warm-up), so
no frame decodes a whole tile. The renderers of the tiles share their shader programs (one
:class:`~render.program.ProgramCache`) and where impostor images are drawn (one
:class:`~render.impostors.ImpostorStudio`, 4 MB, outside the budget like the framebuffers).
A frame draws what is resident; ``wait`` decides what it waits for first: ``"none"``,
``"near"`` (the visible tiles within ``wait_radius`` of the eye: what the first frame waits for
by default, not the city) or ``"all"`` (every visible tile: offline rendering, exact).

A plain model (a directory, or a :class:`~billboards.model.BillboardModel` in memory) is a set
of one tile, so every front end takes either.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from pathlib import Path

import moderngl
import numpy as np

from billboards.model import BillboardModel
from billboards.model_reader import read_manifest
from billboards.model_set import ModelSet, ModelTile, quad_bounds

from core.errors import InputError

from .camera import ClipPlanes, camera_at_origin, gl_camera
from .context import max_texture_size
from .culling import boxes_outside, check_cull, frustum_planes
from .gpu_bytes import renderer_gpu_bytes, tile_gpu_bound
from .impostors import ImpostorStudio
from .paging import FrameBudget, Motion, PagingConfig, TileLoader, tile_priorities
from .program import ProgramCache
from .renderer import BillboardRenderer, check_decode
from .resources import Releasable
from .sky import SkyPass
from .target import OffscreenTargets, background_rgb

logger = logging.getLogger(__name__)

WAIT_MODES = ("auto", "none", "near", "all")


def _share(total: int, parts: int, k: int) -> int:
    """Part ``k`` of ``total`` split as evenly as possible among ``parts``, the first ones larger."""
    share, extra = divmod(total, parts)
    return share + (k < extra)


def as_model_set(source) -> tuple[ModelSet, dict[int, BillboardModel]]:
    """(set, tiles already in memory) of ``source``: a :class:`ModelSet` (nothing in memory) or a
    :class:`BillboardModel` (a set of one tile, that model)."""
    if isinstance(source, ModelSet):
        return source, {}
    if isinstance(source, BillboardModel):
        lo, hi = quad_bounds(source)
        tile = ModelTile("model", (0, 0), lo, hi, source.num_billboards, int(source.nbytes()["total"]), Path("."))
        size = float(np.max(hi[:2] - lo[:2])) if source.num_billboards else 0.0
        info = source.info if isinstance(source.info, dict) else {}
        return ModelSet(Path("."), np.asarray(source.origin, np.float64).copy(), size if size > 0 else 1.0, (tile,),
                        False, info), {0: source}
    raise TypeError(f"a TiledRenderer draws a ModelSet or a BillboardModel, got {type(source).__name__}")


class _SetExtent:
    """What the camera paths (:mod:`render.paths`) read of a model, for a set: ``origin``, ``info``
    and ``centres`` (the tiles' bound corners relative to the origin, (8t, 3) float32)."""

    def __init__(self, model_set: ModelSet):
        self.origin = np.asarray(model_set.origin, np.float64)
        info = dict(model_set.info)
        if "dataset" not in info and model_set.tiles:  # the build's record of its capture, from a tile
            try:
                tile_info = read_manifest(model_set.tiles[0].path).info
                info.update({k: tile_info[k] for k in ("dataset", "poses") if k in tile_info})
            except (OSError, ValueError):
                pass
        self.info = info
        lo, hi = model_set.lo, model_set.hi
        corners = [np.where(np.array([i >> 2 & 1, i >> 1 & 1, i & 1], bool), hi, lo) for i in range(8)]
        self.centres = (np.concatenate(corners) - self.origin).astype(np.float32).reshape(-1, 3)
        self.num_billboards = model_set.num_billboards


def path_model(source):
    """``source`` (a BillboardModel or a ModelSet) as :mod:`render.paths` reads a model: the model
    itself, or a set's origin, info (the first tile's capture when the set records none) and
    extent."""
    if isinstance(source, ModelSet):
        return _SetExtent(source)
    return source


def merge_stats(totals: dict, part: dict) -> None:
    """Add one tile's renderer stats to ``totals``: numbers summed, flags or-ed, lists
    (LOD counts) element-wise."""
    for key, value in part.items():
        if isinstance(value, bool):
            totals[key] = bool(totals.get(key, False)) or value
        elif isinstance(value, (int, float, np.integer, np.floating)):
            totals[key] = totals.get(key, 0) + value
        elif isinstance(value, list):
            old = totals.get(key, [0] * len(value))
            totals[key] = [a + b for a, b in zip(old, value)]


class _Resident:
    __slots__ = ("renderer", "bound", "bytes")

    def __init__(self, renderer: BillboardRenderer, bound: int):
        self.renderer = renderer
        self.bound = bound
        self.bytes = 0


def _tile_setting(name: str) -> property:
    """A bool setting of every resident tile's renderer, settable between frames (and given to
    the tiles uploaded later)."""
    own = "_" + name

    def get(self) -> bool:
        return getattr(self, own)

    def set(self, value: bool) -> None:
        setattr(self, own, bool(value))
        for r in self.resident.values():
            setattr(r.renderer, name, getattr(self, own))

    return property(get, set)


class TiledRenderer(Releasable):
    """Draws a :class:`~billboards.model_set.ModelSet` (or a plain model) from OpenCV cameras,
    paging its tiles under ``paging.gpu_budget``.

    decode, spherical, interpolate, linear, clip, cull, lod: as for
    :class:`~render.renderer.BillboardRenderer` (each tile's renderer gets them; the occlusion
    modes cull per tile against the frame's shared depth, so hzb reads it back once per tile
    drawn; frustum culling, the default, is the set's natural mode). background:
    the clear colour; sky: a :class:`billboards.sky.Sky` drawn behind the model by
    :meth:`render` (e.g. :func:`billboards.sky.read_sky` of the set's root).

    After each :meth:`draw` / :meth:`render`, ``stats`` holds the tiles' renderer stats summed
    (billboards drawn, quads, tiles decoded, LOD counts, timings) and the paging figures: tiles
    (in the set), tiles_visible (in the frustum), tiles_drawn, tiles_missing (visible within
    ``load_radius`` of the eye, not resident), tiles_resident, tiles_warming (resident, decoded
    for the view before they are drawn: :mod:`render.paging`), tiles_loaded (in host memory),
    loads_in_flight, uploads and releases (this frame), upload_s, wait_s, warm_s,
    warm_decoded_tiles, paging_deferred (frames in a row that skipped paging for lack of time,
    :class:`~render.paging.FrameBudget`), gpu_bytes (measured, resident tiles), gpu_reserved (their bounds),
    gpu_budget (None: no limit), billboards (of the set).
    """

    def __init__(self, ctx: moderngl.Context, source, decode: str = "gpu", *, paging: PagingConfig = PagingConfig(),
                 sky=None, spherical: bool | None = None, interpolate: bool = True, linear: bool = True,
                 background=(0.0, 0.0, 0.0), clip: ClipPlanes = ClipPlanes(), cull: str = "frustum", lod=None):
        self.decode = check_decode(decode)
        self.cull = check_cull(cull)
        self.ctx = ctx
        self.model_set, preloaded = as_model_set(source)
        self.paging, self.clip, self.lod = paging, clip, lod
        self.background = background_rgb(background)
        self._interpolate, self._linear = bool(interpolate), bool(linear)
        self._options = dict(spherical=spherical, background=self.background, clip=clip, cull=cull, lod=lod)
        self.lo, self.hi = self.model_set.lo, self.model_set.hi
        self.origin = np.asarray(self.model_set.origin, np.float64)
        self.resident: dict[int, _Resident] = {}
        self.warming: dict[int, int] = {}  # resident tiles not drawn yet → frames they were visible warming
        self.warm_decoded = 0  # texture tiles the last frame decoded for warming tiles
        self.stats: dict = {}
        self.frames = 0
        self.uploads = self.releases = 0
        self.peak_bytes = self.peak_reserved = 0
        self._too_big: set[int] = set()
        self._frame_uploads = self._frame_releases = 0
        self._paging_stats: dict = {}
        self._released = False
        self.motion = Motion()
        self.frame_budget = FrameBudget(paging)
        self._camera = None  # the frame's camera for the set's origin (prepare)
        self.targets = OffscreenTargets(ctx)
        self.programs = ProgramCache(ctx)  # the tiles' renderers compile once, not on each upload
        self.sky_pass: SkyPass | None = None
        self.studio: ImpostorStudio | None = None  # where every tile's impostor images are drawn
        limit = max_texture_size(ctx)

        def bound(model, decode=decode, lod=lod, cull=cull, limit=limit):
            return tile_gpu_bound(model, decode, lod, limit, cull)

        self.loader = TileLoader(self.model_set, bound, preloaded)
        try:
            if decode == "gpu" and lod is not None and lod.impostors is not None:
                self.studio = ImpostorStudio(ctx, lod.impostors.texels, self.programs)
            if sky is not None:
                self.sky_pass = SkyPass(ctx, sky)
        except BaseException:
            self.release()
            raise

    # -- settings shared by every tile
    interpolate = _tile_setting("interpolate")
    linear = _tile_setting("linear")

    @property
    def num_billboards(self) -> int:
        return self.model_set.num_billboards

    # -- GPU account
    def gpu_bytes(self) -> int:
        """Bytes the resident tiles' renderers hold on the GPU now (measured)."""
        return sum(r.bytes for r in self.resident.values())

    def gpu_reserved(self) -> int:
        """Sum of the resident tiles' bounds (:func:`render.gpu_bytes.tile_gpu_bound`)."""
        return sum(r.bound for r in self.resident.values())

    def _measure(self, i: int) -> int:
        r = self.resident[i]
        parts = renderer_gpu_bytes(r.renderer)
        r.bytes = parts["total"] - parts["targets"]
        return r.bytes

    # -- paging
    def _upload(self, i: int, rank: np.ndarray, protected: set[int], sync: bool) -> int | None:
        """Make tile ``i`` resident, releasing lower-priority tiles (larger ``rank``, not
        ``protected``) while the budget needs room; returns its bound, or None when it does not
        fit (or, unless ``sync``, is not loaded yet)."""
        tile = self.loader.get(i) if sync else self.loader.loaded(i)
        if tile is None:
            return None
        budget = self.paging.gpu_budget
        if budget is not None:
            if tile.bound > budget:
                if i not in self._too_big:
                    self._too_big.add(i)
                    logger.warning("tile %s needs up to %.1f MB of GPU memory, more than the budget of %.1f MB; "
                                   "it is not drawn", self.model_set.tiles[i].name, tile.bound / 2**20, budget / 2**20)
                return None
            reserved = self.gpu_reserved()
            if reserved + tile.bound > budget:
                victims = sorted((j for j in self.resident if j not in protected and rank[j] > rank[i]),
                                 key=lambda j: -rank[j])
                freed, chosen = 0, []
                for j in victims:
                    if reserved - freed + tile.bound <= budget:
                        break
                    chosen.append(j)
                    freed += self.resident[j].bound
                if reserved - freed + tile.bound > budget:
                    return None
                for j in chosen:
                    self._release_tile(j)
        renderer = BillboardRenderer(self.ctx, tile.model, self.decode, interpolate=self._interpolate,
                                     linear=self._linear, programs=self.programs, studio=self.studio,
                                     **self._options)
        self.resident[i] = _Resident(renderer, tile.bound)
        if not sync and self.paging.warm_tiles_per_frame > 0:
            self.warming[i] = 0
        self._measure(i)
        self.uploads += 1
        self._frame_uploads += 1
        return tile.bound

    def _release_tile(self, i: int) -> None:
        r = self.resident.pop(i)
        self.warming.pop(i, None)
        r.renderer.release()
        self.loader.trim()  # llvmpipe's textures are heap memory: give the freed pages back
        self.releases += 1
        self._frame_releases += 1

    def prepare(self, K, world_from_cam, size, wait: str = "auto") -> np.ndarray:
        """Page for a view: release, wait for, upload and queue tiles. Returns the tiles to draw
        (resident and in the frustum), nearest first. ``wait``: see the module notes ("auto":
        "near" on the first frame, "none" after)."""
        if self._released:
            raise RuntimeError("TiledRenderer used after release()")
        if wait not in WAIT_MODES:
            raise InputError(f"wait must be one of {WAIT_MODES}, got {wait!r}")
        if wait == "auto":
            wait = "near" if self.frames == 0 else "none"
        self._frame_uploads = self._frame_releases = 0
        self.frame_budget.begin_frame()
        cfg = self.paging
        t0 = time.perf_counter()
        camera = self._camera = gl_camera(K, world_from_cam, size, self.origin, self.clip)
        view_proj = camera.projection.astype(np.float64) @ camera.view.astype(np.float64)
        visible = ~boxes_outside(frustum_planes(view_proj), self.lo - self.origin, self.hi - self.origin)
        pose = np.asarray(world_from_cam, np.float64)
        eye = pose[:3, 3]
        direction = self.motion.update(eye, pose[:3, 2])
        ahead = eye + cfg.prefetch * direction
        dist, wanted, order = tile_priorities(self.lo, self.hi, eye, ahead, visible, cfg)
        rank = np.empty(len(order), np.int64)
        rank[order] = np.arange(len(order))
        eye_dist = np.sqrt(np.sum(np.maximum(np.maximum(self.lo - eye, eye - self.hi), 0.0) ** 2, axis=1))

        for i in [j for j in self.resident if dist[j] > cfg.drop_radius and not visible[j]]:
            self._release_tile(i)
        if wait == "all":
            must = [int(j) for j in order if visible[j]]
        elif wait == "near":
            must = [int(j) for j in order if visible[j] and eye_dist[j] <= cfg.wait_radius]
        else:
            must = []
        protected = set(must)
        t1 = time.perf_counter()
        for i in must:
            if i not in self.resident and i not in self._too_big:
                self._upload(i, rank, protected, sync=True)
        wait_s = time.perf_counter() - t1
        self.frame_budget.spent(wait_s)
        waited = self._frame_uploads
        budget_bytes = 0
        t2 = time.perf_counter()
        for i in (int(j) for j in order):
            if not wanted[i]:
                break  # the order puts wanted tiles first
            if i in self.resident or i in self._too_big:
                continue
            if self._frame_uploads >= cfg.uploads_per_frame + len(must):
                break
            tile = self.loader.loaded(i)
            if tile is None:
                continue
            if budget_bytes > 0 and budget_bytes + tile.bound > cfg.upload_bytes_per_frame:
                break
            if not self.frame_budget.allow_upload():
                break  # no room in this frame's time: a later frame uploads it
            bound = self._upload(i, rank, protected, sync=False)
            if bound is None:
                break  # no room for the most important tile left: the rest wait
            budget_bytes += bound
        upload_s = time.perf_counter() - t2
        self.frame_budget.spent(upload_s, uploads=self._frame_uploads - waited)
        for i in (int(j) for j in order):
            if not wanted[i] or self.loader.in_flight >= cfg.loads_in_flight:
                break
            if i not in self.resident and i not in self._too_big:
                self.loader.request(i)
        for i in self.loader.indices():
            if i not in self.resident and not wanted[i]:
                self.loader.drop(i)
        for i in [j for j in self.warming if visible[j] and (wait == "all" or eye_dist[j] <= cfg.wait_radius)]:
            del self.warming[i]  # near (or every tile waited for): drawn now, whatever it decodes
        draw = [i for i in self.resident if visible[i]]
        draw.sort(key=lambda i: (eye_dist[i], i))
        self._paging_stats = {
            "tiles": len(self.lo), "tiles_visible": int(visible.sum()), "tiles_drawn": len(draw),
            "tiles_missing": int(sum(1 for i in np.flatnonzero(visible & (eye_dist <= cfg.load_radius))
                                     if i not in self.resident)),
            "tiles_wanted": int(wanted.sum()), "tiles_resident": len(self.resident), "tiles_warming": len(self.warming),
            "tiles_loaded": len(self.loader.indices()), "loads_in_flight": self.loader.in_flight,
            "uploads": self._frame_uploads, "releases": self._frame_releases, "wait_s": wait_s,
            "upload_s": upload_s, "page_s": time.perf_counter() - t0 - wait_s - upload_s,
            "paging_deferred": self.frame_budget.deferred}
        return np.array(draw, np.int64)

    def draw(self, K, world_from_cam, size, wait: str = "auto") -> dict:
        """Page (:meth:`prepare`), then draw every resident visible tile into the bound framebuffer
        (cleared by the caller, depth to 1; the viewport the camera's size). Returns the stats."""
        t0 = time.perf_counter()
        tiles = self.prepare(K, world_from_cam, size, wait)
        totals: dict = {}
        t1 = time.perf_counter()
        self._share_impostor_updates(tiles)
        tiles = self._warm([int(i) for i in tiles if int(i) in self.warming], world_from_cam, tiles)
        self._paging_stats.update(tiles_drawn=len(tiles), tiles_warming=len(self.warming))
        t2 = time.perf_counter()
        # the frame's refreshes (LodConfig.refresh_tiles_per_frame) go to the nearest tiles first
        refresh = None if self.lod is None else self.lod.refresh_tiles_per_frame
        for i in tiles:
            r = self.resident[int(i)].renderer
            part = r.draw(camera_at_origin(self._camera, world_from_cam, r.model.origin), refresh_budget=refresh)
            merge_stats(totals, part)
            if refresh is not None:
                refresh = max(refresh - int(part.get("refreshed_tiles", 0)), 0)
        for i in tiles:
            self._measure(int(i))  # instance buffers grow with what is drawn
        totals["draw_s"] = time.perf_counter() - t2
        paging_s = self._paging_stats["wait_s"] + self._paging_stats["upload_s"] + (t2 - t1)
        self.frame_budget.end_frame(time.perf_counter() - t0 - paging_s)
        totals.update(warm_s=t2 - t1, warm_decoded_tiles=self.warm_decoded)
        used, reserved = self.gpu_bytes(), self.gpu_reserved()
        self.peak_bytes = max(self.peak_bytes, used)
        self.peak_reserved = max(self.peak_reserved, reserved)
        totals.update(self._paging_stats)
        totals.update(gpu_bytes=used, gpu_reserved=reserved, gpu_budget=self.paging.gpu_budget,
                      billboards=self.num_billboards, frame_s=time.perf_counter() - t0)
        totals.setdefault("billboards_drawn", totals.get("instances", 0))
        self.frames += 1
        self.stats = totals
        return totals

    def _warm(self, warming: list[int], world_from_cam, tiles: np.ndarray) -> np.ndarray:
        """Warm the visible ``warming`` tiles (nearest first) within the frame's decode budget; of
        ``tiles`` (nearest first), those to draw: every tile not warming, and those whose warm-up
        left nothing to decode or ran ``warm_frames`` frames."""
        self.warm_decoded = 0
        if not warming:
            return tiles
        t0 = time.perf_counter()
        budget = self.frame_budget.warm_tiles(self.paging.warm_tiles_per_frame)
        for i in warming:
            self.warming[i] += 1
            if self.warm_decoded < budget:  # once the frame's budget is spent, the rest wait
                r = self.resident[i].renderer
                decoded, left = r.warm(camera_at_origin(self._camera, world_from_cam, r.model.origin),
                                       budget - self.warm_decoded)
                self.warm_decoded += decoded
                if left == 0:
                    del self.warming[i]
                    continue
            if self.warming[i] >= self.paging.warm_frames:
                del self.warming[i]
        self.frame_budget.spent(time.perf_counter() - t0, warm_tiles=self.warm_decoded)
        return np.array([i for i in tiles if int(i) not in self.warming], np.int64)

    def _share_impostor_updates(self, tiles: np.ndarray) -> None:
        """Share the frame's impostor images (``ImpostorConfig.updates_per_frame`` and
        ``in_full_updates_per_frame``) among the tiles drawn, nearest first, as one model's renderer
        would make them: one tile does not make its own quota while the rest of the frame waits."""
        config = None if self.lod is None else self.lod.impostors
        if config is None or len(tiles) == 0:
            return
        for k, i in enumerate(tiles):
            imp = self.resident[int(i)].renderer.impostors
            if imp is not None:
                imp.config = dataclasses.replace(
                    config, updates_per_frame=_share(config.updates_per_frame, len(tiles), k),
                    in_full_updates_per_frame=_share(config.in_full_updates_per_frame, len(tiles), k))

    def render(self, K, world_from_cam, size, wait: str = "auto") -> np.ndarray:
        """(h, w, 3) uint8 image of the set from the OpenCV camera K (3, 3), world_from_cam (4, 4)
        float64, size = (w, h): one clear, the sky (if any), every resident visible tile."""
        size = (int(size[0]), int(size[1]))
        self.targets.begin(size, self.background)
        if self.sky_pass is not None:
            self.sky_pass.draw(K, world_from_cam, size)
        self.draw(K, world_from_cam, size, wait)
        t0 = time.perf_counter()
        image = self.targets.read(size)
        self.stats["read_s"] = time.perf_counter() - t0
        return image

    def finish(self) -> None:
        self.ctx.finish()

    def release(self) -> None:
        """Release every resident tile, the sky pass and the framebuffers, stop the loader
        (idempotent)."""
        if self._released:
            return
        self._released = True
        for i in list(self.resident):
            self.resident.pop(i).renderer.release()
        if self.sky_pass is not None:
            self.sky_pass.release()
        if self.studio is not None:
            self.studio.release()
        self.programs.release()
        self.targets.release()
        self.loader.close()
