"""The billboard stage: coloured cloud (+ images and poses) → ``model/`` + ``build_report.json``.

1. read the cloud; 2. the facade layer and the octree → blocks and voxel leaves (the
billboards, in Morton order); 3. per chunk of billboards, in worker processes: angular
sampling (from the images, occlusion-aware, or from the cloud's own points) into a memory
map on disk; 4. ground no camera saw takes the texture of seen ground nearby
(:mod:`billboards.synthesis`); 5. per chunk, in workers: the fit against the training
views (:mod:`billboards.fit_tasks`), PCA eigen-textures, quantisation, and the decode error
of what will be stored; 6. the chunks are streamed, in order, into the atlas pages of a
model written atomically. Memory is bounded by the chunks in flight, not by the street's
length; the sampled textures are on disk."""

from __future__ import annotations

import json
import logging
import os
import shutil
import time
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from core.errors import InputError
from core.fileio import write_json
from core.memory import peak_memory
from core.metrics import psnr_from_mse
from core.tasks import executor_workers, ordered_results
from data_synth import load_dataset, load_scene
from data_synth.dataset import held_out_frames
from recon.cloud_io import read_cloud_arrays
from recon.epi import EpiConfig, epi_points

from .atlas import reserved_memmap
from .facade_truth import facade_depth_report
from .fit import FitConfig, Quads, quads_of
from .fit_alpha import apply_alpha, read_alpha_rows, write_alpha_rows
from .fit_tasks import fit_range, fit_report, read_records, write_view_records
from .geometry import BILLBOARD, GROUND, DirectionConfig, base_yaw_toward, quad_edges
from .layer import Layer, LayerConfig, build_layer, grow_side_walls, refine_ground
from .model_writer import ModelWriter, temp_dir
from .octree import Octree, OctreeConfig, build_octree
from .pca import EigenTextures, PcaConfig, eigen_textures
from .photometry import PhotometryConfig, estimate_gains
from .prune import drawn_quads, prune_nodes, prune_ranges, prune_state
from .quantize import dequantize_rows, dequantize_tiles, quantize_rows, quantize_tiles
from .sampling import (ImageSampler, SamplingConfig, Views, VoxelPoints, quad_centres, views_from_dataset,
                       voxel_points)
from .sky import estimate_sky, read_sky, write_sky
from .splat import PointSampler
from .synthesis import synthesise

logger = logging.getLogger(__name__)

SOURCES = ("images", "points")


@dataclass(frozen=True)
class BuildConfig:
    octree: OctreeConfig = field(default_factory=OctreeConfig)        # voxel size, min points
    sampling: SamplingConfig = field(default_factory=SamplingConfig)  # directions, texels, occlusion test
    pca: PcaConfig = field(default_factory=PcaConfig)                 # rank rule
    source: str = "images"       # "images" (project the captured images) or "points" (splat the cloud)
    tile_mode: str = "u8"        # eigen/mean tiles: "u8" (per-tile scale/offset) or "f16"
    coef_mode: str = "f16"       # coefficients: "f32", "f16" or "u8"
    page_size: int = 8192        # atlas page edge (texels); the renderer passes GL_MAX_TEXTURE_SIZE
    chunk: int = 128             # billboards sampled and compressed together (bounds memory)
    task_chunks: int = 8         # chunks per worker task (neighbouring billboards share cached images)
    error_stride: int = 4        # decode PSNR is measured on every n-th billboard (1: all)
    holdout: int = 0             # leave every n-th frame's images out of the sampling (for novel-view tests; 0: none)
    layer: LayerConfig | None = field(default_factory=LayerConfig)  # the facade layer (None: billboards only)
    photometry: PhotometryConfig | None = field(default_factory=PhotometryConfig)  # per-image gains divided out
                                                                                  # before sampling (None: off)
    fit: FitConfig | None = field(default_factory=FitConfig)  # textures fitted to the training images through
                                                             # the rendering (billboards.fit; None: as sampled)
    fit_views_per_task: int = 12      # training views ray cast per worker task of the fit
    tile_metres: float | None = None  # build a model set of square tiles this wide (m, whole voxels; None: one model)
    tile_margin: float = 8.0          # a tile's context: its neighbours' points this near (m; layer, occlusion)
    sample_points: int = 2_000_000    # a tiled build estimates gains and sky from at most this many cloud points

    def __post_init__(self):
        if self.source not in SOURCES:
            raise InputError(f"source must be one of {SOURCES}, got {self.source!r}")
        if self.holdout < 0 or self.holdout == 1:
            raise InputError("holdout must be 0 (none) or ≥ 2 (every n-th frame left out)")
        if self.chunk < 1 or self.task_chunks < 1 or self.error_stride < 1:
            raise InputError("chunk, task_chunks and error_stride must be ≥ 1")
        if self.tile_metres is not None and not (np.isfinite(self.tile_metres) and self.tile_metres > 0):
            raise InputError(f"tile_metres must be a finite number > 0 or None, got {self.tile_metres!r}")
        if not (np.isfinite(self.tile_margin) and self.tile_margin >= 0) or self.sample_points < 1:
            raise InputError("tile_margin must be finite and ≥ 0, sample_points ≥ 1")
        if self.fit_views_per_task < 1:
            raise InputError("fit_views_per_task must be ≥ 1")


@dataclass(frozen=True, eq=False)
class Billboards:
    """The voxels of a cloud, ready for sampling.

    octree: the voxel leaves; leaf (N,) int64 billboard of each point (−1: none);
    voxels: the points grouped by billboard (cube centres, for z-buffers and slabs);
    base_yaw (n,) float64 world yaw toward the capture path; quads (n, 3) float64
    quad centres on the surface (:func:`sampling.quad_centres`); kind (n,) uint8 quad
    kinds; node_range (k, 2) int64 [begin, end) billboards under each octree node; unseen (n,)
    bool the continued ground blocks no camera sees (their textures are synthesised,
    :mod:`billboards.synthesis`); split (n,) uint8 a quad's edge is its kind's halved this many
    times (:mod:`billboards.resolution`); cell (n, 3) float64 the centre of the unsplit block a
    ground block was split from (None: the quads); corner_dz (n, 4) float64 the heights of a ground
    block's corners above its centre (the ground's height field; None: all flat).
    Without a facade layer there is one billboard per voxel leaf, in leaf order; with one,
    a leaf holds its billboard (if its own points make one) and the layer blocks whose
    centres lie in it, so that culling by the octree covers both.
    """

    octree: Octree
    leaf: np.ndarray
    voxels: VoxelPoints
    base_yaw: np.ndarray
    quads: np.ndarray
    kind: np.ndarray
    node_range: np.ndarray
    block_size: float | None = None
    unseen: np.ndarray | None = None
    split: np.ndarray | None = None
    cell: np.ndarray | None = None
    corner_dz: np.ndarray | None = None

    def __post_init__(self):
        if self.corner_dz is None:
            object.__setattr__(self, "corner_dz", np.zeros((len(self.kind), 4)))
        if self.cell is None:
            object.__setattr__(self, "cell", np.asarray(self.quads, np.float64).copy())
        if self.unseen is None:
            object.__setattr__(self, "unseen", np.zeros(len(self.kind), bool))
        if self.split is None:
            object.__setattr__(self, "split", np.zeros(len(self.kind), np.uint8))

    @property
    def num_billboards(self) -> int:
        return len(self.kind)

    def image_sampler(self, views: Views, config: SamplingConfig) -> ImageSampler:
        return ImageSampler(views, self.quads, self.octree.voxel_size, self.base_yaw, self.voxels, config,
                            box_centres=self.voxels.centres, kind=self.kind, block_size=self.block_size,
                            split=self.split, corner_dz=self.corner_dz)

    def voxel_colours(self, colours: np.ndarray) -> np.ndarray:
        """(N', 3) uint8 colours of the points in voxels, in the order of ``voxels.points``."""
        keep = self.leaf >= 0
        return colours[keep][np.argsort(self.leaf[keep], kind="stable")]

    def point_sampler(self, colours: np.ndarray, config: SamplingConfig) -> PointSampler:
        return PointSampler(self.voxels, self.voxel_colours(colours), self.base_yaw, config, centres=self.quads)


def place_billboards(points: np.ndarray, octree: Octree, viewpoints: np.ndarray | None) -> Billboards:
    """Group ``points`` (N, 3) float64 by the voxels of ``octree`` and place their quads,
    facing ``viewpoints`` (v, 3) float64 camera centres (None: base yaw 0)."""
    centres = octree.centres()
    leaf = octree.leaves_of_points(points)
    voxels = voxel_points(points, leaf, centres, octree.origin, octree.voxel_size)
    base_yaw = base_yaw_toward(centres, np.zeros((0, 3)) if viewpoints is None else viewpoints)
    return Billboards(octree, leaf, voxels, base_yaw, quad_centres(voxels, base_yaw),
                      np.full(len(centres), BILLBOARD, np.uint8), octree.node_range.astype(np.int64))


def place_hybrid(points: np.ndarray, config: OctreeConfig, viewpoints: np.ndarray, layer: Layer,
                 block_size: float | None = None, grid_origin: np.ndarray | None = None) -> Billboards:
    """Billboards where the cloud departs from the facade ``layer``, and the layer's blocks.

    points (N, 3) float64 world; viewpoints (v, 3) float64 camera centres; block_size: edge of
    the layer's blocks (m; None: the voxel size). The octree is
    built over the points the layer does not explain plus each block's centre (counted
    ``min_points`` times, so every block's cell is a leaf; on the voxel grid from ``grid_origin``
    when given, see :func:`~billboards.octree.build_octree`); a leaf gets a billboard when
    at least ``min_points`` unexplained points fall in it. Billboards are ordered by leaf
    (Morton order), a leaf's billboard before its blocks.
    """
    points = np.asarray(points, np.float64)
    free = np.flatnonzero(~layer.explained)
    anchors = np.concatenate([points[free], np.repeat(layer.centres, config.min_points, axis=0)])
    octree = build_octree(anchors, config, grid_origin)
    n_leaves = octree.num_voxels
    free_leaf = octree.leaves_of_points(points[free])
    counts = np.bincount(free_leaf[free_leaf >= 0], minlength=n_leaves)
    board_leaves = np.flatnonzero(counts >= config.min_points)
    block_leaves = octree.leaves_of_points(layer.centres) if len(layer.centres) else np.zeros(0, np.int64)
    if np.any(block_leaves < 0):
        raise AssertionError("a layer block fell outside the octree built around it")
    item_leaf = np.concatenate([board_leaves, block_leaves])
    item_kind = np.concatenate([np.full(len(board_leaves), BILLBOARD, np.uint8), layer.kind])
    source = np.concatenate([board_leaves, np.arange(len(block_leaves))])  # leaf (billboard) or block index
    order = np.lexsort((np.arange(len(item_leaf)), item_kind, item_leaf))
    item_leaf, item_kind, source = item_leaf[order], item_kind[order], source[order]
    is_board = item_kind == BILLBOARD
    # Each point's billboard: unexplained points of a billboard leaf, and points on a block.
    item_of_board_leaf = np.full(max(n_leaves, 1), -1, np.int64)  # (a tile's part may have no leaf)
    item_of_board_leaf[source[is_board]] = np.flatnonzero(is_board)
    item_of_block = np.full(len(layer.centres), -1, np.int64)
    item_of_block[source[~is_board]] = np.flatnonzero(~is_board)
    owner = np.full(len(points), -1, np.int64)
    owner[free] = np.where(free_leaf >= 0, item_of_board_leaf[np.maximum(free_leaf, 0)], -1)
    on_block = np.flatnonzero(layer.explained)
    owner[on_block] = item_of_block[layer.point_block[on_block]]
    leaf_centres = octree.centres()
    box_centres = np.where(is_board[:, None], leaf_centres[item_leaf],
                           layer.centres[np.where(is_board, 0, source)] if len(layer.centres) else 0.0)
    voxels = voxel_points(points, owner, box_centres, octree.origin, octree.voxel_size)
    if block_size is not None:  # a block's points reach up to a block and a half from its centre
        voxels = replace(voxels, reach=1.5 * float(block_size))
    base_yaw = base_yaw_toward(box_centres, viewpoints)
    blocks = ~is_board
    base_yaw[blocks] = layer.base_yaw[source[blocks]]
    quads = quad_centres(voxels, base_yaw)
    quads[blocks] = box_centres[blocks]
    item_begin = np.searchsorted(item_leaf, np.arange(n_leaves + 1))
    node_range = item_begin[octree.node_range]
    unseen = np.zeros(len(item_kind), bool)
    unseen[blocks] = layer.synthesised[source[blocks]]
    split = np.zeros(len(item_kind), np.uint8)
    split[blocks] = layer.split[source[blocks]]
    cell = quads.copy()
    cell[blocks] = layer.cell[source[blocks]]
    corner_dz = np.zeros((len(item_kind), 4))
    corner_dz[blocks] = layer.corner_dz[source[blocks]]
    return Billboards(octree, owner, voxels, base_yaw, quads, item_kind, node_range, block_size, unseen, split, cell,
                      corner_dz)


# --------------------------------------------------------------------------- worker side

@dataclass(frozen=True)
class _Task:
    state: str          # directory with the shared arrays
    begin: int          # billboard range [begin, end)
    end: int
    stage: str = "sample"     # "sample": sampled textures into the shared memory map; then "compress"
                              # them, or "fit": solved against the views' records, compressed
    seconds: float | None = None   # the fit's iterations begin no later than this long after the task's start


@dataclass(frozen=True)
class _ViewTask:
    state: str          # directory with the shared arrays
    begin: int          # training view range [begin, end) of the fit
    end: int
    stage: str = "records"    # "records": the colour fit's measurements; "alpha": the alpha decision's sums
    occluded: bool = False    # a tile's: hits behind its context's z-buffer are no measurements


_WORKER: dict = {}


def save_worker_state(state: Path, conf: BuildConfig, placed: Billboards, views: Views | None,
                      colours: np.ndarray | None = None, occluders: VoxelPoints | None = None) -> None:
    """Write what the texture tasks read into ``state``: the billboards, the views (paths, not
    images) and the settings; ``colours`` (N, 3) uint8 of the cloud for ``source="points"``;
    ``occluders``: the points the z-buffers are made of when more than the billboards' own."""
    grouped = placed.voxels
    np.save(state / "quads.npy", placed.quads)
    np.save(state / "points.npy", grouped.points)
    np.save(state / "begin.npy", grouped.begin)
    np.save(state / "centres.npy", grouped.centres)
    np.save(state / "base_yaw.npy", placed.base_yaw)
    np.save(state / "kind.npy", placed.kind)
    np.save(state / "split.npy", placed.split)
    np.save(state / "cell.npy", placed.cell)
    np.save(state / "corner_dz.npy", placed.corner_dz)
    if conf.source == "points":
        np.save(state / "colours.npy", placed.voxel_colours(colours))
    meta = {"config": _config_to_json(conf), "origin": placed.octree.origin.tolist(),
            "voxel_size": placed.octree.voxel_size, "block_size": placed.block_size, "reach": grouped.reach}
    if occluders is not None:
        np.save(state / "occluder_points.npy", occluders.points)
        np.save(state / "occluder_begin.npy", occluders.begin)
        np.save(state / "occluder_centres.npy", occluders.centres)
        meta["occluders"] = {"origin": occluders.origin.tolist(), "reach": occluders.reach}
    if views is not None:
        np.save(state / "K.npy", views.K)
        np.save(state / "world_from_cam.npy", views.world_from_cam)
        np.save(state / "sizes.npy", views.sizes)
        if views.gains is not None:
            np.save(state / "gains.npy", views.gains)
        if views.rig is not None:
            views.rig.save(state / "rig.json")
            np.save(state / "cams.npy", views.cams)
        meta["paths"] = [str(p) for p in views.paths]
    (state / "meta.json").write_text(json.dumps(meta))


def _worker_state(state_dir: str):
    """Load (once per process) the sampler and settings saved in ``state_dir``."""
    if _WORKER.get("dir") == state_dir:
        return _WORKER["sampler"], _WORKER["conf"]
    root = Path(state_dir)
    meta = json.loads((root / "meta.json").read_text())
    conf = _config_from_json(meta["config"])
    centres = np.load(root / "centres.npy")
    quads = np.load(root / "quads.npy")
    base_yaw = np.load(root / "base_yaw.npy")
    kind = np.load(root / "kind.npy")
    voxels = VoxelPoints(np.asarray(meta["origin"], dtype=np.float64), np.load(root / "points.npy", mmap_mode="r"),
                         np.load(root / "begin.npy"), centres, meta["voxel_size"], meta["reach"])
    if conf.source == "images":
        gains = np.load(root / "gains.npy") if (root / "gains.npy").exists() else None
        lens = {}
        if (root / "rig.json").exists():  # distorted cameras: the views undistort their raw images
            from data_synth.rig import Rig

            lens = dict(rig=Rig.load(root / "rig.json"), cams=np.load(root / "cams.npy"))
        views = Views(np.load(root / "K.npy"), np.load(root / "world_from_cam.npy"), np.load(root / "sizes.npy"),
                      tuple(Path(p) for p in meta["paths"]), gains, **lens)
        occluders = None
        if "occluders" in meta:
            occluders = VoxelPoints(np.asarray(meta["occluders"]["origin"], dtype=np.float64),
                                    np.load(root / "occluder_points.npy", mmap_mode="r"),
                                    np.load(root / "occluder_begin.npy"), np.load(root / "occluder_centres.npy"),
                                    meta["voxel_size"], meta["occluders"]["reach"])
        sampler = ImageSampler(views, quads, meta["voxel_size"], base_yaw, voxels, conf.sampling, box_centres=centres,
                               kind=kind, block_size=meta["block_size"], occluders=occluders,
                               split=np.load(root / "split.npy"), corner_dz=np.load(root / "corner_dz.npy"))
    else:
        sampler = PointSampler(voxels, np.load(root / "colours.npy", mmap_mode="r"), base_yaw, conf.sampling,
                               centres=quads)
    _WORKER.clear()
    _WORKER.update(dir=state_dir, sampler=sampler, conf=conf)
    return sampler, conf


def compress_chunk(rgba: np.ndarray, conf: BuildConfig, eig: EigenTextures | None = None) -> tuple[dict, dict]:
    """PCA + quantisation of one chunk of sampled textures.

    rgba (B, d, t, t, 4) uint8 → (arrays for the model writer, error statistics: against
    ``rgba``). Slots per billboard: [mean, eigen_1 … eigen_r]. ``eig``: the chunk's
    eigen-textures already made (fitted), only quantised.
    """
    B, d, t = rgba.shape[:3]
    n = t * t * 4
    raw = rgba.reshape(B, d, n).astype(np.float32) / 255.0
    t0 = time.perf_counter()
    eig = eigen_textures(raw, conf.pca) if eig is None else eig
    t1 = time.perf_counter()
    rank = eig.rank.astype(np.int64)
    # Gather the slots in order: billboard b owns 1 + rank[b] consecutive tiles.
    R = eig.basis.shape[1]
    slot_of = np.concatenate([[0], np.cumsum(1 + rank)])
    m = int(slot_of[-1])
    tiles = np.zeros((m, n), dtype=np.float32)
    rows = np.zeros((m, d), dtype=np.float32)
    tiles[slot_of[:-1]] = eig.mean
    for k in range(R):
        has = rank > k
        tiles[slot_of[:-1][has] + 1 + k] = eig.basis[has, k]
        rows[slot_of[:-1][has] + 1 + k] = eig.coefficients[has, :, k]
    qt = quantize_tiles(tiles.reshape(m, t, t, 4), conf.tile_mode)
    qr = quantize_rows(rows, conf.coef_mode)
    t2 = time.perf_counter()
    # What a decoder will reconstruct from the stored (quantised) data, on every
    # error_stride-th billboard (the error statistics cost as much as the PCA).
    sel = np.arange(0, B, conf.error_stride)
    dt = dequantize_tiles(qt).reshape(m, n)
    dr = dequantize_rows(qr)
    first = slot_of[:-1][sel]
    basis = np.zeros((len(sel), R, n), dtype=np.float32)
    coefficients = np.zeros((len(sel), d, R), dtype=np.float32)
    for k in range(R):
        has = np.flatnonzero(rank[sel] > k)
        basis[has, k] = dt[first[has] + 1 + k]
        coefficients[has, :, k] = dr[first[has] + 1 + k]
    decoded = dt[first][:, None, :] + np.matmul(coefficients, basis)
    np.clip(decoded, 0.0, 1.0, out=decoded)
    raw_sel = raw[sel].reshape(len(sel), d, t * t, 4)
    opaque = rgba[sel].reshape(len(sel), d, t * t, 4)[..., 3] > 0        # (b, d, texels)

    def sq_err(x):
        e = x.reshape(raw_sel.shape) - raw_sel
        np.square(e, out=e)
        return float(e.sum(dtype=np.float64)), float(e[..., :3].sum(axis=-1)[opaque].sum(dtype=np.float64))

    dec_all, dec_rgb = sq_err(decoded)
    del decoded
    pca = eig.mean[sel][:, None, :] + np.matmul(eig.coefficients[sel], eig.basis[sel])
    pca_all, pca_rgb = sq_err(np.clip(pca, 0.0, 1.0))
    stats = {"raw_values": B * d * n, "values": len(sel) * d * n, "opaque_rgb_values": 3 * int(opaque.sum()),
             "sq_err_decoded": dec_all, "sq_err_decoded_rgb": dec_rgb,
             "sq_err_pca": pca_all, "sq_err_pca_rgb": pca_rgb,
             "pca_s": t1 - t0, "quantize_s": t2 - t1, "ranks": np.bincount(rank, minlength=d + 1).tolist()}
    arrays = {"rank": rank.astype(np.uint8), "tiles": qt.data, "slot_scale": qt.scale, "slot_offset": qt.offset,
              "coef_rows": qr.data, "coef_scale": qr.scale, "coef_offset": qr.offset}
    return arrays, stats


def _fit_quads(state_dir: str, conf: BuildConfig) -> Quads:
    """The quads of the model being built as the renderer will place them (once per process)."""
    if _WORKER.get("quads_dir") != state_dir:
        root = Path(state_dir)
        meta = json.loads((root / "meta.json").read_text())
        origin = np.asarray(meta["origin"], np.float64)
        d = conf.sampling.directions
        _WORKER.update(quads_dir=state_dir, quads=quads_of(
            origin, (np.load(root / "quads.npy") - origin).astype(np.float32),
            np.load(root / "base_yaw.npy").astype(np.float32), np.load(root / "kind.npy"), meta["voxel_size"],
            meta["block_size"] or meta["voxel_size"], conf.sampling.tile, d.yaw_offsets, d.pitches, d.pitched_quads,
            split=np.load(root / "split.npy"), corner_dz=np.load(root / "corner_dz.npy").astype(np.float32)))
    return _WORKER["quads"]


def _cast_task(task: _ViewTask) -> dict:
    """The fit's measurements of training views [begin, end) into ``records_BEGIN.npy`` (or the
    alpha decision's sums into ``alpha_BEGIN.npy``)."""
    sampler, conf = _worker_state(task.state)
    root = Path(task.state)
    rgba = np.load(root / "rgba.npy", mmap_mode="r")
    if task.stage == "alpha":
        return write_alpha_rows(root / f"alpha_{task.begin:06d}.npy", _fit_quads(task.state, conf), rgba,
                                sampler.views, range(task.begin, task.end), read_sky(root), conf.fit,
                                conf.sampling.max_distance)
    s = conf.sampling
    occluders = (lambda i: (sampler.cache.get(i)[2], s.zbuffer_scale, s.slab_margin, s.rel_tolerance)
                 ) if task.occluded else None
    return write_view_records(root / f"records_{task.begin:06d}.npy", _fit_quads(task.state, conf), rgba,
                              sampler.views, range(task.begin, task.end), conf.fit, s.max_distance, occluders)


def _compress_range(root: Path, begin: int, end: int, conf: BuildConfig, eig: EigenTextures | None = None) -> list:
    """The compressed chunks of billboards [begin, end) from the shared memory map, with their
    synthesised flags; ``eig``: their eigen-textures already made (fitted), indexed from ``begin``."""
    rgba = np.load(root / "rgba.npy", mmap_mode="r")
    synthesised = np.load(root / "synthesised.npy", mmap_mode="r")
    out = []
    for s in range(begin, end, conf.chunk):
        e = min(end, s + conf.chunk)
        arrays, stats = compress_chunk(np.asarray(rgba[s:e]), conf,
                                       None if eig is None else eig.slice(s - begin, e - begin))
        arrays["synthesised"] = np.array(synthesised[s:e])
        out.append((arrays, stats))
    return out


def _run_task(task: _Task):
    sampler, conf = _worker_state(task.state)
    root = Path(task.state)
    if task.stage == "sample":
        rgba = np.load(root / "rgba.npy", mmap_mode="r+")
        stats = []
        for s in range(task.begin, task.end, conf.chunk):
            t0 = time.perf_counter()
            sampled = sampler.sample(np.arange(s, min(task.end, s + conf.chunk)))
            rgba[s:s + len(sampled.rgba)] = sampled.rgba
            stats.append({"sampling_s": time.perf_counter() - t0, "sampling": sampled.stats})
        rgba.flush()
        return stats
    if task.stage == "alpha":
        rgba = np.load(root / "rgba.npy", mmap_mode="r+")
        t = rgba.shape[2]
        rows = read_alpha_rows(sorted(root.glob("alpha_*.npy")), task.begin, task.end, t * t)
        mine = np.array(rgba[task.begin:task.end])
        stats = apply_alpha(mine, task.begin, rows, _fit_quads(task.state, conf).kind, conf.fit)
        rgba[task.begin:task.end] = mine
        rgba.flush()
        return stats
    if task.stage == "fit":
        rgba = np.load(root / "rgba.npy", mmap_mode="r")
        records = read_records(sorted(root.glob("records_*.npy")), task.begin, task.end)
        # transients are left out of the fit as out of the sampling, or neither
        fit = conf.fit if conf.sampling.transients else replace(conf.fit, transients=None)
        eig, fit_stats = fit_range(_fit_quads(task.state, conf), rgba, task.begin, task.end, records, fit,
                                   time.time() + task.seconds, conf.pca)
        return _compress_range(root, task.begin, task.end, conf, eig), fit_stats
    if task.stage == "compress":
        return _compress_range(root, task.begin, task.end, conf)
    raise InputError(f"unknown task stage {task.stage!r}")


def texture_tasks(state: Path, conf: BuildConfig, n: int) -> list[_Task]:
    """The tasks that sample and compress the textures of ``n`` billboards saved in ``state``."""
    step = conf.chunk * conf.task_chunks
    return [_Task(str(state), b, min(n, b + step)) for b in range(0, n, step)]


def sample_textures(state: Path, conf: BuildConfig, tasks: list[_Task], kind: np.ndarray, quads: np.ndarray,
                    base_yaw: np.ndarray, unseen: np.ndarray, executor: Executor | None,
                    progress: bool | None, desc: str = "sampling") -> tuple[list[dict], np.ndarray]:
    """Sample every texture of the billboards saved in ``state`` (kind (n,) uint8, quads (n, 3)
    float64, base_yaw (n,) float64, unseen (n,) bool: :class:`Billboards`; their splits and cells are
    read from ``state``) into the memory map ``state/rgba.npy``, then give the ground blocks that have
    none one from seen ground nearby (:func:`~billboards.synthesis.synthesise`: changes ``base_yaw`` in
    place; it and which blocks are synthesised are saved for the next tasks), and leave out of
    ``state`` the quads that draw nothing (transparent from every direction,
    :func:`~billboards.prune.prune_state`). Returns the tasks' sampling statistics and keep (n,)
    bool the quads left, in their order (the caller's per-quad arrays and node ranges follow it:
    :func:`~billboards.prune.prune_ranges`)."""
    s, n = conf.sampling, len(kind)
    # its blocks reserved: a full disk is an OSError naming the file, not a worker killed by SIGBUS
    reserved_memmap(state / "rgba.npy", np.uint8, (n, s.directions.num_directions, s.tile, s.tile, 4)).flush()
    stats = [st for chunk in ordered_results(_run_task, tasks, executor, window=2 * executor_workers(executor),
                                             desc=desc, progress=progress) for st in chunk]
    rgba = np.load(state / "rgba.npy", mmap_mode="r+")
    front = int(np.argmin(np.abs(s.directions.yaw_offsets)))
    meta = json.loads((state / "meta.json").read_text())
    split = np.load(state / "split.npy")
    edges = quad_edges(kind, split, meta["voxel_size"], meta["block_size"] or meta["voxel_size"])
    synthesised, _ = synthesise(rgba, kind, quads, base_yaw, unseen, front, split, np.load(state / "cell.npy"), edges)
    rgba.flush()
    del rgba
    np.save(state / "synthesised.npy", synthesised.astype(np.uint8))
    np.save(state / "base_yaw.npy", base_yaw)
    keep = drawn_quads(np.load(state / "rgba.npy", mmap_mode="r"))
    if not keep.all():
        prune_state(state, keep)
        logger.info("%d of %d quads draw nothing from any direction: left out", int((~keep).sum()), n)
    return stats, keep


def compressed_textures(tasks: list[_Task], executor: Executor | None, progress: bool | None, desc: str = "billboards"):
    """The compressed chunks of the sampled textures, task by task in order (lists of
    (arrays for the model writer, statistics))."""
    return ordered_results(_run_task, [replace(t, stage="compress") for t in tasks], executor,
                           window=2 * executor_workers(executor), desc=desc, progress=progress)


# --------------------------------------------------------------------------- parent side

def _config_to_json(conf: BuildConfig) -> dict:
    return json.loads(json.dumps(asdict(conf)))


def _config_from_json(data: dict) -> BuildConfig:
    s = data["sampling"]
    sampling = SamplingConfig(**{**s, "directions": DirectionConfig(**{**s["directions"],
                                                                        "pitches_deg": tuple(s["directions"]["pitches_deg"])})})
    layer = data.get("layer")
    if layer is not None:
        layer = LayerConfig(**{**layer, "epi": EpiConfig(**layer["epi"])})
    photometry = data.get("photometry")
    if photometry is not None:
        photometry = PhotometryConfig(**photometry)
    fit = data.get("fit")
    if fit is not None:
        fit = FitConfig(**fit)
    return BuildConfig(**{**data, "octree": OctreeConfig(**data["octree"]), "sampling": sampling,
                          "pca": PcaConfig(**data["pca"]), "layer": layer, "photometry": photometry, "fit": fit})


@dataclass(frozen=True, eq=False)
class BuildResult:
    model: Path
    report: dict


def main(conf: BuildConfig, cloud_path: os.PathLike | str, dataset_dir: os.PathLike | str | None,
         model_dir: os.PathLike | str, executor: Executor | None = None, progress: bool | None = None,
         poses: os.PathLike | str | None = None) -> BuildResult:
    """Build ``model_dir`` from a cloud and (for ``source="images"``) a dataset's images and poses.

    With ``conf.tile_metres`` the model is a set of tiles built one by one
    (:func:`billboards.build_tiles.build_tiled`). Writes ``model_dir/build_report.json``
    too. ``executor`` runs the texture tasks (None:
    this process), twice its worker count kept in flight so none idles. ``poses``: a
    ``poses.json`` used instead of the dataset's own (``WORK/poses.json`` of a recon whose
    poses came from SfM or a COLMAP model), recorded in the model's info so that eval and
    render use it too; frames without a pose are left out.
    """
    if conf.tile_metres is not None:  # a model set, tile by tile
        from .build_tiles import build_tiled

        return build_tiled(conf, cloud_path, dataset_dir, model_dir, executor, progress, poses)
    model_dir = Path(model_dir)
    stages: dict[str, float] = {}
    t0 = time.perf_counter()
    points, colours = read_cloud_arrays(cloud_path, require_colours=True)
    stages["read_cloud_s"] = time.perf_counter() - t0

    views = None
    held_out: list[int] = []
    cameras = 0
    if dataset_dir is not None:
        dataset = load_dataset(dataset_dir, poses=poses)
        posed = dataset.posed
        if not posed.any():
            where = poses if poses is not None else Path(dataset_dir) / "poses.json"
            raise InputError(f"{where}: no frame has a pose (a photo folder: `bbcity recon DATASET --poses sfm`, "
                             "then `bbcity build WORK`)")
        # the frames left out of the textures that can be viewpoints (eval needs their poses)
        held_out = [f for f in held_out_frames(dataset.num_frames, conf.holdout) if posed[f]]
        frames = [f for f in range(dataset.num_frames) if f not in set(held_out) and posed[f]]
        views = views_from_dataset(dataset, frames)
        cameras = dataset.rig.num_cameras
        if conf.source == "images" and len(views) and not sees_any(views, points, conf.sampling.max_distance):
            # every texel would stay transparent: an empty-looking model that builds without complaint
            raise InputError(f"no camera of {dataset_dir} sees any point of {cloud_path}: wrong dataset or "
                             f"poses? (cloud within {_box(points)}, cameras within {_box(views.centres)})")
    elif conf.source == "images":
        raise InputError("source 'images' needs the dataset's images and poses (--images DATASET)")

    photometry_report: dict = {"enabled": False}
    exposure = None
    if (conf.photometry is not None and conf.photometry.enabled and views is not None and conf.source == "images"
            and len(views) and len(points)):
        # Exposure and white balance divided out of every image before anything reads its colours
        # (the layer's EPIs, the sky, the textures), so the eigen-textures spend no rank on them.
        t1 = time.perf_counter()
        photometry = estimate_gains(views, points, conf.photometry, progress=progress)
        views = replace(views, gains=photometry.gains)
        stages["photometry_s"] = time.perf_counter() - t1
        photometry_report = photometry.report()
        # which (frame, camera) each gain belongs to, in the order of views_from_dataset
        exposure = {"views": [[f, c] for f in frames for c in range(cameras)], "gains": photometry.gains.tolist()}

    t1 = time.perf_counter()
    # The sky behind the model, from the capture's own sky pixels (the whole cloud marks what is not sky).
    sky = estimate_sky(views, points) if views is not None and conf.source == "images" else None
    stages["sky_s"] = time.perf_counter() - t1

    layer = None
    layer_report: dict = {"enabled": False}
    if conf.layer is not None and views is not None and conf.source == "images" and len(views) and len(points):
        t1 = time.perf_counter()
        passes = epi_points(views.K, views.world_from_cam, views.image, cameras, conf.layer.epi)
        stages["epi_s"] = time.perf_counter() - t1
        t1 = time.perf_counter()
        size = conf.octree.voxel_size or build_octree(points, conf.octree).voxel_size
        block_size = conf.layer.block_size or size
        grid_origin = points.min(axis=0)   # one voxel grid for blocks and billboards (as in tiled builds)
        layer = build_layer(points, passes, block_size, grid_origin, views.centres, conf.layer,
                            cameras=(views.K, views.world_from_cam, views.sizes))
        stages["layer_s"] = time.perf_counter() - t1
        layer, wall_depth = grow_side_walls(layer, points, views, sky, block_size, conf.layer.wall_depth)
        layer = refine_ground(layer, points, block_size, (views.K, views.world_from_cam, views.sizes),
                              conf.layer.resolution, conf.sampling.tile)
        layer_report = _layer_report(layer, passes, points, dataset, conf.layer)
        layer_report["side_walls_deepened"] = wall_depth
        layer_report["block_size"] = block_size

    t1 = time.perf_counter()
    if layer is not None and len(layer.centres):
        octree_conf = replace(conf.octree, voxel_size=size, depth=None)
        placed = place_hybrid(points, octree_conf, views.centres, layer, block_size, grid_origin)
        octree = placed.octree
    else:
        octree = build_octree(points, conf.octree)
        placed = None
        block_size = None
    stages["octree_s"] = time.perf_counter() - t1
    if octree.num_voxels == 0:
        raise InputError(f"{cloud_path}: no voxel holds {conf.octree.min_points} points "
                         f"at voxel size {octree.voxel_size:g} m; nothing to build")
    logger.info("%d points → %d voxels of %.3g m (depth %d)", len(points), octree.num_voxels,
                octree.voxel_size, octree.depth)

    sampling = conf.sampling
    if views is None and sampling.directions.count * sampling.directions.spacing_deg < 360:
        # No capture path: sample the whole circle.
        count = sampling.directions.count
        sampling = replace(sampling, directions=replace(sampling.directions, spacing_deg=360.0 / count))
    conf = replace(conf, sampling=sampling)

    t2 = time.perf_counter()
    state = temp_dir(model_dir.parent, f".{model_dir.name}.build-")
    try:
        if placed is None:
            placed = place_billboards(points, octree, views.centres if views is not None else None)
        base_yaw, quads, kind, unseen, split = placed.base_yaw, placed.quads, placed.kind, placed.unseen, placed.split
        corner_dz = placed.corner_dz
        node_range = placed.node_range
        save_worker_state(state, conf, placed, views, colours)
        write_sky(state, sky)   # what the fit's alpha sees behind the last quad along a ray
        stages["prepare_s"] = time.perf_counter() - t2
        del points, colours, placed, layer

        n = len(kind)
        tasks = texture_tasks(state, conf, n)
        t3 = time.perf_counter()
        totals = _Totals(conf.sampling.directions.num_directions)
        d = conf.sampling.directions.num_directions
        fitting = conf.fit is not None and conf.source == "images" and views is not None and len(views) > 0
        with ModelWriter(model_dir, tile=conf.sampling.tile, page_size=conf.page_size, tile_mode=conf.tile_mode,
                         coef_mode=conf.coef_mode, num_directions=d) as writer:
            done = 0

            def append(chunks):
                nonlocal done
                for arrays, stats in chunks:
                    b = len(arrays["rank"])
                    writer.append(centres=(quads[done:done + b] - octree.origin).astype(np.float32),
                                  base_yaw=base_yaw[done:done + b].astype(np.float32), kind=kind[done:done + b],
                                  split=split[done:done + b], corner_dz=corner_dz[done:done + b], **arrays)
                    done += b
                    totals.add(stats)

            sampled, keep = sample_textures(state, conf, tasks, kind, quads, base_yaw, unseen, executor, progress)
            for st in sampled:
                totals.add(st)
            if not keep.all():   # quads transparent from every direction explain no pixel
                quads, base_yaw, kind, split, corner_dz = (a[keep] for a in (quads, base_yaw, kind, split, corner_dz))
                node_range = prune_ranges(node_range, keep)
                tasks = texture_tasks(state, conf, len(kind))
            stages["sample_s"] = time.perf_counter() - t3
            if fitting:
                fit = fit_textures(conf, state, tasks, len(views), append, executor, progress)
                stages.update(fit.pop("stages"))
            else:
                for chunks in compressed_textures(tasks, executor, progress):
                    append(chunks)
            stages["sample_compress_s"] = time.perf_counter() - t3  # (with a fit: its stages too)
            t4 = time.perf_counter()
            nodes = _node_table(octree, node_range)
            info = {"source": conf.source, "occlusion_aware": conf.sampling.occlusion,
                    # absolute: the model means the same from any directory (the viewer finds the poses)
                    "cloud": str(Path(cloud_path).resolve()),
                    "dataset": None if dataset_dir is None else str(Path(dataset_dir).resolve()),
                    "held_out_frames": held_out}
            if exposure is not None:
                info["exposure"] = exposure  # eval gives a held-out frame the exposure of its neighbours
            if poses is not None and dataset_dir is not None:
                info["poses"] = str(Path(poses).resolve())
            writer.finish(origin=octree.origin, voxel_size=octree.voxel_size,
                          yaw_offsets=conf.sampling.directions.yaw_offsets, pitches=conf.sampling.directions.pitches,
                          pitched_quads=conf.sampling.directions.pitched_quads, info=info, block_size=block_size,
                          **nodes)
            stages["write_s"] = time.perf_counter() - t4
    finally:
        shutil.rmtree(state, ignore_errors=True)

    write_sky(model_dir, sky)
    from .model_reader import load
    model = load(model_dir)
    report = totals.report(model, conf, octree, len(views) if views is not None else 0)
    report["layer"] = layer_report
    report["photometry"] = photometry_report
    report["fit"] = fit if fitting else {"enabled": False}
    report["pruned_quads"] = int((~keep).sum())
    report.update(cloud=str(cloud_path), dataset=None if dataset_dir is None else str(dataset_dir),
                  poses=None if poses is None or dataset_dir is None else str(poses), stages=stages, total_s=time.perf_counter() - t0, peak_memory=peak_memory(),
                  config=_config_to_json(conf))
    write_json(model_dir / "build_report.json", report)
    logger.info("model: %d billboards, %d slots, %.1f MB, compression %.1f×, decode PSNR %s dB → %s",
                model.num_billboards, model.num_slots, report["bytes"]["model"] / 1e6,
                report["compression_ratio"], _db(report["psnr"]["decoded_rgb_opaque_db"]), model_dir)
    return BuildResult(model_dir, report)


def fit_textures(conf: BuildConfig, state: Path, tasks: list[_Task], num_views: int, append,
                 executor: Executor | None, progress: bool | None, tile: str | None = None) -> dict:
    """Decide the alpha of the sampled textures (:func:`sample_textures`) by the training views,
    ray cast those views against them, solve each task's textures against its records and
    ``append`` their compressed chunks in order. ``tile``: the name of a tile being built alone
    (its neighbours' quads are unknown: a hit behind the tile's context is no measurement, and
    alpha stays as sampled, since what a see-through texel shows may be a neighbour's). Returns
    the build report's "fit" with its "stages" seconds."""
    window = 2 * executor_workers(executor)
    who = "" if tile is None else f"{tile}: "
    t0 = time.perf_counter()
    per = conf.fit_views_per_task
    batches = [(b, min(num_views, b + per)) for b in range(0, num_views, per)]
    alpha = {"enabled": conf.fit.alpha and tile is None}
    if alpha["enabled"]:
        casts = list(ordered_results(_cast_task, [_ViewTask(str(state), b, e, "alpha") for b, e in batches],
                                     executor, window=window, desc="fit: alpha views", progress=progress))
        counts = list(ordered_results(_run_task, [replace(t, stage="alpha") for t in tasks],
                                      executor, window=window, desc="fit: alpha", progress=progress))
        for path in state.glob("alpha_*.npy"):
            path.unlink()
        alpha.update({k: sum(c[k] for c in counts) for k in ("decided", "shown", "cleared")},
                     rays=sum(c["rays"] for c in casts), cast_worker_s=sum(c["cast_s"] for c in casts))
        logger.info("%sfit: alpha of %d texels decided by the training images: %d now shown, %d now seen through",
                    who, alpha["decided"], alpha["shown"], alpha["cleared"])
    t1 = time.perf_counter()
    view_tasks = [_ViewTask(str(state), b, e, occluded=tile is not None) for b, e in batches]
    casts = list(ordered_results(_cast_task, view_tasks, executor, window=window, desc="fit: views",
                                 progress=progress))
    t2 = time.perf_counter()
    # What is left of the budget, shared fairly: each task's iterations may take its part of it.
    share = max(0.0, conf.fit.seconds - (t2 - t0)) * executor_workers(executor) / max(1, len(tasks))
    fit_stats = []
    for chunks, stats in ordered_results(_run_task, [replace(t, stage="fit", seconds=share) for t in tasks],
                                         executor, window=window, desc="fit: textures", progress=progress):
        append(chunks)
        fit_stats.append(stats)
    t3 = time.perf_counter()
    report = fit_report(fit_stats, casts, conf.fit, t3 - t0)
    report["alpha"] = alpha
    report["hidden"] = sum(c["hidden"] for c in casts)
    logger.info("%sfit: %d views, %d measurements (%d transients left out), training pixels %s → %s dB "
                "(transients too: %s → %s dB) in %.1f s", who, report["views"], report["measurements"],
                report["transients"], _db(report["psnr_before_db"]), _db(report["psnr_after_db"]),
                _db(report["psnr_all_before_db"]), _db(report["psnr_all_after_db"]), t3 - t0)
    report["stages"] = {"fit_alpha_s": t1 - t0, "fit_cast_s": t2 - t1, "fit_solve_compress_s": t3 - t2}
    return report


def sees_any(views: Views, points: np.ndarray, max_distance: float, sample: int = 50_000,
             batch: int = 64) -> bool:
    """Whether any view sees any of (every n-th of) ``points`` (m, 3) float64 world: in front of
    it, inside its image and nearer than ``max_distance`` (m, beyond which the sampler uses no
    camera). A cheap test (a sample, projected into ``batch`` views at a time), not occlusion."""
    pts = points[::max(1, -(-len(points) // sample))]
    for b in range(0, len(views), batch):
        T, K = views.world_from_cam[b:b + batch], views.K[b:b + batch]
        rel = pts[None, :, :] - T[:, None, :3, 3]                          # (v, n, 3)
        cam = np.matmul(rel, T[:, :3, :3])                                  # R^T (p − C)
        z = cam[..., 2]
        front = (z > 1e-3) & (np.einsum("vnk,vnk->vn", rel, rel) < max_distance ** 2)
        z = np.where(front, z, 1.0)
        u = K[:, None, 0, 0] * cam[..., 0] / z + K[:, None, 0, 2]
        v = K[:, None, 1, 1] * cam[..., 1] / z + K[:, None, 1, 2]
        w, h = views.sizes[b:b + batch, 0, None], views.sizes[b:b + batch, 1, None]
        if np.any(front & (u >= -0.5) & (u <= w - 0.5) & (v >= -0.5) & (v <= h - 0.5)):
            return True
    return False


def _box(xyz: np.ndarray) -> str:
    """'[x0, y0, z0] … [x1, y1, z1]' of (n, 3) positions, metres."""
    lo, hi = xyz.min(axis=0), xyz.max(axis=0)
    return f"[{', '.join(f'{x:.1f}' for x in lo)}] … [{', '.join(f'{x:.1f}' for x in hi)}] m"


def _node_table(octree: Octree, node_range: np.ndarray) -> dict:
    """The model's node arrays; node_range (k, 2) [begin, end) billboards under each node (the
    nodes left without a billboard are left out, :func:`~billboards.prune.prune_nodes`)."""
    level, bounds, children, node_range = prune_nodes(octree.node_level, octree.node_bounds() - octree.origin,
                                                      octree.node_children, node_range)
    return {"node_level": level.astype(np.uint8), "node_bounds": bounds.astype(np.float32),
            "node_children": children.astype(np.int32), "node_range": node_range.astype(np.int32)}


def _layer_report(layer: Layer, passes, points: np.ndarray, dataset, config: LayerConfig) -> dict:
    """Counts of the facade layer and, when ``dataset`` has ground truth, its facade depth against it."""
    report = {"enabled": True, "passes": len(passes), "epi_points": int(sum(len(p.points) for p in passes)),
              "facade_blocks": int((layer.kind != GROUND).sum()), "ground_blocks": int((layer.kind == GROUND).sum()),
              "side_wall_blocks": int(layer.side_wall.sum()), "kerb_blocks": int(layer.kerb.sum()),
              "ground_blocks_continued": int(layer.continued.sum()),
              "ground_blocks_unseen": int(layer.synthesised.sum()),
              "ground_blocks_by_times_split": np.bincount(layer.split[layer.kind == GROUND],
                                                          minlength=config.resolution.max_split + 1).tolist(),
              "explained_points": int(layer.explained.sum()), "points": int(len(points))}
    if layer.columns and dataset.has_ground_truth:
        report["facade_depth"] = facade_depth_report(layer.columns, points, load_scene(dataset.root), config)
    return report


def _psnr_db(sq_err: float, count: int) -> float | None:
    """PSNR (dB, peak 1) of a sum of squared errors over ``count`` values, capped at
    TOL.psnr_max_db for an exact decode; None when nothing was measured (valid JSON either way)."""
    return None if count == 0 else psnr_from_mse(sq_err / count)


def _db(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}"


class _Totals:
    """Accumulates the per-chunk statistics into the build report."""

    def __init__(self, d: int):
        self.sums: dict[str, float] = {}
        self.ranks = np.zeros(d + 1, dtype=np.int64)
        self.sampling: dict[str, int] = {}

    def add(self, stats: dict) -> None:
        for key, value in stats.items():
            if key == "ranks":
                self.ranks += np.asarray(value, dtype=np.int64)
            elif key == "sampling":
                for k, v in value.items():
                    self.sampling[k] = self.sampling.get(k, 0) + v
            else:
                self.sums[key] = self.sums.get(key, 0.0) + value

    def report(self, model, conf: BuildConfig, octree: Octree, num_views: int) -> dict:
        s = self.sums
        raw_bytes = int(s.get("raw_values", 0))  # 8-bit RGBA samples: one byte per value
        nbytes = model.nbytes()
        last = int(np.max(np.flatnonzero(self.ranks))) if self.ranks.any() else 0
        return {
            "billboards": model.num_billboards, "voxels": octree.num_voxels, "octree_depth": octree.depth, "voxel_size": octree.voxel_size,
            "synthesised": int(np.count_nonzero(model.synthesised)),
            "nodes": int(octree.num_nodes), "views": num_views, "directions": conf.sampling.directions.num_directions,
            "tile": conf.sampling.tile, "slots": model.num_slots, "pages": len(model.pages),
            "rank_histogram": {str(r): int(c) for r, c in enumerate(self.ranks[:last + 1])},
            "mean_rank": float((self.ranks * np.arange(len(self.ranks))).sum() / max(1, self.ranks.sum())),
            "bytes": {"raw_samples": raw_bytes, "model": int(nbytes["total"]), **{k: int(v) for k, v in nbytes.items()}},
            "compression_ratio": raw_bytes / max(1, nbytes["total"]),
            "psnr_measured_on": f"every {conf.error_stride}th billboard" if conf.error_stride > 1 else "every billboard",
            "psnr": {"decoded_rgba_db": _psnr_db(s.get("sq_err_decoded", 0), int(s.get("values", 0))),
                     "decoded_rgb_opaque_db": _psnr_db(s.get("sq_err_decoded_rgb", 0), int(s.get("opaque_rgb_values", 0))),
                     "pca_rgba_db": _psnr_db(s.get("sq_err_pca", 0), int(s.get("values", 0))),
                     "pca_rgb_opaque_db": _psnr_db(s.get("sq_err_pca_rgb", 0), int(s.get("opaque_rgb_values", 0)))},
            "worker_seconds": {"sampling_s": s.get("sampling_s", 0.0), "pca_s": s.get("pca_s", 0.0),
                               "quantize_s": s.get("quantize_s", 0.0)},
            "sampling": self.sampling,
        }
